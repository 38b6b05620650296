"""The scene: obstacles over time, the safety distance D_sf, the workspace, and clearance to them.

A `Scene` holds `crtraj.world.obstacle.Obstacle` s (plain data, their time
functions are documented there) and evaluates all of them at once: centres
and radii at given times, their exact ranges and swept capsules over an
interval, and the robot's clearance.

Clearance of a point p is ``|p - c(t)| - R(t) - inflate - D_sf``: positive
means the point keeps the safety distance D_sf from the surface (with the
robot's disc radius as `inflate`; see `crtraj.world.margin`).

Time: `Scene.time_origin` is added to every time given to a scene, so
``scene.with_time_shift(dt)`` is the same scene seen ``dt`` seconds later
(the receding-horizon replanner restarts its clock at zero).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_TIME, Table
from crtraj.world import margin, packing
from crtraj.world.geometry import MovingShape, shape_from_table, shape_to_dict
from crtraj.world.geometry import shape_clearance as _shape_clearance
from crtraj.world.obstacle import MAX_COORDINATE, PROFILE_CODE, Obstacle, sin_range

# The paper's search space: 300 x 300 x 500 mm centred on the base axis. It
# stands on the base's home plane z = 0 and reaches 500 mm up, which holds the
# straight 400 mm cdsr2 at full base extension (z = +100) and every point of
# the paper's simulations (tip heights 170..390 mm, spheres 195..395 mm).
DEFAULT_WORKSPACE = ((-150.0, -150.0, 0.0), (150.0, 150.0, 500.0))

# Most obstacles a scene may have: every solver carries one slot per obstacle
# (the paper's scenes have at most 7).
MAX_OBSTACLES = 100


def _with_shapes(scene: Scene, p: np.ndarray, t0: Any, t1: Any, inflate: float, out: np.ndarray) -> np.ndarray:
    """`out` lowered to the scene's shapes' clearance of points p (..., P, 3) over [t0, t1] (s; scalars or
    broadcastable to the leading dims): ``lower_bound - inflate - D_sf`` (`crtraj.world.geometry`)."""
    if not scene.shapes:
        return out
    t0 = scene._abs_time(t0, "t0")
    t1 = scene._abs_time(t1, "t1")
    d = _shape_clearance(scene.shapes, p, t0, t1)
    return np.minimum(out, margin.clearance(d, scene.safety_distance, inflate))


@dataclass(frozen=True)
class Scene:
    """Obstacles, safety distance D_sf (mm) and workspace box (mm).

    `obstacles` are the moving, breathing spheres every solver packs as slots; `shapes` are obstacles of
    other shapes (`crtraj.world.geometry.MovingShape`: boxes, capsules, cylinders, half spaces, meshes,
    point clouds), which the clearance functions below include through the distance interface.
    Read from a problem file's ``[scene]`` table with `Scene.from_table`.
    """

    obstacles: tuple[Obstacle, ...] = ()
    safety_distance: float = margin.DEFAULT_SAFETY_DISTANCE
    workspace_lo: tuple[float, float, float] = DEFAULT_WORKSPACE[0]
    workspace_hi: tuple[float, float, float] = DEFAULT_WORKSPACE[1]
    time_origin: float = 0.0
    shapes: tuple[MovingShape, ...] = ()
    _arr: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)
    # the one motion profile code every obstacle has, -1 when mixed or none (`_progress_of` skips the others)
    _profile: int = field(init=False, repr=False, compare=False)
    # every centre fixed (linear profile, zero displacement, no -0.0 coordinate): c0 + s d is c0 bit for bit
    # (s is finite, d is +0.0), so the centre formulas need no progress at all
    _static: bool = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        for o in self.obstacles:
            if not isinstance(o, Obstacle):
                raise InputError(f"scene.obstacle: expected Obstacle objects, got {type(o).__name__}")
        object.__setattr__(self, "shapes", tuple(self.shapes))
        for o in self.shapes:
            if not isinstance(o, MovingShape):
                raise InputError(f"scene.shape: expected MovingShape objects, got {type(o).__name__}")
        if not (math.isfinite(self.safety_distance) and self.safety_distance >= 0):
            raise InputError(f"scene.safety_distance: must be >= 0 mm, got {self.safety_distance}")
        if not math.isfinite(self.time_origin):
            raise InputError(f"scene.time_origin: must be finite, got {self.time_origin}")
        lo = tuple(float(v) for v in self.workspace_lo)
        hi = tuple(float(v) for v in self.workspace_hi)
        if len(lo) != 3 or len(hi) != 3 or not all(math.isfinite(v) for v in lo + hi):
            raise InputError("scene.workspace: lo and hi must be 3 finite numbers each (mm)")
        if any(a >= b for a, b in zip(lo, hi, strict=True)):
            raise InputError(f"scene.workspace: lo must be below hi on every axis, got lo {list(lo)}, hi {list(hi)}")
        object.__setattr__(self, "workspace_lo", lo)
        object.__setattr__(self, "workspace_hi", hi)
        obs = self.obstacles
        arr = {
            "c0": np.array([o.center for o in obs], dtype=float).reshape(-1, 3),
            "d": np.array([o.displacement for o in obs], dtype=float).reshape(-1, 3),
            "dur": np.array([o.duration for o in obs], dtype=float),
            "code": np.array([PROFILE_CODE[o.profile] for o in obs], dtype=int),
            "A": np.array([o.radius for o in obs], dtype=float),
            "B": np.array([o.amplitude for o in obs], dtype=float),
            "w": np.array([o.omega for o in obs], dtype=float),
            "p": np.array([o.phase for o in obs], dtype=float),
        }
        # the same fields as rows of numbers (M, 12) for compiled code (`motion_table`): built once, not per call
        cols = (arr["c0"], arr["d"], arr["dur"][:, None], arr["code"][:, None].astype(float))
        cols += tuple(arr[k][:, None] for k in ("A", "B", "w", "p"))
        arr["table"] = np.ascontiguousarray(np.concatenate(cols, axis=1))
        # the swept sphere's centre of a fixed obstacle, in `swept_spheres`' own arithmetic
        arr["mid0"] = 0.5 * (arr["c0"] + arr["c0"])
        for v in arr.values():
            v.setflags(write=False)
        object.__setattr__(self, "_arr", arr)
        codes = set(arr["code"].tolist())
        object.__setattr__(self, "_profile", codes.pop() if len(codes) == 1 else -1)
        c0, d = arr["c0"], arr["d"]
        fixed = not (d != 0.0).any() and not ((c0 == 0.0) & np.signbit(c0)).any()
        object.__setattr__(self, "_static", fixed and self._profile == 0)

    # ------------------------------------------------------------- properties
    @property
    def n_obstacles(self) -> int:
        """The number of sphere obstacles (the solvers' slots); `shapes` are counted by `n_shapes`."""
        return len(self.obstacles)

    @property
    def n_shapes(self) -> int:
        """The number of obstacles of other shapes (`shapes`)."""
        return len(self.shapes)

    @property
    def has_obstacles(self) -> bool:
        """True when the scene has a sphere or a shape to keep D_sf from."""
        return bool(self.obstacles) or bool(self.shapes)

    @property
    def shapes_static(self) -> bool:
        """True when no shape moves or breathes."""
        return all(s.static for s in self.shapes)

    @property
    def workspace(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo (3,), hi (3,)) corners of the workspace box (mm)."""
        return np.array(self.workspace_lo), np.array(self.workspace_hi)

    def in_workspace(self, points: Any) -> np.ndarray:
        """True where points (..., 3) lie inside the workspace box (bool array (...,))."""
        p = np.asarray(points, dtype=float)
        lo, hi = self.workspace
        return np.all((p >= lo) & (p <= hi), axis=-1)

    def speed_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Per obstacle (max |dc/dt| (mm/s), max |dR/dt| (mm/s)), each (M,)."""
        return (
            np.array([o.center_speed_max for o in self.obstacles], dtype=float),
            np.array([o.radius_rate_max for o in self.obstacles], dtype=float),
        )

    # ------------------------------------------------------------------ state
    def _progress(self, tt: np.ndarray) -> np.ndarray:
        """Motion progress s (S+(M,)) at absolute times tt (S+(1,))."""
        a = self._arr
        dur = a["dur"]
        kind = self._profile
        # one profile for all: only its formula (the selection below would copy exactly these values)
        if kind == 0:
            return np.clip(tt / dur, 0.0, 1.0)
        if kind == 1:
            return np.sin(0.5 * np.pi * tt / dur)
        if kind == 2:
            return 0.5 * (1.0 - np.cos(np.pi * tt / dur))
        lin = np.clip(tt / dur, 0.0, 1.0)
        sin_p = np.sin(0.5 * np.pi * tt / dur)
        cos_p = 0.5 * (1.0 - np.cos(np.pi * tt / dur))
        return np.where(a["code"] == 0, lin, np.where(a["code"] == 1, sin_p, cos_p))

    def _abs_time(self, t: Any, name: str = "t") -> np.ndarray:
        tt = np.asarray(t, dtype=float)
        if np.count_nonzero(np.isfinite(tt)) != tt.size:  # "all finite", at a fraction of `.all()`'s overhead
            raise InputError(f"{name}: contains NaN or infinity")
        return tt + self.time_origin

    def _abs_times(self, t0: Any, t1: Any) -> tuple[np.ndarray, np.ndarray]:
        """Absolute interval ends (S+(1,)) of [t0, t1] (s), each checked once."""
        return self._abs_time(t0, "t0")[..., None], self._abs_time(t1, "t1")[..., None]

    def _fixed_centers(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """A fresh (shape + (3,)) array of a static scene's centres `key` ("c0" or "mid0")."""
        return np.broadcast_to(self._arr[key], (*shape, 3)).copy()

    def states(self, t: Any) -> tuple[np.ndarray, np.ndarray]:
        """Obstacle centres and radii (mm) at time(s) t (s).

        Scalar t -> ((M, 3), (M,)); t of shape S -> (S + (M, 3), S + (M,)).
        """
        tt = self._abs_time(t)[..., None]
        a = self._arr
        radii = a["A"] + a["B"] * np.sin(a["w"] * tt + a["p"])
        if self._static:
            return self._fixed_centers("c0", radii.shape), radii
        s = self._progress(tt)
        centers = a["c0"] + s[..., None] * a["d"]
        return centers, radii

    def radius_range(self, t0: Any, t1: Any) -> tuple[np.ndarray, np.ndarray]:
        """Exact (min, max) radius of each obstacle over [t0, t1] (mm): shapes S + (M,)."""
        return self._radius_range(*self._abs_times(t0, t1))

    def _radius_range(self, tt0: np.ndarray, tt1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`radius_range` at checked absolute times."""
        a = self._arr
        lo, hi = sin_range(a["w"] * tt0 + a["p"], a["w"] * tt1 + a["p"])
        B = a["B"]
        Blo, Bhi = B * lo, B * hi
        return a["A"] + np.minimum(Blo, Bhi), a["A"] + np.maximum(Blo, Bhi)

    def progress_range(self, t0: Any, t1: Any) -> tuple[np.ndarray, np.ndarray]:
        """Exact (min, max) of the motion progress s over [t0, t1]: shapes S + (M,)."""
        return self._progress_range(*self._abs_times(t0, t1))

    def _progress_range(self, tt0: np.ndarray, tt1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`progress_range` at checked absolute times."""
        a = self._arr
        ta, tb = np.minimum(tt0, tt1), np.maximum(tt0, tt1)
        dur = a["dur"]
        kind = self._profile
        # one profile for all: only its formula (the selection below would copy exactly these values)
        if kind == 0:
            return np.clip(ta / dur, 0.0, 1.0), np.clip(tb / dur, 0.0, 1.0)
        if kind == 1:
            return sin_range(0.5 * np.pi * ta / dur, 0.5 * np.pi * tb / dur)
        if kind == 2:
            clo, chi = sin_range(np.pi * ta / dur + np.pi / 2, np.pi * tb / dur + np.pi / 2)
            return 0.5 * (1.0 - chi), 0.5 * (1.0 - clo)
        lin0, lin1 = np.clip(ta / dur, 0.0, 1.0), np.clip(tb / dur, 0.0, 1.0)  # monotone
        slo, shi = sin_range(0.5 * np.pi * ta / dur, 0.5 * np.pi * tb / dur)
        # (1 - cos th)/2 = (1 - sin(th + pi/2))/2
        clo, chi = sin_range(np.pi * ta / dur + np.pi / 2, np.pi * tb / dur + np.pi / 2)
        code = a["code"]
        smin = np.where(code == 0, lin0, np.where(code == 1, slo, 0.5 * (1.0 - chi)))
        smax = np.where(code == 0, lin1, np.where(code == 1, shi, 0.5 * (1.0 - clo)))
        return smin, smax

    def swept(self, t0: Any, t1: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The exact volume each obstacle sweeps over [t0, t1], as capsules.

        Returns (a, b, r): segment ends a, b (S + (M, 3), mm) the centre moves
        along, and the largest radius r (S + (M,), mm) over the interval.
        """
        tt0, tt1 = self._abs_times(t0, t1)
        _, rmax = self._radius_range(tt0, tt1)
        if self._static:
            return self._fixed_centers("c0", rmax.shape), self._fixed_centers("c0", rmax.shape), rmax
        smin, smax = self._progress_range(tt0, tt1)
        a = self._arr
        return a["c0"] + smin[..., None] * a["d"], a["c0"] + smax[..., None] * a["d"], rmax

    def swept_spheres(self, t0: Any, t1: Any) -> tuple[np.ndarray, np.ndarray]:
        """Spheres that contain each obstacle over the whole of [t0, t1]: centres S + (M, 3) mm at the
        middle of the `swept` capsule's segment, radii S + (M,) mm its largest radius plus half the
        segment's length. The length is summed x, y, z in that order, an order the compiled edge
        check (`crtraj.planning.validity._compiled`) repeats, so both give the same numbers bit for bit.
        """
        if self._static:
            # a = b = c0 in `swept`: the length below is +0.0 and the centre 0.5 (c0 + c0)
            _, rmax = self._radius_range(*self._abs_times(t0, t1))
            return self._fixed_centers("mid0", rmax.shape), rmax + 0.0
        a, b, rmax = self.swept(t0, t1)
        d = b - a
        length = np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])
        return 0.5 * (a + b), rmax + 0.5 * length

    def motion_table(self) -> np.ndarray:
        """Every obstacle's motion and breathing as rows of numbers (M, 12), for compiled code:
        start centre (3) mm, displacement (3) mm, duration s, profile code (0 linear, 1 sin, 2 cos),
        mean radius A mm, amplitude B mm, angular rate w rad/s, phase rad (`Obstacle`'s fields). Read-only."""
        return self._arr["table"]

    # -------------------------------------------------------------- clearance
    def _points(self, points: Any) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        if p.ndim < 2 or p.shape[-1] != 3:
            raise InputError(f"points: expected shape (..., P, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise InputError("points: contains NaN or infinity")
        return p

    def clearance_points(self, points: Any, t: Any, inflate: float = 0.0) -> np.ndarray:
        """min over points and obstacles of ``|p - c(t)| - R(t) - inflate - D_sf`` (mm).

        points: (..., P, 3) mm. t: scalar or broadcastable to the leading dims
        ``...``. Returns (...,); +inf when the scene has no obstacles.
        """
        p = self._points(points)
        lead = p.shape[:-2]
        if self.n_obstacles == 0:
            return _with_shapes(self, p, t, t, inflate, np.full(lead, np.inf))
        centers, radii = self.states(t)  # S+(M,3), S+(M,)
        out = np.full(np.broadcast_shapes(lead, centers.shape[:-2]), np.inf)
        # a loop over obstacles (a handful) keeps memory at (..., P) per pass
        for i in range(self.n_obstacles):
            c = centers[..., i, :][..., None, :]  # S+(1,3)
            dist = np.linalg.norm(p - c, axis=-1)  # broadcast(...,P)
            np.minimum(out, dist.min(axis=-1) - radii[..., i], out=out)
        return _with_shapes(self, p, t, t, inflate, margin.clearance(out, self.safety_distance, inflate))

    def clearance_points_over(self, points: Any, t0: Any, t1: Any, inflate: float = 0.0) -> np.ndarray:
        """Conservative clearance (mm) of fixed points over the whole interval [t0, t1].

        Bound: each centre moves along a straight line, so over [t0, t1] it
        stays on the segment between its extreme progress values (computed
        exactly from the profile), and the radius stays below its exact
        maximum over the interval (from the sine). The obstacle therefore
        stays inside the capsule of that segment and radius, and
        ``dist(p, segment) - R_max - inflate - D_sf`` bounds the clearance from
        below at every instant. It is never larger than the point checks at
        t0 and t1 (the paper's check), and equals them when the obstacle is
        at rest and at its largest radius. Returns (...,); +inf without obstacles.
        """
        p = self._points(points)
        lead = p.shape[:-2]
        if self.n_obstacles == 0:
            return _with_shapes(self, p, t0, t1, inflate, np.full(lead, np.inf))
        a, b, rmax = self.swept(t0, t1)
        out = np.full(np.broadcast_shapes(lead, a.shape[:-2]), np.inf)
        for i in range(self.n_obstacles):
            ai = a[..., i, :][..., None, :]
            ab = b[..., i, :][..., None, :] - ai
            den = np.sum(ab * ab, axis=-1)
            num = np.sum((p - ai) * ab, axis=-1)
            # projection onto the segment; a resting centre (den = 0) projects to a
            u = np.divide(num, den, out=np.zeros(np.broadcast_shapes(num.shape, den.shape)), where=den > 0)
            u = np.clip(u, 0.0, 1.0)
            dist = np.linalg.norm(p - (ai + u[..., None] * ab), axis=-1)
            np.minimum(out, dist.min(axis=-1) - rmax[..., i], out=out)
        bound = margin.clearance(out, self.safety_distance, inflate)
        # mathematically already <= both ends; the min removes rounding doubt
        ends = np.minimum(self.clearance_points(p, t0, inflate), self.clearance_points(p, t1, inflate))
        return _with_shapes(self, p, t0, t1, inflate, np.minimum(bound, ends))

    def clearance(self, model: Any, x: Any, t: Any, n_points: int | None = None) -> np.ndarray:
        """Body clearance (mm) of configuration(s) x at time t: the paper's check.

        Uses ``model.points(x, n_points)`` (default: the robot's collision
        points) inflated by ``model.robot.body_radius``. x (nx,) -> scalar
        array; x (N, nx) -> (N,). Positive: the whole sampled body keeps D_sf.
        """
        pts = model.points(x, n_points)
        return self.clearance_points(pts, t, inflate=model.robot.body_radius)

    def clearance_over(self, model: Any, x: Any, t0: Any, t1: Any, n_points: int | None = None) -> np.ndarray:
        """Conservative body clearance (mm) of fixed configuration(s) x over [t0, t1].

        See `clearance_points_over` for the bound (swept capsule per obstacle).
        """
        pts = model.points(x, n_points)
        return self.clearance_points_over(pts, t0, t1, inflate=model.robot.body_radius)

    # ---------------------------------------------------------------- packing
    def pack(self, t: float, max_obstacles: int) -> np.ndarray:
        """Obstacles at time t as solver slots (`crtraj.world.packing`), shape (packing.WIDTH * max_obstacles,).

        Slot i is ``[cx, cy, cz, R, active]`` (mm, mm, mm, mm, 1) with the
        obstacle's own radius R (not inflated). Slots past `n_obstacles` are
        padding (inert with or without the flag).
        """
        if np.ndim(t) != 0:
            raise InputError(f"t: pack expects one time (s), got shape {np.shape(t)}")
        centers, radii = self.states(float(t))
        return packing.pack(centers, radii, max_obstacles)

    def pack_over(self, t0: float, t1: float, max_obstacles: int) -> np.ndarray:
        """Like `pack`, but each slot is one fixed sphere enclosing the obstacle over [t0, t1].

        Centre: middle of the swept segment; radius: exact max radius plus half
        the segment length. Conservative (encloses the capsule of `swept`).
        """
        centers, radii = self.swept_spheres(float(t0), float(t1))
        return packing.pack(centers, radii, max_obstacles)

    # ---------------------------------------------------------------- helpers
    def with_time_shift(self, dt: float) -> Scene:
        """The same scene with its clock advanced by dt (s): new.states(t) == old.states(t + dt)."""
        return replace(self, time_origin=self.time_origin + float(dt))

    def with_obstacles(self, obstacles: Any) -> Scene:
        """A copy with a different obstacle list (same D_sf, workspace, clock)."""
        return replace(self, obstacles=tuple(obstacles))

    # --------------------------------------------------------------- file I/O
    @classmethod
    def from_table(cls, t: Table) -> Scene:
        """Read ``[scene]``.

        Keys: ``safety_distance`` (mm, default `margin.DEFAULT_SAFETY_DISTANCE` = 5),
        ``workspace = {lo = [x,y,z], hi = [x,y,z]}`` (mm, default the paper's
        300 x 300 x 500 box, x,y in [-150, 150], z in [0, 500]),
        ``time_origin`` (s, default 0), and ``[[scene.obstacle]]`` tables with
        ``center`` (mm), ``radius`` (mm, or ``{mean, amplitude, omega, phase}``),
        optional ``motion = {to, duration | period, profile}`` and ``name``, and ``[[scene.shape]]`` tables
        (`crtraj.world.geometry._table`: box, capsule, cylinder, halfspace, sphere, mesh, points).
        """
        if t.has("time_step"):  # documented once, never used: refuse it rather than ignore it
            t.raw("time_step")
            raise t.error("time_step", "no longer supported (it had no effect); remove it")
        obstacles = tuple(Obstacle.from_table(ot) for ot in t.tables("obstacle", most=MAX_OBSTACLES))
        shapes = tuple(shape_from_table(st) for st in t.tables("shape", most=MAX_OBSTACLES))
        names = [o.name for o in obstacles if o.name] + [s.shape.name for s in shapes if s.shape.name]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise t.error("obstacle", f"duplicate obstacle name {dup!r}")
        lo, hi = DEFAULT_WORKSPACE
        if t.has("workspace"):
            wt = t.table("workspace")
            lo = wt.vec("lo", 3, lo, limit=MAX_COORDINATE)
            hi = wt.vec("hi", 3, hi, limit=MAX_COORDINATE)
            wt.finish()
            bad = [i for i in range(3) if not lo[i] < hi[i]]
            if bad:
                raise wt.error("hi", f"must be above lo on every axis, got lo {list(lo)}, hi {list(hi)}")
        scene = cls(
            obstacles=obstacles,
            safety_distance=t.float("safety_distance", margin.DEFAULT_SAFETY_DISTANCE, ge=0.0, limit=MAX_COORDINATE),
            workspace_lo=(lo[0], lo[1], lo[2]),
            workspace_hi=(hi[0], hi[1], hi[2]),
            time_origin=t.float("time_origin", 0.0, limit=MAX_TIME),
            shapes=shapes,
        )
        t.finish()
        return scene

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the ``[scene]`` schema (round-trips through `from_table`)."""
        d: dict[str, Any] = {
            "safety_distance": self.safety_distance,
            "workspace": {"lo": list(self.workspace_lo), "hi": list(self.workspace_hi)},
        }
        if self.time_origin != 0.0:
            d["time_origin"] = self.time_origin
        d["obstacle"] = [o.to_dict() for o in self.obstacles]
        if self.shapes:
            d["shape"] = [shape_to_dict(s) for s in self.shapes]
        return d
