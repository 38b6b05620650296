"""Random dynamic scenes for the paper's Table I (sec. IV-B), seeded and reproducible.

How the paper's text maps to the generator (units mm, rad, s):

- "radii controlled by (A + B sin(t)) mm, A in 30-50 mm, B in 10-20 mm":
  A ~ U[30, 50], B ~ U[10, 20], omega = 1 rad/s, phase 0.
- "move linearly between the start and target points, covering a trajectory
  length of 50-100 mm, influenced by sin or cos, average speed under 15 mm/s":
  each centre moves on a straight segment [a, b] of length L ~ U[50, 100]
  (its *travel*: the extent of the motion), driven by a profile drawn at
  random from the scene's ``cos`` (a -> b -> a, ``centre = a, to = b``) and
  ``sin`` (oscillation about the midpoint m, ``centre = m, to = b``). Both
  cover 2 L per period, so the mean speed is L / D (cos) or 2 L / (4 D')
  with D' the sin quarter period; v ~ U[5, 15) mm/s sets D = L / v (cos) and
  D' = L / (2 v) (sin). The midpoint m sits at a fraction f ~ U[0.2, 0.8] of
  the straight segment from the start tip to the goal tip, offset sideways by
  rho ~ U[0, A] in a random direction, so the obstacle crosses the straight
  path at some time; the motion axis is the start -> goal direction tilted
  by a random angle up to 30 degrees.
- "time is discretised into steps of 1 s": crtraj's planners and checks work
  in continuous time (swept capsules), so there is no scene time step.

Start and goal (the paper does not say how it drew them):

- The start configuration is drawn uniformly from the robot's configuration
  box and kept when it is within every limit and its tip lies in the tip box
  (default x, y in [-130, 130], z in [150, 450] mm: inside the paper's
  300 x 300 x 500 mm search space). The goal tip is the tip of a second such
  configuration (the *goal witness*) at least `min_tip_distance` (150 mm)
  from the start tip.
- Screens that make a scene a fair query rather than an impossible one: the
  start body keeps the safety distance plus the disc radius from every
  obstacle over the first time step (the robot cannot move away faster),
  the goal tip keeps that distance plus `goal_margin` from everything every
  obstacle ever sweeps (so safe goal configurations can exist at any arrival
  time), and the goal witness's body is clear at t = 0. An obstacle that
  fails a screen is redrawn; after `max_attempts` draws the start and goal
  are redrawn too.

Every scenario is drawn from its own ``numpy.random.Generator`` seeded with
``(seed, obstacle count, index)``, so any one of them can be regenerated on
its own, in any process, in any order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_SEED, MAX_TIME, Table, check_vec
from crtraj.core.options import Options, option
from crtraj.model.kinematics import Model
from crtraj.world.margin import DEFAULT_SAFETY_DISTANCE
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import MAX_OBSTACLES, Scene

# Most start/goal draws of one scenario (default 200), and the largest scenario
# index (bench runs at most a few hundred per obstacle count).
MAX_ATTEMPTS = 100_000
MAX_INDEX = 1_000_000

# Backbone points used by the screens: 128 points put < 3.2 mm of arc between
# points on the 400 mm default robot. Every body point lies within half that
# spacing (arc length >= distance) of a screened point, so the screens demand
# that much clearance on top (`slack` in `_screens`): the continuous body, not
# only the points, then keeps the safety distance.
_SCREEN_POINTS = 128
# Configurations drawn per batch when rejection-sampling start/goal poses.
_BATCH = 256


def _range(name: str, v: Any, lo_ok: float = 0.0) -> tuple[float, float]:
    """A [low, high] pair of finite numbers with lo_ok <= low <= high."""
    a, b = check_vec(v, name, 2)
    if not lo_ok <= a <= b:
        raise InputError(f"{name}: expected finite [low, high] with {lo_ok:g} <= low <= high, got {[a, b]!r}")
    return a, b


# [low, high] ranges and the tip box corners: read as lists, checked in `ScenarioOptions._check`
_RANGES = ("radius_mean", "radius_amplitude", "travel", "mean_speed", "fraction")
_BOX = ("tip_box_lo", "tip_box_hi")


@dataclass(frozen=True)
class ScenarioOptions(Options):
    """Bounds of the random scenes, the ``[scenarios]`` section; the defaults are the paper's (module docstring).

    radius_mean, radius_amplitude: ranges of A and B (mm). omega: radius
    frequency (rad/s). travel: range of the centre's motion extent L (mm).
    mean_speed: range of the centre's mean speed (mm/s; the upper end is
    excluded). fraction: where along the start -> goal tip segment the motion
    is centred. max_tilt: largest angle between the motion axis and the
    start -> goal direction (rad). min_tip_distance: start to goal tip (mm).
    tip_box_lo/hi: box the start and goal tips are drawn in (mm).
    safety_distance: the scene's D_sf (mm).
    start_window: time the start body must stay clear (s). goal_margin:
    extra clearance of the goal tip (mm). max_attempts: obstacle draws before
    the start and goal are redrawn.
    """

    SECTION: ClassVar[str] = "scenarios"

    seed: int = option(0, ge=0, le=MAX_SEED)
    radius_mean: tuple[float, float] = option((30.0, 50.0), read=False)
    radius_amplitude: tuple[float, float] = option((10.0, 20.0), read=False)
    omega: float = option(1.0, ge=0.0)
    travel: tuple[float, float] = option((50.0, 100.0), read=False)
    mean_speed: tuple[float, float] = option((5.0, 15.0), read=False)
    fraction: tuple[float, float] = option((0.2, 0.8), read=False)
    max_tilt: float = option(math.radians(30.0), ge=0.0)
    min_tip_distance: float = option(150.0, ge=0.0)
    tip_box_lo: tuple[float, float, float] = option((-130.0, -130.0, 150.0), read=False)
    tip_box_hi: tuple[float, float, float] = option((130.0, 130.0, 450.0), read=False)
    safety_distance: float = option(DEFAULT_SAFETY_DISTANCE, ge=0.0)
    start_window: float = option(1.0, gt=0.0, le=MAX_TIME)
    goal_margin: float = option(5.0, ge=0.0)
    max_attempts: int = option(200, ge=1, le=MAX_ATTEMPTS)

    def _check(self) -> None:
        # numpy integers pass the base check; store Python ints so that to_dict gives JSON data
        object.__setattr__(self, "seed", int(self.seed))
        object.__setattr__(self, "max_attempts", int(self.max_attempts))
        for key in _RANGES:
            object.__setattr__(self, key, _range(f"scenarios.{key}", getattr(self, key)))
        if self.radius_amplitude[1] > self.radius_mean[0]:
            raise InputError(
                f"scenarios.radius_amplitude: largest B {self.radius_amplitude[1]:g} mm exceeds smallest A "
                f"{self.radius_mean[0]:g} mm (the radius would go negative)"
            )
        if not self.mean_speed[0] > 0:
            raise InputError(f"scenarios.mean_speed: low must be > 0 mm/s, got {self.mean_speed[0]:g}")
        if self.fraction[1] > 1.0:
            raise InputError(f"scenarios.fraction: must lie within [0, 1], got {list(self.fraction)}")
        lo, hi = (check_vec(getattr(self, key), f"scenarios.{key}", 3, limit=MAX_LENGTH) for key in _BOX)
        if any(not a < b for a, b in zip(lo, hi, strict=True)):
            raise InputError(
                f"scenarios.tip_box_lo: must be below tip_box_hi on every axis, got lo {list(lo)}, hi {list(hi)}"
            )
        object.__setattr__(self, "tip_box_lo", lo)
        object.__setattr__(self, "tip_box_hi", hi)

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        if t.has("time_step"):
            t.raw("time_step")
            raise t.error("time_step", "no longer supported (it had no effect); remove it")
        defaults = {f.name: f.default for f in fields(cls)}
        return {key: t.vec(key, len(defaults[key]), defaults[key]) for key in (*_RANGES, *_BOX)}


@dataclass(frozen=True, eq=False)
class Scenario:
    """One planning query: a scene, a start configuration and a goal tip.

    n_obstacles, index, seed identify it (see `ScenarioGenerator.generate`).
    start: start configuration x (nx,). start_tip, goal: tips (3,) in mm.
    goal_config: the configuration the goal tip was drawn from (a witness
    that the goal is reachable, clear at t = 0; planners may end elsewhere).
    attempts: start/goal draws the generator needed.
    """

    n_obstacles: int
    index: int
    seed: int
    scene: Scene
    start: np.ndarray
    start_tip: np.ndarray
    goal: np.ndarray
    goal_config: np.ndarray
    attempts: int = 1

    @property
    def key(self) -> tuple[int, int]:
        """(obstacle count, index)."""
        return (self.n_obstacles, self.index)

    def to_dict(self) -> dict[str, Any]:
        """Plain data (round-trips through `from_dict`)."""
        return {
            "n_obstacles": self.n_obstacles,
            "index": self.index,
            "seed": self.seed,
            "scene": self.scene.to_dict(),
            "start_config": [float(v) for v in self.start],
            "start_tip": [float(v) for v in self.start_tip],
            "goal_tip": [float(v) for v in self.goal],
            "goal_config": [float(v) for v in self.goal_config],
            "attempts": self.attempts,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Scenario:
        t = Table(d, "scenario")
        out = cls(
            n_obstacles=t.int("n_obstacles", ge=0, le=MAX_OBSTACLES),
            index=t.int("index", ge=0, le=MAX_INDEX),
            seed=t.int("seed", ge=0, le=MAX_SEED),
            scene=Scene.from_table(Table(t.raw("scene"), "scenario.scene")),
            start=np.array(t.vec("start_config", limit=MAX_LENGTH)),
            start_tip=np.array(t.vec("start_tip", 3, limit=MAX_LENGTH)),
            goal=np.array(t.vec("goal_tip", 3, limit=MAX_LENGTH)),
            goal_config=np.array(t.vec("goal_config", limit=MAX_LENGTH)),
            attempts=t.int("attempts", 1, ge=1, le=MAX_ATTEMPTS),
        )
        t.finish()
        if out.scene.n_obstacles != out.n_obstacles:
            raise InputError(
                f"scenario.n_obstacles: {out.n_obstacles} but the scene has {out.scene.n_obstacles} obstacles"
            )
        return out


def _perpendicular(rng: np.random.Generator, e: np.ndarray) -> np.ndarray:
    """A random unit vector perpendicular to the unit vector e."""
    while True:
        v = rng.normal(size=3)
        v -= v.dot(e) * e
        n = np.linalg.norm(v)
        if n > 1e-6:
            return v / n


class ScenarioGenerator:
    """Draws the Table I scenarios for one robot (module docstring lists every rule)."""

    def __init__(self, model: Model, options: ScenarioOptions | None = None) -> None:
        self.model = model
        self.robot = model.robot
        self.options = options or ScenarioOptions()
        self._box = self.robot.config_box()

    # ---------------------------------------------------------------- poses
    def _sample_configs(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A batch of configurations within limits whose tips lie in the tip box: (X, tips)."""
        o = self.options
        lo, hi = self._box
        lo_t, hi_t = np.array(o.tip_box_lo), np.array(o.tip_box_hi)
        for _ in range(10_000):
            X = rng.uniform(lo, hi, size=(_BATCH, len(lo)))
            X = X[self.robot.limit_violation(X) <= 0.0]
            if not len(X):
                continue
            tips = self.model.tip_position(X)
            keep = np.all((tips >= lo_t) & (tips <= hi_t), axis=1)
            if keep.any():
                return X[keep], tips[keep]
        raise InputError("tip_box: no configuration of the robot puts its tip in the tip box")

    def _start_goal(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        o = self.options
        X, tips = self._sample_configs(rng)
        xs, ps = X[0], tips[0]
        for _ in range(10_000):
            far = np.linalg.norm(tips - ps, axis=1) >= o.min_tip_distance
            if far.any():
                i = int(np.argmax(far))
                return xs, ps, X[i], tips[i]
            X, tips = self._sample_configs(rng)
        raise InputError(f"min_tip_distance: no goal tip {o.min_tip_distance:g} mm from the start in the tip box")

    # ------------------------------------------------------------ obstacles
    def _obstacle(self, rng: np.random.Generator, ps: np.ndarray, pg: np.ndarray, k: int) -> Obstacle:
        o = self.options
        seg = pg - ps
        e = seg / np.linalg.norm(seg)
        A = rng.uniform(*o.radius_mean)
        B = rng.uniform(*o.radius_amplitude)
        L = rng.uniform(*o.travel)
        v = rng.uniform(*o.mean_speed)
        v = min(v, np.nextafter(o.mean_speed[1], 0.0)) if o.mean_speed[1] > o.mean_speed[0] else v
        mid = ps + rng.uniform(*o.fraction) * seg + rng.uniform(0.0, A) * _perpendicular(rng, e)
        tilt = rng.uniform(0.0, o.max_tilt)
        axis = math.cos(tilt) * e + math.sin(tilt) * _perpendicular(rng, e)
        if rng.random() < 0.5:
            profile = "cos"
            center = mid - 0.5 * L * axis
            duration = L / v
        else:
            profile = "sin"
            center = mid
            duration = L / (2.0 * v)
        to = center + (L if profile == "cos" else 0.5 * L) * axis
        return Obstacle(
            center=(float(center[0]), float(center[1]), float(center[2])),
            radius=float(A),
            amplitude=float(B),
            omega=float(o.omega),
            phase=0.0,
            to=(float(to[0]), float(to[1]), float(to[2])),
            duration=float(duration),
            profile=profile,
            name=f"obs{k}",
        )

    def _screens(self, ob: Obstacle, xs: np.ndarray, pg: np.ndarray, xg: np.ndarray) -> bool:
        """True when one obstacle passes every screen of the module docstring."""
        o = self.options
        scene = Scene(obstacles=(ob,), safety_distance=o.safety_distance)
        m = self.model
        slack = self.robot.total_length / (2.0 * (_SCREEN_POINTS - 1))  # mm, see _SCREEN_POINTS
        if float(scene.clearance_over(m, xs, 0.0, o.start_window, n_points=_SCREEN_POINTS)) < slack:
            return False
        # a window this long covers every phase of the radius and of either profile
        t_all = 4.0 * ob.duration + 2.0 * math.pi / max(ob.omega, 1e-9) + 1.0
        inflate = self.robot.body_radius + o.goal_margin
        if float(scene.clearance_points_over(pg[None, :], 0.0, t_all, inflate=inflate)) < 0.0:
            return False
        return float(scene.clearance(m, xg, 0.0, n_points=_SCREEN_POINTS)) >= slack

    # ----------------------------------------------------------------- API
    def generate(self, n_obstacles: int, index: int) -> Scenario:
        """Scenario number `index` with `n_obstacles` obstacles (deterministic for the options' seed)."""
        if isinstance(n_obstacles, bool) or not isinstance(n_obstacles, (int, np.integer)) or n_obstacles < 0:
            raise InputError(f"n_obstacles: must be an integer >= 0, got {n_obstacles!r}")
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
            raise InputError(f"index: must be an integer >= 0, got {index!r}")
        o = self.options
        rng = np.random.default_rng([int(o.seed), int(n_obstacles), int(index)])
        attempts = 0
        while True:
            attempts += 1
            if attempts > 1000:
                raise InputError(
                    f"scenarios: could not place {n_obstacles} obstacles after 1000 start/goal draws; "
                    "loosen the bounds (tip box, goal margin, start window)"
                )
            xs, ps, xg, pg = self._start_goal(rng)
            obstacles: list[Obstacle] = []
            for k in range(int(n_obstacles)):
                for _ in range(o.max_attempts):
                    ob = self._obstacle(rng, ps, pg, k)
                    if self._screens(ob, xs, pg, xg):
                        obstacles.append(ob)
                        break
                else:
                    break
            if len(obstacles) == n_obstacles:
                break
        scene = Scene(obstacles=tuple(obstacles), safety_distance=o.safety_distance)
        return Scenario(
            n_obstacles=int(n_obstacles),
            index=int(index),
            seed=int(o.seed),
            scene=scene,
            start=xs.copy(),
            start_tip=ps.copy(),
            goal=pg.copy(),
            goal_config=xg.copy(),
            attempts=attempts,
        )

    def generate_all(self, counts: tuple[int, ...], n_scenarios: int) -> list[Scenario]:
        """Every scenario of a table: for each count, indices 0 .. n_scenarios - 1."""
        return [self.generate(c, i) for c in counts for i in range(n_scenarios)]
