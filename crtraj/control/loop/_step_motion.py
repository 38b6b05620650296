"""The motion of one control step: the tracking controller and its servo model simulated over the step
(in C when the validity kernel is compiled, else in numpy), and the motion of holding still: a stop
planned within the acceleration limits from the current state (`crtraj.control.braking.servo_stop`)
when the robot is moving. Units: mm, rad, s."""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from crtraj.control.braking import servo_stop
from crtraj.control.loop._run_record import Motion
from crtraj.control.loop._scene_checks import SceneChecks
from crtraj.control.tracking import CompiledTracking, TrackingController

log = logging.getLogger(__name__)


class StepMotion:
    """Simulates the robot over one step of dt s, in n_sub tracking periods.

    tracker: the `TrackingController` (with its servo model). checks: the `SceneChecks` whose motion bound
    spaces the samples (and whose build cache holds the compiled tracking). resolution: mm of body motion
    between samples. brake_limits: the `RateLimits` a hold's stop keeps (None: a hold stops at once).
    """

    def __init__(
        self,
        tracker: TrackingController,
        checks: SceneChecks,
        dt: float,
        n_sub: int,
        resolution: float,
        brake_limits: Any = None,
    ) -> None:
        self.tracker, self.servo, self.checks = tracker, tracker.servo, checks
        self.dt, self.n_sub, self.resolution = dt, n_sub, resolution
        self.brake_limits = brake_limits
        # with compiled checks (a C compiler), each step's tracking simulation runs in C as well
        build = checks.compiled_build()
        self.compiled = self._compiled(*build) if build is not None else None

    def _compiled(self, cache: Any, metric_matrix: np.ndarray) -> CompiledTracking | None:
        """The C tracking simulation (`CompiledTracking`) from the validity kernel's build cache; None when it
        fails to build (logged)."""
        h = self.dt / self.n_sub
        try:
            return CompiledTracking.load(self.tracker, h, metric_matrix, cache)
        except (RuntimeError, OSError) as exc:
            log.warning("compiled tracking unavailable (%s): simulating in numpy", exc)
            return None

    def track(self, q: np.ndarray, qc: np.ndarray, x0: np.ndarray, x1: np.ndarray, t: float, inc: np.ndarray) -> Motion:
        """Simulate the tracking controller toward the straight move x0 -> x1 over one step.

        inc: the set-point's configuration change in the control period before t
        (the history of the actuator acceleration limits).
        Returns the step's `Motion`; its first sample is the current state at t.
        """
        n, ctl, servo, checks = self.n_sub, self.tracker, self.servo, self.checks
        dt, resolution = self.dt, self.resolution
        if self.compiled is not None:
            done = self.compiled.step(q, qc, x0, x1, t, inc, n, dt, resolution)
            if done is not None:
                return Motion(*done)
        h = dt / n
        rate = (x1 - x0) / dt
        ts, xs = [np.array([t])], [servo.config(q)[None]]
        cmds = np.empty((n, len(q)))
        for j in range(n):
            xm = servo.config(q)
            cmd = ctl.step(xm, qc, x0 + (j + 1) / n * (x1 - x0), h, x_reference_rate=rate, previous_increment=inc)
            inc = cmd.increment
            q_end = servo.advance(q, cmd.q, h)
            span = float(checks.motion_bound(servo.config(q_end) - xm))
            ns = max(1, math.ceil(2.0 * span / resolution))
            tau = h * np.arange(1, ns + 1) / ns
            ts.append(t + j * h + tau)
            xs.append(servo.config(servo.trajectory(q, cmd.q, tau)))
            q, qc = q_end, cmd.q
            cmds[j] = qc
        return Motion(q, qc, np.concatenate(ts), np.concatenate(xs), cmds)

    def periods(self, q: np.ndarray, cmds: np.ndarray) -> np.ndarray:
        """Actual actuation (n_sub, nq) mm at the end of each control period of a step that starts at q
        and holds each of `cmds` for one period (the servo model, as `track` advances it)."""
        h = self.dt / self.n_sub
        out = np.empty((len(cmds), len(q)))
        for j, c in enumerate(cmds):
            q = self.servo.advance(q, c, h)
            out[j] = q
        return out

    def hold(self, q: np.ndarray, x: np.ndarray, t: float, q_last: np.ndarray | None = None) -> Motion:
        """The motion of holding for one step from t: at rest (or without limits, or without the actuation
        q_last one control period before), actuators commanded to their measured positions q; moving, the
        first step of `stop` (the rest of the stop is the next steps' hold)."""
        if q_last is None or self.brake_limits is None or not np.any(q != q_last):
            return self._still(q, x, t)
        motion, _ = self.stop(q, q_last, t)
        return motion

    def stop(self, q: np.ndarray, q_last: np.ndarray, t: float) -> tuple[Motion, tuple[np.ndarray, np.ndarray]]:
        """The stop from actual actuation q (mm) at t, moving from q_last one control period before, within
        `brake_limits` (`crtraj.control.braking.servo_stop`): (this step's motion, at rest after the stop, and
        (times (S,), configurations (S, nx)) sampled densely over the whole stop, which may outlast the step).
        The servo model executes the stop's set-points exactly as planned."""
        h = self.dt / self.n_sub
        Q, C = servo_stop(self.servo, q, q_last, h, self.brake_limits)
        if not len(Q):
            return self._still(q, self.servo.config(q), t), (np.array([t]), self.servo.config(q)[None])
        ts, xs = [np.array([t])], [self.servo.config(q)[None]]
        start = q
        for j, c in enumerate(C):
            span = float(self.checks.motion_bound(self.servo.config(Q[j]) - self.servo.config(start)))
            tau = h * np.arange(1, max(1, math.ceil(2.0 * span / self.resolution)) + 1)
            tau /= len(tau)
            ts.append(t + j * h + tau)
            xs.append(self.servo.config(self.servo.trajectory(start, c, tau)))
            start = Q[j]
        T, X = np.concatenate(ts), np.concatenate(xs)
        n = self.n_sub
        cmds = np.vstack([C[:n], np.repeat(Q[-1:], max(n - len(C), 0), axis=0)])
        q_end = Q[min(n, len(Q)) - 1]
        in_step = np.less_equal(T, t + self.dt + 1e-12)
        Ts, Xs = T[in_step], X[in_step]
        if Ts[-1] < t + self.dt - 1e-12:  # at rest before the step ends
            Ts, Xs = np.append(Ts, t + self.dt), np.vstack([Xs, Xs[-1:]])
        return Motion(q_end, cmds[-1].copy(), Ts, Xs, cmds), (T, X)

    def _still(self, q: np.ndarray, x: np.ndarray, t: float) -> Motion:
        """The motion of holding still for one step from t: actuators commanded to their measured positions q."""
        return Motion(
            q.copy(),
            q.copy(),
            np.array([t, t + self.dt]),
            np.stack([x, x]),
            np.repeat(q[None], self.n_sub, axis=0),
        )
