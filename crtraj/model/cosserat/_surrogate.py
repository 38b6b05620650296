"""The rod's correction to PCC as a fast, differentiable function: a tabulated surrogate of Delta(x).

For a configuration x (the PCC parameters and the base translation z), the Cosserat rod driven in the robot
file's actuation mode with its weight (`crtraj.model.cosserat.RodDrive`) takes a body that PCC does not see.
The rod's shape does not depend on z (the base stage only lifts it), and it depends on the bending only through
the effective bending vectors u_bar_k (`Robot.bending`, rad), so the correction

    Delta(x) = rod(x) - PCC(x)  at the robot's collision points (mm; the last one is the tip)

is a smooth function of the 2 n_segments components of u_bar. It is tabulated once per robot file on a grid
and interpolated by a cubic B-spline (``casadi.bspline``), which is differentiable and can be generated to C
with the rest of a checker.

The grid. Each segment's u_bar_k lies in the disc |u_bar_k| <= theta_max_k (the robot's limit). A square grid
of u_bar would put a quarter of its nodes outside the disc, where the rod coils beyond what the solver resolves,
so each disc is the image of the square [-1, 1]^2 under the elliptical grid mapping (Fong, "Analytical methods
for squaring the disc", 2014): ``u = a sqrt(1 - b^2 / 2)``, ``v = b sqrt(1 - a^2 / 2)`` (times theta_max_k),
smooth, one to one, with a closed-form inverse. The table holds Delta at the nodes of an evenly spaced
``grid`` x ... x ``grid`` lattice of those squares (2 n_segments axes), solved in a snake order so that every
solve warm-starts from a neighbour. The rod's points at the collision points' arc lengths come from its
integration nodes by a cubic spline along the arc (nodes a few mm apart: far below the surrogate's error).

Its error. After the build, ``holdout`` random configurations within the limits (seeded), not on the grid, are
solved fresh and compared with PCC + the surrogate: the largest body error (over all collision points) and tip
error (mm) are stored with the table and are the surrogate's stated bound.

The cache. The table is kept in the build cache's folder (`crtraj.core.build_cache.default_root`, or
``$CRTRAJ_CACHE_DIR``) as an ``.npz`` (read without pickle) beside a JSON manifest holding its key (the robot's
model description, every ``[robot.mechanics]`` value, the build options and the generating sources' hash), the
SHA-256 of the table and the measured error. A changed robot file or mechanics value changes the key, so a
stale table is never found; a table whose bytes, shapes or manifest do not check out is rebuilt.

Units: mm, rad.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import default_root
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_bytes, atomic_write_json, read_json
from crtraj.core.lazy import lazy_module
from crtraj.model.cosserat._drive import PRETENSION, RodDrive
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

# SciPy's interpolate package costs about 0.3 s to import; `crtraj plan` loads this module but builds no surrogate
interpolate = lazy_module("scipy.interpolate")

log = logging.getLogger(__name__)

# Layout of a cache entry: a change makes every old entry foreign (rebuilt).
FORMAT = 1
# Grid nodes per axis: at least 4 for a cubic B-spline; 40^4 nodes would be hours of rod solves.
MIN_GRID, MAX_GRID = 4, 40
MAX_HOLDOUT = 100_000
# The table of a 40^4 grid, 10 points, is 2.3e7 numbers; anything much larger is not ours.
_MAX_TABLE_BYTES = 400 * 1024 * 1024
# The sources whose change changes the table (hashed into the key).
_SOURCES = ("_surrogate.py", "_drive.py", "_statics.py", "_equations.py", "_cables.py", "../kinematics.py")
# The stated bound is the held-out maximum times this: a few hundred held-out configurations find the largest
# error of the table to within tens of percent (measured on cdsr2), so the bound allows half again.
BOUND_FACTOR = 1.5
# Rejection sampling of the held-out configurations: draws per wanted sample before giving up.
_DRAWS = 200


@dataclass(frozen=True)
class SurrogateOptions:
    """How the table is built. grid: nodes per axis (2 n_segments axes, so grid^(2 n_segments) rod solves).
    holdout: random configurations the error is measured on. seed: their seed. pretension: N in every tendon
    at the straight pose (`RodDrive`)."""

    grid: int = 9
    holdout: int = 200
    seed: int = 0
    pretension: float = PRETENSION

    def __post_init__(self) -> None:
        if not MIN_GRID <= int(self.grid) <= MAX_GRID:
            raise InputError(f"surrogate grid: must be in [{MIN_GRID}, {MAX_GRID}] nodes per axis, got {self.grid}")
        if not 1 <= int(self.holdout) <= MAX_HOLDOUT:
            raise InputError(f"surrogate holdout: must be in [1, {MAX_HOLDOUT}], got {self.holdout}")
        if not (math.isfinite(self.pretension) and self.pretension > 0.0):
            raise InputError(f"surrogate pretension: must be a finite number > 0 N, got {self.pretension}")


@dataclass(frozen=True)
class SurrogateError:
    """The surrogate against fresh rod solves on held-out configurations (mm): largest and 95th-percentile
    distance over all collision points (body) and at the tip; samples: how many configurations."""

    body_max: float
    body_p95: float
    tip_max: float
    tip_p95: float
    samples: int

    @property
    def body_bound(self) -> float:
        """The stated bound on the body error (mm): the held-out maximum times `BOUND_FACTOR`."""
        return BOUND_FACTOR * self.body_max

    @property
    def tip_bound(self) -> float:
        """The stated bound on the tip error (mm): the held-out maximum times `BOUND_FACTOR`."""
        return BOUND_FACTOR * self.tip_max

    def text(self) -> str:
        return (
            f"body max {self.body_max:.3f} mm (p95 {self.body_p95:.3f}), tip max {self.tip_max:.3f} mm "
            f"(p95 {self.tip_p95:.3f}) over {self.samples} held-out configurations"
        )


# ----------------------------------------------------------------------------- the disc <-> square map
def square_to_disc(a: Any, b: Any) -> tuple[Any, Any]:
    """The elliptical grid mapping: (a, b) in [-1, 1]^2 to the unit disc (numpy or CasADi)."""
    return a * np.sqrt(1.0 - b * b / 2.0), b * np.sqrt(1.0 - a * a / 2.0)


def disc_to_square(u: Any, v: Any) -> tuple[Any, Any]:
    """The inverse of `square_to_disc` in CasADi (SX/MX/DM): the unit disc to [-1, 1]^2. The square roots'
    arguments are clipped at 0, so a point a little outside the disc maps to the square's edge region."""
    r2 = np.sqrt(2.0) * 2.0
    s, t = 2.0 + u * u - v * v, 2.0 - u * u + v * v
    a = 0.5 * ca.sqrt(ca.fmax(s + r2 * u, 0.0)) - 0.5 * ca.sqrt(ca.fmax(s - r2 * u, 0.0))
    b = 0.5 * ca.sqrt(ca.fmax(t + r2 * v, 0.0)) - 0.5 * ca.sqrt(ca.fmax(t - r2 * v, 0.0))
    return a, b


# ----------------------------------------------------------------------------- the key
def surrogate_key(robot: Robot, mech: Mechanics, options: SurrogateOptions) -> dict[str, Any]:
    """Everything the table depends on: the robot's model description (not its name, description or actuator
    hardware), every mechanics value (the actuation mode and gravity included), the options and the sources."""
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256(b"".join((here / f).read_bytes() for f in _SOURCES)).hexdigest()
    spec = {k: v for k, v in robot.to_dict().items() if k not in ("name", "description", "actuators")}
    return {
        "format": FORMAT,
        "robot": spec,
        "mechanics": mech.to_dict(),
        "options": {"grid": int(options.grid), "holdout": int(options.holdout), "seed": int(options.seed)}
        | {"pretension": float(options.pretension)},
        "sources": digest,
    }


def key_digest(key: dict[str, Any]) -> str:
    """Hex SHA-256 of the canonical JSON of `key` (names the cache entry)."""
    return hashlib.sha256(json.dumps(key, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


# ----------------------------------------------------------------------------- sampling the rod
class RodSampler:
    """The rod of `robot` in its actuation mode, with gravity, sampled at the collision points: `delta` gives
    rod - PCC (P, 3) mm for one bending; `rod_points` the rod's own points."""

    def __init__(self, robot: Robot, mech: Mechanics, pretension: float) -> None:
        self.robot, self.mech = robot, mech
        self.drive = RodDrive(robot, mech, pretension=pretension, gravity=True)
        self.model = Model(robot)
        self.arcs = self.model.arc_positions(self.model.n_points)
        steps = mech.steps
        node_arcs = [np.zeros(1)] + [s.length * np.arange(1, steps + 1) / steps for s in robot.segments]
        offsets = np.cumsum([0.0] + [s.length for s in robot.segments[:-1]])
        self.node_arcs = np.concatenate([node_arcs[0]] + [a + o for a, o in zip(node_arcs[1:], offsets, strict=True)])

    def rod_points(self, x: np.ndarray) -> np.ndarray | None:
        """The rod's points (P, 3) mm at the collision points' arcs for configuration x (world frame); None
        when the solve fails (the solvers already start again from the straight rod when a warm start fails)."""
        s = self.drive.shape_config(x)
        if not s.is_success():
            return None
        return np.asarray(interpolate.CubicSpline(self.node_arcs, s.points, axis=0)(self.arcs))

    def pcc_points(self, x: np.ndarray) -> np.ndarray:
        """PCC's points (P, 3) mm at the collision points, world frame."""
        return np.asarray(self.model.points(x)).reshape(-1, 3)

    def config_of(self, ub: np.ndarray) -> np.ndarray:
        """A configuration (base at z = 0) whose effective bending vectors are ub (n_segments, 2) rad."""
        x = np.zeros(self.robot.nx)
        x[: 2 * self.robot.n_segments] = np.linalg.solve(self.robot.coupling_matrix(), np.ravel(ub))
        return x


def snake(shape: tuple[int, ...]) -> list[tuple[int, ...]]:
    """Every index of `shape`, ordered so that consecutive indices differ by one step along one axis."""
    if len(shape) == 1:
        return [(i,) for i in range(shape[0])]
    inner = snake(shape[1:])
    out: list[tuple[int, ...]] = []
    for i in range(shape[0]):
        out.extend((i, *rest) for rest in (inner if i % 2 == 0 else inner[::-1]))
    return out


def grid_axis(n: int) -> np.ndarray:
    """The grid's nodes along one square axis: n evenly spaced in [-1, 1]."""
    return np.linspace(-1.0, 1.0, int(n))


def bending_at(robot: Robot, square: np.ndarray) -> np.ndarray:
    """Effective bending vectors (n_segments, 2) rad at square coordinates (2 n_segments,) in [-1, 1]."""
    sq = np.asarray(square, dtype=float).reshape(robot.n_segments, 2)
    u, v = square_to_disc(sq[:, 0], sq[:, 1])
    tmax = np.array([s.theta_max for s in robot.segments])
    return np.stack([u, v], axis=1) * tmax[:, None]


def build_table(robot: Robot, mech: Mechanics, options: SurrogateOptions) -> np.ndarray:
    """Delta (grid,) * 2 n_segments + (P, 3) mm at every grid node (the module docstring); `InputError` when a
    rod solve fails at a node (it names the bending)."""
    sampler = RodSampler(robot, mech, options.pretension)
    axis = grid_axis(options.grid)
    shape = (options.grid,) * (2 * robot.n_segments)
    table = np.empty((*shape, sampler.model.n_points, 3))
    order = snake(shape)
    start, report = time.perf_counter(), max(len(order) // 10, 1)
    for i, idx in enumerate(order):
        x = sampler.config_of(bending_at(robot, axis[list(idx)]))
        rod = sampler.rod_points(x)
        if rod is None:
            ub = np.round(robot.bending(x).ravel(), 4).tolist()
            raise InputError(
                f"rod surrogate: the rod's solve failed at bending {ub} rad (actuation {sampler.drive.actuation}); "
                "check [robot.mechanics] (moduli, steps, tolerance, max_iter)"
            )
        table[idx] = rod - sampler.pcc_points(x)
        if (i + 1) % report == 0:
            log.info("rod surrogate: %d of %d grid nodes, %.1f s", i + 1, len(order), time.perf_counter() - start)
    return table


def sample_within_limits(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """n configurations (n, nx), uniform in the configuration box, kept if within the limits."""
    lo, hi = robot.config_box()
    out: list[np.ndarray] = []
    for _ in range(_DRAWS):
        x = rng.uniform(lo, hi, size=(max(n, 16), robot.nx))
        out.extend(x[robot.limit_violation(x) <= 0.0])
        if len(out) >= n:
            return np.array(out[:n])
    raise InputError(f"robot: fewer than {n} of {_DRAWS * max(n, 16)} random configurations are within limits")


# ----------------------------------------------------------------------------- the surrogate
class RodSurrogate:
    """Delta(x) = rod(x) - PCC(x) at the collision points of one robot, interpolated (the module docstring).

    Build or load one with `RodSurrogate.load`; `function` is the CasADi function x (nx,) -> Delta (3, P) mm,
    `delta` and `body` evaluate it in numpy; `error` is the measured bound (None until measured)."""

    def __init__(self, robot: Robot, table: np.ndarray, key: dict[str, Any], error: SurrogateError | None) -> None:
        self.robot, self.table, self.key, self.error = robot, np.asarray(table, dtype=float), key, error
        self.digest = key_digest(key)
        self.n_points = self.table.shape[-2]
        self.function = self._build_function()
        self._model = Model(robot, self.n_points)

    def _build_function(self) -> ca.Function:
        """The cubic B-spline through the table composed with x -> u_bar -> square coordinates. The spline's
        coefficients are fitted axis by axis (not-a-knot, `scipy.interpolate.make_interp_spline`: a tensor
        product of 1-D interpolations), which takes milliseconds where CasADi's own ``interpolant`` fit solves
        one system over the whole grid (45 s for 7^4 nodes); ``casadi.bspline`` then evaluates it."""
        r, dims = self.robot, 2 * self.robot.n_segments
        coef = self.table.reshape(*self.table.shape[:dims], -1)
        knots: list[float] = []
        for ax in range(dims):
            spline = interpolate.make_interp_spline(grid_axis(self.table.shape[0]), coef, k=3, axis=ax)
            coef, knots = spline.c, list(spline.t)
        x = ca.MX.sym("x", r.nx)
        ub = ca.mtimes(ca.DM(r.coupling_matrix()), x[:dims])
        coords = []
        for k, seg in enumerate(r.segments):
            coords += list(disc_to_square(ub[2 * k] / seg.theta_max, ub[2 * k + 1] / seg.theta_max))
        # casadi.bspline takes the coefficients with the output index fastest, then the last axis (C order)
        lut = ca.bspline(
            ca.vertcat(*coords), ca.DM(coef.ravel(order="C")), [knots] * dims, [3] * dims, coef.shape[-1], {}
        )
        return ca.Function("rod_delta", [x], [ca.reshape(lut, 3, self.n_points)], ["x"], ["delta"])

    def delta(self, x: np.ndarray) -> np.ndarray:
        """Delta (P, 3) mm at configuration x (nx,)."""
        return np.asarray(self.function(np.asarray(x, dtype=float))).T

    def body(self, x: np.ndarray) -> np.ndarray:
        """The rod's body by the surrogate: PCC's collision points plus Delta, (P, 3) mm, world frame."""
        return np.asarray(self._model.points(x)).reshape(-1, 3) + self.delta(x)

    def measure(self, mech: Mechanics, options: SurrogateOptions) -> SurrogateError:
        """The error against fresh rod solves on `options.holdout` seeded random configurations within limits."""
        sampler = RodSampler(self.robot, mech, options.pretension)
        xs = sample_within_limits(self.robot, options.holdout, np.random.default_rng(options.seed))
        body, tip = [], []
        for x in xs:
            rod = sampler.rod_points(x)
            if rod is None:
                raise InputError(
                    f"rod surrogate: the rod's solve failed at held-out configuration {np.round(x, 4).tolist()}"
                )
            d = np.linalg.norm(self.body(x) - rod, axis=1)
            body.append(d.max())
            tip.append(d[-1])
        b, t = np.array(body), np.array(tip)
        return SurrogateError(
            float(b.max()), float(np.percentile(b, 95)), float(t.max()), float(np.percentile(t, 95)), len(xs)
        )

    # ------------------------------------------------------------------ the cache
    @classmethod
    def load(
        cls,
        robot: Robot,
        mech: Mechanics | None = None,
        options: SurrogateOptions | None = None,
        *,
        cache_dir: str | Path | None = None,
    ) -> RodSurrogate:
        """The surrogate of `robot` (its ``[robot.mechanics]`` unless `mech`): from the cache when an entry with
        the same key verifies, else built now, measured and stored (the module docstring)."""
        mech = Mechanics.from_robot(robot) if mech is None else mech
        options = SurrogateOptions() if options is None else options
        key = surrogate_key(robot, mech, options)
        store = SurrogateStore(Path(cache_dir) if cache_dir is not None else default_root())
        found = store.read(robot, key)
        if found is not None:
            return found
        start = time.perf_counter()
        table = build_table(robot, mech, options)
        built = time.perf_counter() - start
        sur = cls(robot, table, key, None)
        sur.error = sur.measure(mech, options)
        log.info(
            "rod surrogate of %s: %d nodes in %.1f s; %s", robot.name, table[..., 0, 0].size, built, sur.error.text()
        )
        store.write(sur, built)
        return sur


class SurrogateStore:
    """Surrogate tables in a folder: ``rod_surrogate-<digest>.npz`` and its ``.json`` manifest."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def paths(self, digest: str) -> tuple[Path, Path]:
        stem = f"rod_surrogate-{digest[:24]}"
        return self.root / f"{stem}.npz", self.root / f"{stem}.json"

    def write(self, sur: RodSurrogate, build_seconds: float) -> None:
        """Table first, manifest last (each atomically): a manifest exists only beside its complete table."""
        assert sur.error is not None
        buf = io.BytesIO()
        np.savez(buf, table=sur.table)
        data = buf.getvalue()
        table_path, manifest_path = self.paths(sur.digest)
        self.root.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(table_path, data)
        err = sur.error
        manifest = {
            "key": sur.key,
            "digest": sur.digest,
            "sha256": hashlib.sha256(data).hexdigest(),
            "size": len(data),
            "shape": list(sur.table.shape),
            "error_mm": {"body_max": err.body_max, "body_p95": err.body_p95, "tip_max": err.tip_max}
            | {"tip_p95": err.tip_p95, "samples": err.samples},
            "build_s": build_seconds,
        }
        atomic_write_json(manifest_path, manifest)

    def read(self, robot: Robot, key: dict[str, Any]) -> RodSurrogate | None:
        """The stored surrogate of `key`, or None when there is none or it does not check out (then it is
        rebuilt and overwritten by the caller: never used)."""
        digest = key_digest(key)
        table_path, manifest_path = self.paths(digest)
        if not (table_path.is_file() and manifest_path.is_file()):
            return None
        try:
            man = read_json(manifest_path)
            data = table_path.read_bytes()
            if (
                not isinstance(man, dict)
                or man.get("key") != json.loads(json.dumps(key))
                or len(data) != man.get("size")
                or len(data) > _MAX_TABLE_BYTES
                or hashlib.sha256(data).hexdigest() != man.get("sha256")
            ):
                raise ValueError("manifest, size or checksum")
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                table = np.asarray(z["table"], dtype=float)
            e = man["error_mm"]
            error = SurrogateError(
                *(float(e[k]) for k in ("body_max", "body_p95", "tip_max", "tip_p95")), int(e["samples"])
            )
            if list(table.shape) != man.get("shape") or not np.all(np.isfinite(table)):
                raise ValueError("table shape or values")
        except (InputError, OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("rod surrogate: cache entry %s is unusable (%s); rebuilding it", table_path.name, exc)
            return None
        return RodSurrogate(robot, table, key, error)
