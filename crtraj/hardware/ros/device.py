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
from crtraj.hardware.ros.messages import scene_markers

# backbone points shown in RViz
VIEW_POINTS = 41


class RosDevice:
    """Drives a robot through ROS 2 topics; implements `crtraj.control.ports.Device`.

    Each step's motion is the servo model's response to the step's commands (`servo`, the loop's
    first-order servo), sampled at `points_per_step` points with its exact velocities. Before
    anything is published, those points pass `verifier` (a `crtraj.hardware.verify.FrameVerifier`
    at the points' spacing) against the scene snapshot the loop checked the step with
    (`scene_now`): actuator position, velocity and acceleration limits from where the robot
    is, cable consistency, configuration limits, and the continuous body with D_sf. A step that
    fails is not sent: the device holds and the loop gets a `DeviceError` naming the time and the
    reason. A hold publishes one point at the last commanded position, at rest, one step ahead.

    Time: the bridge's `clock` (s; the ROS clock by default, a virtual one in tests) stamps what is
    sent; loop time t is clock time origin + t. A step whose start time has passed when it is
    measured or sent starts then (the origin moves to now: `resyncs`); one whose computation took
    more than `lead` s is refused: the live obstacles are predicted `lead` s ahead of each step's
    start (`FeedObstacles`' lead) and their keep-out spheres only grow with time, so the check
    covers a step that runs up to `lead` s after the snapshot it was checked against. The
    measurement at loop time t is the first joint state stamped at or after it
    (`RosNode.wait_joint_state`, waiting at most ``ros.joint_state_timeout`` s); none in time
    means the robot is lost and the run ends. `sleep` paces the loop (a virtual clock's sleep
    advances it). Lockstep: in real time the robot pauses for one computation between steps, while
    the limits are checked for steps that join without a pause (see the README, "ROS 2").
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
        self._last: np.ndarray | None = None  # last commanded actuator values and their velocity
        self._vel = np.zeros(actuators.n)
        self._qc: np.ndarray | None = None  # the command in force (actuation, mm)
        self._problem = ""
        self.estopped = False
        self.moves = self.holds = self.refused_steps = self.measured_steps = 0
        self.refusal = ""
        self.late = 0
        self.resyncs = 0  # steps sent after their start time: the clock mapping moved to now

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
        return self.actuators.actuation(st[0])

    def begin(self, t_origin: float) -> None:
        """Loop time 0 is now on the bridge's clock (`t_origin`, a perf_counter time, is not its clock)."""
        self._origin = self.clock()

    def problem(self) -> str:
        return self._problem

    def measure(self, t: float, q: np.ndarray, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """The first joint state stamped at or after loop time t (actuation, mm), the command in force."""
        self._catch_up(t)  # a step that starts late is measured, computed and checked from now
        st = self.node.wait_joint_state(self._origin + t - 1e-6, self.options.joint_state_timeout)
        if st is None:
            self._problem = (
                f"ros: no joint state on {self.options.joint_state_topic} for t={t:.2f} s within "
                f"{self.options.joint_state_timeout:g} s (robot lost)"
            )
            return q, qc, False
        self.measured_steps += 1
        q_meas = self.actuators.actuation(st[0])
        return q_meas, (q_meas if self._qc is None else self._qc), True

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
        if late > self.lead:
            # the obstacles were predicted `lead` s ahead of the step's start: later than that, the check
            # no longer covers when the step would run
            self._catch_up(t)
            self._refuse(t, f"computed {late:.3f} s after its start time, more than ros.lead = {self.lead:g} s")
        # computed after its start time: it starts now (a controller drops a trajectory that ended in the past);
        # the obstacle keep-outs only grow with time, so running up to `lead` s later than checked is covered
        self._catch_up(t)
        values, vel = self.samples(q0, commands)
        here = self.actuators.command(np.asarray(q0, dtype=float))
        stamps = t + self.offsets
        v = self.verifier.with_scene(self.scene_now())
        why = v.failure(stamps, values, start=here, start_velocity=self._vel)
        if why is not None:
            self._refuse(t, why)
        self.node.publish_trajectory(self._origin + t, self.offsets, values, vel)
        self._last, self._vel = values[-1], vel[-1]
        self._qc = np.asarray(commands[-1], dtype=float)
        self.moves += 1
        self._show(t + self.dt, values[-1])

    def _catch_up(self, t: float) -> None:
        """When loop time t is already past on the clock, make it now (the origin moves; `resyncs`)."""
        late = self.clock() - (self._origin + t)
        if late > 0.0:
            self._origin += late
            self.resyncs += 1

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
        """Sleep until loop time t on the bridge's clock; True when more than one step late."""
        lag = self.clock() - self._origin - t
        if lag < 0.0:
            self.sleep(-lag)
        late = lag > self.dt
        self.late += late
        return late

    def hold(self, reason: str) -> None:
        """Publish the last commanded position at rest, one step ahead (the robot stays there)."""
        if self._last is None:
            return
        now = self.clock()
        zero = np.zeros(self.actuators.n)
        self.node.publish_trajectory(now, np.array([self.dt]), self._last[None], zero[None])
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

    def describe(self) -> dict[str, Any]:
        return {
            "moves": self.moves,
            "holds": self.holds,
            "measured_steps": self.measured_steps,
            "refused_steps": self.refused_steps,
            "refusal": self.refusal,
            "late_steps": self.late,
            "resyncs": self.resyncs,
            "problem": self._problem,
            "ros": self.node.describe(),
        }
