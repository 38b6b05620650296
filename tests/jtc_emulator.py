"""A joint_trajectory_controller emulator for the ROS bridge tests: an rclpy node around `jtc_core.JtcCore` (each
distro's semantics, written from the controller's C++ source without crtraj's controller model).

- Subscribes ``/<name>/joint_trajectory`` (reliable); each message is validated on receipt at the virtual clock
  (`JtcCore.refusal`); refusals are recorded in `rejected`.
- Cycles every `period` s of the test's virtual clock (`feed_clock.VirtualClock.every`): a message received at
  least `latency` s before a cycle is adopted there (the newest replaces the others), as the distro does it
  (replacement, or Rolling's blend); the command written is recorded in `commanded` and published as
  sensor_msgs/JointState stamped with the cycle time (perfect tracking).
- Its parameters are declared with the distro's names and defaults (overridable), plus ``joints``,
  ``state_interfaces``, ``update_rate`` and each joint's ``constraints.<joint>.trajectory`` and ``.goal``;
  ``/<name>/get_parameters`` answers as rclcpp's parameter service does: a request naming one undeclared
  parameter gets no values at all.

Units: whatever the messages carry (rad, m), s.
"""

from __future__ import annotations

import threading

import numpy as np
from jtc_core import JtcCore, Msg, Pt


def _seconds(t) -> float:
    return float(t.sec) + 1e-9 * float(t.nanosec)


def from_ros(msg) -> Msg:
    """A trajectory_msgs/JointTrajectory as `jtc_core.Msg`."""

    def arr(x):
        return np.array(x, dtype=float) if len(x) else None

    pts = tuple(
        Pt(_seconds(p.time_from_start), np.array(p.positions, dtype=float), arr(p.velocities), arr(p.accelerations),
           len(p.effort))
        for p in msg.points
    )  # fmt: skip
    return Msg(tuple(msg.joint_names), _seconds(msg.header.stamp), pts)


class JtcEmulator:
    """The emulated controller. joints: its joint names; start: the joints' positions at rest; clock: the test's
    `VirtualClock`; period: its update period (s); distro: "humble", "jazzy" or "rolling"; params: parameter values
    over the distro's defaults; lag, latency: as above; velocity_state: a velocity state interface."""

    def __init__(
        self,
        ctx,
        domain_id,
        joints,
        start,
        clock,
        *,
        name="joint_trajectory_controller",
        period=0.004,
        joint_state_topic="/joint_states",
        distro="humble",
        params=None,
        lag=None,
        latency=0.0,
        velocity_state=True,
    ):
        import rclpy
        from rcl_interfaces.srv import GetParameters
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.joints, self.clock, self.period = tuple(joints), clock, float(period)
        self.latency = float(latency)
        self.core = JtcCore(joints, start, distro=distro, period=period, params=params, lag=lag,
                            velocity_state=velocity_state)  # fmt: skip
        self.node = rclpy.create_node(name, context=ctx, start_parameter_services=False)
        declared = {
            "joints": list(self.joints),
            "state_interfaces": ["position", "velocity"] if velocity_state else ["position"],
            "update_rate": round(1.0 / self.period),
            **{f"constraints.{j}.{k}": 0.0 for j in self.joints for k in ("trajectory", "goal")},
            **self.core.params,
        }
        for key, value in declared.items():
            self.node.declare_parameter(key, value)
        self.node.create_service(GetParameters, f"/{name}/get_parameters", self._get_parameters)
        self.lock = threading.Condition()
        self.received, self.rejected, self.accepted = [], [], 0
        self.adopted: list[tuple[float, dict]] = []  # (cycle time, {"before": the point before the trajectory})
        self._pending: list = []  # (receipt time, message)
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.js = self.node.create_publisher(JointState, joint_state_topic, reliable)
        self.node.create_subscription(JointTrajectory, f"/{name}/joint_trajectory", self._on_trajectory, reliable)
        self._js_type = JointState
        self._running = True
        clock.every(self.period, self._cycle)

    @property
    def commanded(self) -> list[tuple[float, np.ndarray]]:
        return self.core.commanded

    def _get_parameters(self, request, response):
        """rclcpp's ParameterService: all the values, or none when one name is not declared."""
        names = list(request.names)
        if all(self.node.has_parameter(n) for n in names):
            response.values = [self.node.get_parameter(n).get_parameter_value() for n in names]
        return response

    # ------------------------------------------------------------------ input
    def _on_trajectory(self, msg) -> None:
        self.core.params.update(
            {k: self.node.get_parameter(k).value for k in self.core.params if self.node.has_parameter(k)}
        )
        converted = from_ros(msg)
        why = self.core.refusal(converted, self.clock())
        with self.lock:
            self.received.append(msg)
            if why is None:
                self.accepted += 1
                self.core.holding = False
                self._pending.append((self.clock(), converted))
            else:
                self.rejected.append(why)
            self.lock.notify_all()

    # ---------------------------------------------------------------- control
    def _cycle(self, now: float) -> bool:
        with self.lock:
            if not self._running:
                return False
            due = [m for r, m in self._pending if r + self.latency <= now + 1e-12]
            self._pending = [(r, m) for r, m in self._pending if r + self.latency > now + 1e-12]
        if due:
            self.core.pending = due[-1]  # validated on receipt; several due at once: the last replaces the others
        adopting = self.core.pending is not None
        self.core.cycle(now)
        if adopting:
            self.adopted.append((now, {"before": dict(self.core.traj.before)}))
        with self.lock:
            self.lock.notify_all()
        self.publish_state(now)
        return True

    def publish_state(self, now: float) -> None:
        """Publish the joints' state (the current command) stamped `now` (s)."""
        js = self._js_type(name=list(self.joints), position=[float(x) for x in self.core.command])
        ns = round(now * 1e9)
        js.header.stamp.sec, js.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        self.js.publish(js)

    # ------------------------------------------------------------------ tests
    def wait_received(self, n: int, timeout: float) -> bool:
        with self.lock:
            return self.lock.wait_for(lambda: len(self.received) >= n, timeout)

    def stop(self) -> None:
        with self.lock:
            self._running = False

    def destroy(self) -> None:
        self.stop()
        self.node.destroy_node()
