"""The motion of one control step: the tracking controller and its servo model simulated over the step
(in C when the validity kernel is compiled, else in numpy), and the motion of holding still.
Units: mm, rad, s."""

from __future__ import annotations

import logging
import math

import numpy as np

from crtraj.control.compiled_tracking import CompiledTracking
from crtraj.control.run_record import Motion
from crtraj.control.scene_checks import SceneChecks
from crtraj.control.tracking import TrackingController

log = logging.getLogger(__name__)


class StepMotion:
    """Simulates the robot over one step of dt s, in n_sub tracking periods.

    tracker: the `TrackingController` (with its servo model). checks: the `SceneChecks` whose motion bound
    spaces the samples (and whose build cache holds the compiled tracking). resolution: mm of body motion
    between samples.
    """

    def __init__(
        self, tracker: TrackingController, checks: SceneChecks, dt: float, n_sub: int, resolution: float
    ) -> None:
        self.tracker, self.servo, self.checks = tracker, tracker.servo, checks
        self.dt, self.n_sub, self.resolution = dt, n_sub, resolution
        # with compiled checks (a C compiler), each step's tracking simulation runs in C as well
        self.compiled = self._compiled() if checks.validator.state.kernel is not None else None

    def _compiled(self) -> CompiledTracking | None:
        """The C tracking simulation (`crtraj.control.compiled_tracking`) from the validity kernel's build cache;
        None in tip mode, without a C compiler, or when it fails to build (logged)."""
        cache = self.checks.kernels.build_cache
        h = self.dt / self.n_sub
        try:
            return CompiledTracking.load(self.tracker, h, self.checks.validator.space.metric_matrix, cache)
        except (RuntimeError, OSError) as exc:
            log.warning("compiled tracking unavailable (%s): simulating in numpy", exc)
            return None

    def track(self, q: np.ndarray, qc: np.ndarray, x0: np.ndarray, x1: np.ndarray, t: float, inc: np.ndarray) -> Motion:
        """Simulate the tracking controller toward the straight move x0 -> x1 over one step.

        inc: the set-point's configuration change in the control period before t
        (the history of the actuator acceleration limits).
        Returns (q at the end, set-point at the end, sample times (S,),
        actual configurations at the samples (S, nx), set-points per control
        period (n_sub, nq)). The first sample is the current state at t.
        """
        n, ctl, servo, v = self.n_sub, self.tracker, self.servo, self.checks.validator
        dt, resolution = self.dt, self.resolution
        if self.compiled is not None:
            done = self.compiled.step(q, qc, x0, x1, t, inc, n, dt, resolution)
            if done is not None:
                return done
        h = dt / n
        rate = (x1 - x0) / dt
        ts, xs = [np.array([t])], [servo.config(q)[None]]
        cmds = np.empty((n, len(q)))
        for j in range(n):
            xm = servo.config(q)
            cmd = ctl.step(xm, qc, x0 + (j + 1) / n * (x1 - x0), h, x_reference_rate=rate, previous_increment=inc)
            inc = cmd.increment
            q_end = servo.advance(q, cmd.q, h)
            span = float(v.motion_bound(servo.config(q_end) - xm))
            ns = max(1, math.ceil(2.0 * span / resolution))
            tau = h * np.arange(1, ns + 1) / ns
            ts.append(t + j * h + tau)
            xs.append(servo.config(servo.trajectory(q, cmd.q, tau)))
            q, qc = q_end, cmd.q
            cmds[j] = qc
        return q, qc, np.concatenate(ts), np.concatenate(xs), cmds

    def periods(self, q: np.ndarray, cmds: np.ndarray) -> np.ndarray:
        """Actual actuation (n_sub, nq) mm at the end of each control period of a step that starts at q
        and holds each of `cmds` for one period (the servo model, as `track` advances it)."""
        h = self.dt / self.n_sub
        out = np.empty((len(cmds), len(q)))
        for j, c in enumerate(cmds):
            q = self.servo.advance(q, c, h)
            out[j] = q
        return out

    def hold(self, q: np.ndarray, x: np.ndarray, t: float) -> Motion:
        """The motion of holding still for one step from t: actuators commanded to their measured positions q."""
        return (
            q.copy(),
            q.copy(),
            np.array([t, t + self.dt]),
            np.stack([x, x]),
            np.repeat(q[None], self.n_sub, axis=0),
        )
