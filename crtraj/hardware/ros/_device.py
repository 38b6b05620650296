"""The closed loop's device port over ROS 2: each verified step leaves as a JointTrajectory that a stock
joint_trajectory_controller executes exactly as verified.

`RosDevice` implements `crtraj.control.ports.Device` on a `crtraj.hardware.ros._node.RosNode`. Units:
actuation q in mm, actuator values in rad / mm, times in s.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from crtraj.control.ports import DeviceError, Landing
from crtraj.hardware.limits import LimitPeaks
from crtraj.hardware.ros import _jtc as jtc
from crtraj.hardware.ros._messages import scene_markers
from crtraj.hardware.ros._shaping import hold_message, step_message

log = logging.getLogger(__name__)

# backbone points shown in RViz
VIEW_POINTS = 41
# tip samples per trajectory point in the executed path shown in RViz
PATH_SUBSAMPLES = 2
# samples of the executed curve per trajectory point, for the verifier (its dt is the spacing)
VERIFY_SUBSTEPS = 4


class RosDevice:
    """Drives a robot through a joint_trajectory_controller (JTC); implements `crtraj.control.ports.Device`.

    Each step's motion is the servo model's response to the step's commands (`servo`, the loop's
    first-order servo), sampled at `points_per_step` points with its exact velocities, shaped into one
    message (`crtraj.hardware.ros._shaping.step_message`): the committed curve's knots from the send time
    to the step's start, the step's points, and a stop tail to rest. Before anything is published the
    curve the controller will execute from the message's arrival (`crtraj.hardware.ros._jtc.executed`,
    the point before the trajectory being the committed curve `state_lag` s before arrival, as the
    controller reads its state one update late) passes the controller's own acceptance
    rules (`jtc.rejection` with `jtc` parameters) and, sampled every `verifier.dt` s up to rest,
    `verifier` (a `crtraj.hardware.verify.FrameVerifier`) against the scene snapshot the loop checked the
    step with (`scene_now`): actuator position, velocity and acceleration limits, cable consistency,
    configuration limits, and the continuous body with D_sf. A step that fails is not sent: the robot
    stays on the committed curve, which stops on its verified tail, and the loop gets a `DeviceError`
    naming the time and the reason. A hold re-sends the committed curve from now (it ends at rest).

    Time (pipelined): the bridge's `clock` (s; the ROS clock by default, a virtual one in tests) stamps
    what is sent; loop time t is clock time origin + t, and step t is computed and sent `lead` s before
    it starts. Messages are stamped `controller.lookahead` s later than that (`jtc.message_epoch`): Jazzy
    and later write their trajectory sampled one update period ahead, so each cycle commands the
    committed curve at its own time. The measurement at loop time t is the committed curve at t, corrected by the newest
    joint state's deviation from it at the state's stamp, decayed with the servo's lag; a joint state
    older than ``ros.joint_state_timeout`` s means the robot is lost and the run ends. A message may
    take up to `arrival_margin` s to reach the controller: a step ready later than that before its
    start (computed more than ``lead - arrival_margin`` s late) is refused and counted (`late_refused`);
    within that bound its lateness changes nothing in what the robot executes. Once at rest, a late
    loop moves the origin on (`restarts`).
    `sleep` paces the loop (a virtual clock's sleep advances it).
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
        controller: jtc.JtcParameters | None = None,
        arrival_margin: float = 0.0,
        state_lag: float = 0.0,
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
        self.arrival_margin, self.state_lag = float(arrival_margin), float(state_lag)
        self.controller = jtc.JtcParameters() if controller is None else controller
        self.n_points = self.options.points_per_step
        self.offsets = self.dt * np.arange(1, self.n_points + 1) / self.n_points
        # the verified curve is sampled at the verifier's spacing (finer than the points)
        self.spacing = float(verifier.dt) if verifier is not None else self.dt / self.n_points
        self._origin = clock()
        self._curve = _rest(np.zeros(actuators.n))  # the committed curve (loop time), as the JTC executes it
        self._end = 0.0  # loop time the last step sent ends (s)
        self._last: np.ndarray | None = None  # actuator values and velocity at the end of the last step
        self._vel = np.zeros(actuators.n)
        self._qc: np.ndarray | None = None  # the command in force (actuation, mm)
        self._problem = ""
        self.estopped = False
        self.moves = self.holds = self.refused_steps = self.measured_steps = 0
        self.refusal = ""
        self.late = 0
        self.late_refused = 0  # steps ready too late to arrive before their start (beyond the lateness bound)
        self.restarts = 0  # times a late loop at rest moved the origin on
        self.peaks = LimitPeaks(actuators, self.spacing)  # of the executed curves published

    @property
    def committed(self) -> jtc.Spline:
        """The curve the controller executes from what was sent (loop time s, actuator values)."""
        return self._curve

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
        self._curve, self._end = _rest(st[0]), 0.0
        return self.actuators.actuation(st[0])

    def begin(self, t_origin: float) -> None:
        """Loop time 0 is `lead` s from now on the bridge's clock (`t_origin`, a perf_counter time, is not
        its clock): the first step is sent now."""
        self._origin = self.clock() + self.lead

    def problem(self) -> str:
        return self._problem

    def measure(self, t: float, q: np.ndarray, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """The actuation (mm) at loop time t and the command in force: the committed curve at t,
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
        if self._not_following(dev, st[1] - self._origin):
            return q, qc, False
        q_now = here + self.servo.decay(max(t - (st[1] - self._origin), 0.0)) * dev
        # off the sent steps (a hold, a refusal) the set-point in force is the committed curve's: it may still be
        # on its stop tail, and a next step planned from rest there would ask for a jump in acceleration
        return q_now, (qc if self._joins(t) else self.landing(t - self.dt, 1, self.dt).qc), True

    def _not_following(self, dev: np.ndarray, tau: float) -> bool:
        """True (and the run's problem set) when the robot is more than ``ros.following_error`` mm off the curve
        sent to the controller at loop time tau: the controller is not executing the verified motion (inactive,
        or another controller claims the joints), and the topic interface would never say so."""
        limit = self.options.following_error
        worst = int(np.argmax(np.abs(dev)))
        if limit <= 0.0 or abs(dev[worst]) <= limit:
            return False
        joint = self.options.joint_name(self.actuators.names[worst])
        self._problem = (
            f"ros: joint {joint!r} is {abs(dev[worst]):.2f} mm off the curve sent to "
            f"{self.options.controller} at t = {tau:.3f} s (ros.following_error {limit:g} mm): the controller "
            "is not executing it; check that it is active (ros2 control list_controllers) and owns the joint"
        )
        return True

    def _commanded(self, tau: float) -> np.ndarray:
        """The commanded actuator values at loop time tau (the committed curve)."""
        return self._curve.at(float(tau))[0]

    def landing(self, t: float, periods: int, control_dt: float) -> Landing:
        """The committed curve over the step from loop time t (it stops on its verified tail and rests at its
        end), as actuation and first-order set-points at the ends of the control periods."""
        P, V, _ = self._curve.at(t + control_dt * np.arange(1, periods + 1))
        return Landing.first_order(self.actuators.actuation(P), V / self.actuators.scale, self.servo.tau)

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
        """Verify the curve the controller will execute and publish the step starting at loop time t;
        `DeviceError` (why) when it was not sent."""
        if self.estopped or self._problem:
            raise DeviceError(self._problem or "e-stopped")
        now = self.clock() - self._origin
        if now + self.arrival_margin > t + 1e-9:
            # it might arrive after its start, when the robot is on the previous step's stop tail already
            self.late_refused += 1
            self._refuse(
                t,
                f"ready {now - (t - self.lead):.3f} s late, beyond the bound ros.lead - ros.arrival_margin = "
                f"{self.lead - self.arrival_margin:.3f} s ({now - t:+.3f} s from its start time)",
            )
        values, vel = self.samples(q0, commands)
        names = tuple(self.node.names)
        epoch = jtc.message_epoch(self._origin, self.controller)
        msg = step_message(self._curve, now, t, (self.offsets, values, vel), self.actuators.amax, names, epoch)
        why = self._verify(msg, now)
        if why is not None:
            self._refuse(t, why)
        self._last, self._vel, self._end = values[-1], vel[-1], t + self.dt
        self._qc = np.asarray(commands[-1], dtype=float)
        self.moves += 1
        self._show(t + self.dt, values[-1])

    def _verify(self, msg: jtc.JtcMessage, now: float) -> str | None:
        """Check `msg` sent at loop time `now` as the controller will take and execute it; publish it and make
        its executed curve the committed one when it passes; else the reason."""
        names = tuple(self.node.names)
        epoch = jtc.message_epoch(self._origin, self.controller)
        why = jtc.rejection(msg, names, now, self.controller, epoch=epoch)
        if why is not None:
            return f"the controller would refuse it: {why}"
        # the point before the trajectory is the controller's lagged state (never used: the message's first point
        # is already due when it arrives; `crtraj.hardware.ros._shaping`)
        p0, v0 = jtc.state_before(self._curve, now, self.state_lag)
        curve = jtc.executed(msg, now, p0, v0, epoch=epoch)
        stamps = now + self.spacing * np.arange(math.ceil((curve.end - now) / self.spacing - 1e-9) + 1)
        P, V, _ = curve.at(stamps)
        why = self.verifier.with_scene(self.scene_now()).failure(stamps[1:], P[1:], start=P[0], start_velocity=V[0])
        if why is not None:
            return why
        self._publish(msg, curve, stamps, P)
        self.peaks.add(P[1:], P[0], V[0])
        return None

    def _publish(self, msg: jtc.JtcMessage, curve: jtc.Spline, stamps: np.ndarray, P: np.ndarray) -> None:
        """Send `msg` (loop time) and make `curve` the committed one; show its tip path."""
        tfs = np.array([p.time_from_start for p in msg.points])
        pos = np.array([p.positions for p in msg.points])
        vel = np.array([p.velocities for p in msg.points])
        self.node.publish_trajectory(jtc.message_epoch(self._origin, self.controller) + msg.stamp, tfs, pos, vel)
        self._curve = self._curve.since(stamps[0] - 2.0).then(curve)
        publish_path = getattr(self.node, "publish_path", None)
        if publish_path is not None and self.model is not None:
            k = max(round(self.dt / self.n_points / self.spacing / PATH_SUBSAMPLES), 1)
            X = self.model.robot.config(self.actuators.actuation(P[::k]))
            tips = self.model.points(X, 2)[:, -1, :]
            publish_path(self._origin + stamps[0], tips)

    def _refuse(self, t: float, why: str) -> None:
        """Count and record a refused step, hold, and raise the `DeviceError` the loop expects."""
        self.refused_steps += 1
        self.refusal = self.refusal or why
        log.warning("ros: step at t=%.2f s refused before sending: %s", t, why)
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
            # at rest: move loop time on, keeping the committed curve where it was in clock time
            self._origin += lag
            self._curve = self._curve.shifted(-lag)
            self._end -= lag
            self.restarts += 1
        late = lag > self.dt
        self.late += late
        return late

    def hold(self, reason: str) -> None:
        """Re-send the committed curve from now: it stops on its verified tail (or stays at rest)."""
        if self._last is None:
            return
        now = self.clock() - self._origin
        epoch = jtc.message_epoch(self._origin, self.controller)
        msg = hold_message(self._curve, now, self.dt / self.n_points, tuple(self.node.names), epoch)
        tfs = np.array([p.time_from_start for p in msg.points])
        pos = np.array([p.positions for p in msg.points])
        vel = np.array([p.velocities for p in msg.points])
        self.node.publish_trajectory(epoch + msg.stamp, tfs, pos, vel)
        p0, v0 = jtc.state_before(self._curve, now, self.state_lag)
        self._curve = self._curve.since(now - 2.0).then(jtc.executed(msg, now, p0, v0, epoch=epoch))
        self._vel = np.zeros(self.actuators.n)
        self._qc = self.actuators.actuation(self._curve.positions[-1])
        self.holds += 1
        log.info("ros: hold (%s)", reason)

    def estop(self, reason: str) -> None:
        """Hold, and refuse every later move (final)."""
        self.hold(reason)
        self.estopped = True
        self._problem = self._problem or f"e-stopped: {reason}"

    def finish(self, q_final: np.ndarray) -> dict[str, Any]:
        """The robot stays where the committed curve comes to rest (the loop ends at rest); the report."""
        return self.describe()

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of the executed curves published, as fractions of the
        limits (finite differences at the verifier's spacing, as it checks them; NaN before any)."""
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
            "late_refused": self.late_refused,
            "restarts": self.restarts,
            "problem": self._problem,
            "ros": self.node.describe(),
        }


def _rest(values: np.ndarray) -> jtc.Spline:
    """A curve at rest at actuator `values` (one knot at loop time 0)."""
    v = np.asarray(values, dtype=float)
    return jtc.Spline.hermite(np.zeros(1), v[None], np.zeros((1, v.size)))
