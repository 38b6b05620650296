"""The Cosserat rod as the closed loop's plant: a simulated robot behind the loop's `Device` port.

The loop plans and verifies with PCC; `RodPlant` is the robot it drives. Each verified step's commands
go through the loop's own servo model (`crtraj.control.tracking.ServoModel`: position-controlled
servos), and at the end of every control period the rod's shape at the reached actuator positions is
solved in the robot file's actuation mode (`crtraj.model.cosserat.RodDrive`: commanded cable lengths for
position servos, the default, or fixed tensions; reported as ``actuation``). The loop's measurement is the plant's:
the servos' readback (`measure`), and, as a `TipSensor`, the tip of the rod's shape (with optional
capture noise), which the loop's tip sensing (`crtraj.control.loop._tip_sensing`) corrects the goal with.

Collisions and clearance are judged by the rod's shape: at every control period, the backbone (its
integration nodes, a few mm apart) inflated by the robot's body radius against the obstacles at that
time, ``|p - c(t)| - R(t) - body_radius - D_sf`` (mm), as the loop's own sampled clearance is. A rod solve
that does not converge is never replaced by a guess: `problem` then says so and the loop stops.

Units: mm, N, rad, s.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crtraj.control.executed import limit_fractions
from crtraj.control.ports import Landing
from crtraj.control.tracking import ServoModel
from crtraj.core.errors import InputError
from crtraj.model.cosserat import RodDrive, RodShape
from crtraj.model.rate_limits import RateLimits

log = logging.getLogger(__name__)


@dataclass
class PlantTrace:
    """What the plant did, one row per control period (and t = 0): time (s), actuation q (mm), the rod's
    tip (mm) and its clearance (mm, minus D_sf; NaN where the solve failed)."""

    t: list[float] = field(default_factory=list)
    q: list[np.ndarray] = field(default_factory=list)
    tip: list[np.ndarray] = field(default_factory=list)
    clearance: list[float] = field(default_factory=list)


class RodPlant:
    """A simulated robot whose body is the Cosserat rod (the loop's `Device` and `TipSensor`).

    drive: the `RodDrive` (robot, mechanics, pretension, gravity). scene: the obstacles
    (`crtraj.world.scene.Scene`, the truth the plant is judged against). goal: the task's tip goal (3,)
    mm. tip_noise: standard deviation per axis (mm) of the tip readings; seed: the noise's seed.
    to_plant: the plant's own actuation (mm, in `drive.robot`'s terms) for the loop's actuation q, when
    the loop's robot file differs from the plant's (e.g. a calibrated one: the servo values the loop
    sends, read back through the plant's own actuators); None: the same. Call `attach` with the loop's
    servo model and start actuation before the run.
    """

    def __init__(
        self,
        drive: RodDrive,
        scene: Any,
        goal: np.ndarray,
        *,
        tip_noise: float = 0.0,
        seed: int = 0,
        to_plant: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> None:
        if not 0.0 <= tip_noise <= 100.0:
            raise InputError(f"tip_noise: must be in [0, 100] mm, got {tip_noise}")
        self.drive, self.scene, self.to_plant = drive, scene, to_plant
        self.goal = np.asarray(goal, dtype=float)
        self.body_radius = drive.robot.body_radius
        self._noise, self._rng = float(tip_noise), np.random.default_rng(seed)
        self.servo: ServoModel | None = None
        self.rate_limits: RateLimits | None = None
        self.trace = PlantTrace()
        self._q: np.ndarray | None = None
        self._t = 0.0
        self._last: tuple[np.ndarray, RodShape] | None = None
        self._failure = ""
        self._holds = 0
        self._hold_from: float | None = None  # loop time a held step began (judged when it ends, in `pace`)
        self._estop = ""
        self.solves = 0
        self.solve_time: list[float] = []
        self.periods, self.control_dt = 1, 0.0

    def attach(
        self, servo: ServoModel, q_start: np.ndarray, periods: int, control_dt: float, rate_limits: RateLimits | None
    ) -> None:
        """Use the loop's servo model and start at actuation q_start (mm); periods: control periods of
        control_dt s per step; rate_limits: the actuators' limits (for `limit_fractions`)."""
        self.servo, self.rate_limits = servo, rate_limits
        self.periods, self.control_dt = int(periods), float(control_dt)
        self._q = np.asarray(q_start, dtype=float).copy()

    # ------------------------------------------------------------- the rod
    def shape(self, q: np.ndarray) -> RodShape:
        """The rod at the loop's actuation q (mm); the last solve is reused for the same q."""
        q = np.asarray(q, dtype=float)
        if self._last is not None and np.array_equal(self._last[0], q):
            return self._last[1]
        t0 = time.perf_counter()
        s = self.drive.shape(q if self.to_plant is None else np.asarray(self.to_plant(q), dtype=float).reshape(-1))
        self.solve_time.append(time.perf_counter() - t0)  # s of wall time: what the plant costs a simulation
        self.solves += 1
        self._last = (q.copy(), s)
        return s

    def _observe(self, t: float, q: np.ndarray) -> None:
        """Solve the rod at q and record its tip and clearance at time t."""
        s = self.shape(q)
        tr = self.trace
        tr.t.append(float(t))
        tr.q.append(np.array(q, dtype=float))
        tr.tip.append(s.tip.copy())
        if s.is_success():
            c = float(self.scene.clearance_points(s.points, t, inflate=self.body_radius))
        else:
            c = math.nan
            if not self._failure:
                self._failure = f"plant: the rod's solve failed at t={t:.2f} s ({s.status}); no shape to go on"
                log.warning(self._failure)
        tr.clearance.append(c)

    # ------------------------------------------------------------- TipSensor
    def tip(self, t: float, q: np.ndarray) -> np.ndarray | None:
        """The rod's tip (3,) mm at actuation q plus the capture noise; None when the solve failed."""
        s = self.shape(q)
        if not s.is_success():
            return None
        return s.tip + (self._rng.normal(0.0, self._noise, 3) if self._noise > 0 else 0.0)

    def close(self) -> None:
        """Nothing to release."""

    # ---------------------------------------------------------------- Device
    def start_actuation(self) -> np.ndarray:
        if self._q is None:
            raise RuntimeError("RodPlant.attach must be called before the run")
        self.trace = PlantTrace()
        self._observe(0.0, self._q)
        return self._q.copy()

    def begin(self, t_origin: float) -> None:
        """The plant runs on loop time: nothing to start."""

    def problem(self) -> str:
        return self._failure

    def measure(self, t: float, q: np.ndarray, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """The servos' readback: where the plant's actuators are (mm)."""
        self._t = t
        assert self._q is not None
        return self._q.copy(), qc, True

    def move(self, t: float, q0: np.ndarray, commands: np.ndarray, control_dt: float) -> None:
        """Run the servos through the step's commands, solving the rod at the end of every control period."""
        assert self.servo is not None
        q = np.asarray(q0, dtype=float)
        for j, c in enumerate(np.asarray(commands, dtype=float)):
            q = self.servo.advance(q, c, control_dt)
            self._observe(t + (j + 1) * control_dt, q)
        self._q = q

    def hold(self, reason: str) -> None:
        """The servos hold where they are: the shape stays while the obstacles move (judged in `pace`)."""
        self._holds += 1
        self._hold_from = self._t

    def landing(self, t: float, periods: int, control_dt: float) -> Landing:
        """The servos stay where they are (a step the plant did not run, or a hold)."""
        assert self._q is not None
        return Landing.at_rest(self._q, periods)

    def estop(self, reason: str) -> None:
        self._estop = reason

    def pace(self, t: float) -> bool:
        """No waiting (loop time is simulated). A held step ends here: its control periods are judged."""
        if self._hold_from is not None:
            assert self._q is not None
            for j in range(self.periods):
                self._observe(self._hold_from + (j + 1) * self.control_dt, self._q)
            self._hold_from = None
        return False

    def finish(self, q_final: np.ndarray) -> dict[str, Any]:
        """The run ended: a held last step is judged, and the report returned."""
        self.pace(self._t)
        return self.describe()

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of the plant's motion, as fractions of the limits."""
        q = np.array(self.trace.q)
        if self.rate_limits is None or self.servo is None or len(q) < 3:
            return {"max_velocity_fraction": math.nan, "max_acceleration_fraction": math.nan}
        h = float(np.median(np.diff(self.trace.t)))
        return limit_fractions(self.trace.t[0], h, self.servo.config(q), self.rate_limits)

    # ---------------------------------------------------------------- report
    def describe(self) -> dict[str, Any]:
        """The plant's report for the run record (kind "plant"): figures by the rod's shape, and the trace."""
        tr = self.trace
        c = np.array(tr.clearance, dtype=float)
        tips = np.array(tr.tip, dtype=float).reshape(-1, 3)
        err = np.linalg.norm(tips - self.goal, axis=1) if len(tips) else np.zeros(0)
        d_sf = float(self.scene.safety_distance)
        seen = c[1:][np.isfinite(c[1:])]
        return {
            "kind": "plant",
            "model": "cosserat",
            "actuation": self.drive.actuation,
            "gravity": self.drive.gravity,
            "pretension_n": self.drive.pretension,
            "tip_noise_mm": self._noise,
            "periods": max(len(c) - 1, 0),
            "final_tip_error_mm": float(err[-1]) if len(err) else math.nan,
            "min_clearance_mm": float(seen.min()) if seen.size else math.nan,
            "collisions": int(np.sum(seen + d_sf < 0.0)),
            "safety_violations": int(np.sum(seen < 0.0)),
            "failed_solves": int(np.sum(~np.isfinite(c))),
            "failure": self._failure,
            "holds": self._holds,
            "estop": self._estop,
            "solves": self.solves,
            "median_solve_s": float(np.median(self.solve_time)) if self.solve_time else math.nan,
            "t": tr.t,
            "q": [list(map(float, q)) for q in tr.q],
            "tip": tips.tolist(),
            "clearance": [None if not math.isfinite(v) else v for v in c.tolist()],
        }

    def summary_line(self) -> str:
        """One line: the figures by the rod's shape."""
        d = self.describe()
        g = "with gravity" if d["gravity"] else "weightless"
        fail = f"; {d['failure']}" if d["failure"] else ""
        return (
            f"plant (Cosserat rod, actuation {d['actuation']}, {g}): final tip error {d['final_tip_error_mm']:.2f} mm, "
            f"min clearance {d['min_clearance_mm']:.2f} mm, collisions {d['collisions']} "
            f"(D_sf breaches {d['safety_violations']}) over {d['periods']} control periods; {d['solves']} rod solves, "
            f"median {d['median_solve_s'] * 1e3:.1f} ms{fail}"
        )
