"""The closed loop's device port over ROS 2: each verified step leaves as a JointTrajectory.

`RosDevice` implements `crtraj.control.ports.Device` on a `crtraj.hardware.ros.node.RosNode`. Units:
actuation q in mm, actuator values in rad / mm, times in s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from crtraj.control.ports import DeviceError
from crtraj.hardware.limits import LimitPeaks
from crtraj.hardware.ros.messages import scene_markers

# backbone points shown in RViz
VIEW_POINTS = 41


class RosDevice:
    """Drives a robot through ROS 2 topics; implements `crtraj.control.ports.Device`.

    Each step's motion is the servo model's response to the step's commands (`servo`, the loop's
    first-order servo), sampled at `points_per_step` points with its exact velocities. Before
    anything is published, those points pass `verifier` (a `crtraj.hardware.verify.FrameVerifier`
    at the points' spacing) against the scene snapshot the loop checked the step with
    (`scene_now`): actuator position, velocity and acceleration limits from the end of what was sent
    (at its velocity, or at rest after a hold), cable consistency, configuration limits, and the
    continuous body with D_sf. A step that fails is not sent: the device holds and the loop gets a
    `DeviceError` naming the time and the reason. A hold publishes one point at rest at the last
    point sent, starting when what is under way ends (it was checked; braking is always allowed).

    Time (pipelined, like `crtraj.hardware.link.DeviceLink`): the bridge's `clock` (s; the ROS clock
    by default, a virtual one in tests) stamps what is sent; loop time t is clock time origin + t, and
    step t is computed and sent `lead` s before it starts, so steps join without a pause (a controller
    follows the current trajectory until the next one's start stamp). The live obstacles are
    predicted `lead` s ahead accordingly (`FeedObstacles`' lead). The commanded motion is one
    timeline: the points sent, then rest at the last one. The measurement at loop time t is its
    position at t, corrected by the newest joint state's deviation from the timeline at its stamp,
    decayed with the servo's lag; a joint state older than ``ros.joint_state_timeout`` s means the
    robot is lost and the run ends. A step not ready before its start time is refused (the robot
    holds); once at rest, a late loop moves the origin on (`restarts`). `sleep` paces the loop (a
    virtual clock's sleep advances it).
    """

    def __init__(
        self,
        node: Any,
        actuators: Any,
        model: Any,
        servo: Any,
        dt: float,
        verifier: Any,
        scene_now: Callable[[], Any],
        *,
        clock: Callable[[], float] = time.time,
        sleep: Callable[[float], None] = time.sleep,
        lead: float = 0.0,
    ) -> None:
        self.node = node
        self.options = node.options
        self.actuators = actuators
        self.model = model
        self.servo = servo
        self.dt = float(dt)
        self.verifier = verifier
        self.scene_now = scene_now
        self.clock, self.sleep = clock, sleep
        self.lead = float(lead)
        self.n_points = self.options.points_per_step
        self.offsets = self.dt * np.arange(1, self.n_points + 1) / self.n_points
        self._origin = clock()
        self._hist_t = np.zeros(1)  # the commanded timeline: loop times (s) and actuator values, then rest
        self._hist_v = np.zeros((1, actuators.n))
        self._end = 0.0  # loop time the motion sent so far ends (s)
        self._last: np.ndarray | None = None  # last commanded actuator values and their velocity
        self._vel = np.zeros(actuators.n)
        self._qc: np.ndarray | None = None  # the command in force (actuation, mm)
        self._problem = ""
        self.estopped = False
        self.moves = self.holds = self.refused_steps = self.measured_steps = 0
        self.refusal = ""
        self.late = 0
        self.restarts = 0  # times a late loop at rest moved the origin on
        self.peaks = LimitPeaks(actuators, self.dt / self.n_points)  # of the points published

    # --------------------------------------------------------------- state
    def start_actuation(self) -> np.ndarray:
        """Where the robot is (its newest joint state, waiting up to ``ros.start_timeout`` s), as
        actuation q (mm); `DeviceError` when it never said."""
        st = self.node.joint_state() or self.node.wait_joint_state(-math.inf, self.options.start_timeout)
        if st is None:
            raise DeviceError(
                f"ros: no joint state on {self.options.joint_state_topic} within {self.options.start_timeout:g} s"
            )
        self._last, self._vel = st[0], np.zeros(self.actuators.n)
        self._hist_t, self._hist_v, self._end = np.zeros(1), st[0][None].copy(), 0.0
        return self.actuators.actuation(st[0])

    def begin(self, t_origin: float) -> None:
        """Loop time 0 is `lead` s from now on the bridge's clock (`t_origin`, a perf_counter time, is not
        its clock): the first step is sent now."""
        self._origin = self.clock() + self.lead

    def problem(self) -> str:
        return self._problem

    def measure(self, t: float, q: np.ndarray, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """The actuation (mm) at loop time t and the command in force: the commanded timeline at t,
        corrected by the newest joint state's deviation from it at the state's stamp."""
        newest = self.clock() - self.options.joint_state_timeout
        st = self.node.joint_state()
        if st is None or st[1] < newest:
            st = self.node.wait_joint_state(newest, self.options.joint_state_timeout)
        if st is None:
            self._problem = (
                f"ros: no joint state on {self.options.joint_state_topic} newer than "
                f"{self.options.joint_state_timeout:g} s (robot lost)"
            )
            return q, qc, False
        self.measured_steps += 1
        here = self.actuators.actuation(self._commanded(t))
        dev = self.actuators.actuation(st[0]) - self.actuators.actuation(self._commanded(st[1] - self._origin))
        q_now = here + self.servo.decay(max(t - (st[1] - self._origin), 0.0)) * dev
        return q_now, (qc if self._joins(t) else q_now), True

    def _commanded(self, tau: float) -> np.ndarray:
        """The commanded actuator values at loop time tau (rest at the ends of the timeline)."""
        return np.array([np.interp(tau, self._hist_t, self._hist_v[:, i]) for i in range(self.actuators.n)])

    def _joins(self, t: float) -> bool:
        """Step t continues the motion sent so far without a pause (else it starts from rest)."""
        return abs(t - self._end) <= 1e-9 and bool(np.any(self._vel != 0.0))

    # -------------------------------------------------------------- motion
    def samples(self, q0: np.ndarray, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(actuator values, actuator velocities) (points, n) of the servo model at `offsets` into a step
        from actuation q0 (mm) under `commands` (one per control period): q relaxes to each command
        with the servo's time constant, dq/dt = (c - q) / tau."""
        C = np.asarray(commands, dtype=float)
        h = self.dt / len(C)
        starts = [np.asarray(q0, dtype=float)]
        for c in C[:-1]:
            starts.append(self.servo.advance(starts[-1], c, h))
        j = np.clip(np.ceil(self.offsets / h - 1e-9).astype(int) - 1, 0, len(C) - 1)
        tau = (self.offsets - j * h)[:, None]
        Q = C[j] + np.exp(-tau / self.servo.tau) * (np.array(starts)[j] - C[j])
        V = (C[j] - Q) / self.servo.tau
        return self.actuators.command(Q), V * self.actuators.scale

    def move(self, t: float, q0: np.ndarray, commands: np.ndarray, control_dt: float) -> None:
        """Verify and publish the step starting at loop time t; `DeviceError` (why) when it was not sent."""
        if self.estopped or self._problem:
            raise DeviceError(self._problem or "e-stopped")
        late = self.clock() - (self._origin + t)
        if late > 0.0:
            self._refuse(t, f"ready {late:.3f} s after its start time (it is due ros.lead = {self.lead:g} s before)")
        values, vel = self.samples(q0, commands)
        # the robot is at the end of what was sent: moving on from it, or at rest there
        v0 = self._vel if self._joins(t) else np.zeros(self.actuators.n)
        stamps = t + self.offsets
        why = self.verifier.with_scene(self.scene_now()).failure(stamps, values, start=self._last, start_velocity=v0)
        if why is not None:
            self._refuse(t, why)
        self.node.publish_trajectory(self._origin + t, self.offsets, values, vel)
        self.peaks.add(values, self._last, v0)
        keep = self._hist_t >= t - 2.0
        keep[-1] = True  # the rest point the new step starts from
        self._hist_t = np.concatenate([self._hist_t[keep], [t], stamps])
        self._hist_v = np.concatenate([self._hist_v[keep], self._last[None], values])
        self._last, self._vel, self._end = values[-1], vel[-1], t + self.dt
        self._qc = np.asarray(commands[-1], dtype=float)
        self.moves += 1
        self._show(t + self.dt, values[-1])

    def _refuse(self, t: float, why: str) -> None:
        """Count and record a refused step, hold, and raise the `DeviceError` the loop expects."""
        self.refused_steps += 1
        self.refusal = self.refusal or why
        self.hold(f"step at t={t:.2f} s refused before sending: {why}")
        raise DeviceError(f"ros: step refused before sending: {why}")

    def _show(self, t: float, values: np.ndarray) -> None:
        """Publish the body at actuator `values` and the obstacles at loop time t for RViz."""
        X = self.model.robot.config(self.actuators.actuation(values))
        centers, radii = self.scene_now().states(t)
        P = self.model.points(X, VIEW_POINTS)
        msg = scene_markers(self.options.frame_id, self._origin + t, P, self.model.robot.body_radius, centers, radii)
        self.node.publish_markers(msg)

    def pace(self, t: float) -> bool:
        """Sleep until step t is due to be sent, `lead` s before it starts; True when more than one step
        late. A late loop with the robot at rest moves the origin on instead (step t then starts `lead` s
        from now)."""
        lag = self.clock() - (self._origin + t - self.lead)
        if lag < 0.0:
            self.sleep(-lag)
        elif lag > 0.0 and t > self._end + 1e-9:
            # at rest: move loop time on, keeping the commanded timeline where it was in clock time
            self._origin += lag
            self._hist_t = self._hist_t - lag
            self._end -= lag
            self.restarts += 1
        late = lag > self.dt
        self.late += late
        return late

    def hold(self, reason: str) -> None:
        """Publish the last commanded position at rest, one step ahead (the robot stays there)."""
        if self._last is None:
            return
        # after what was sent (it was checked and is under way): the robot stops at its last point
        stamp = max(self.clock(), self._origin + self._end)
        zero = np.zeros(self.actuators.n)
        self.node.publish_trajectory(stamp, np.array([self.dt]), self._last[None], zero[None])
        self._vel = zero
        self._qc = self.actuators.actuation(self._last)
        self.holds += 1

    def estop(self, reason: str) -> None:
        """Hold, and refuse every later move (final)."""
        self.hold(reason)
        self.estopped = True
        self._problem = self._problem or f"e-stopped: {reason}"

    def finish(self, q_final: np.ndarray) -> dict[str, Any]:
        """The robot stays at the last commanded position (the loop ends at rest); the report."""
        return self.describe()

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of the points published, as fractions of the limits
        (finite differences at the points' spacing, as the verifier checks them; NaN before any)."""
        return self.peaks.as_dict()

    def describe(self) -> dict[str, Any]:
        return {
            **self.limit_fractions(),
            "moves": self.moves,
            "holds": self.holds,
            "measured_steps": self.measured_steps,
            "refused_steps": self.refused_steps,
            "refusal": self.refusal,
            "late_steps": self.late,
            "restarts": self.restarts,
            "problem": self._problem,
            "ros": self.node.describe(),
        }
