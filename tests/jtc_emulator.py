"""A joint_trajectory_controller emulator for the ROS bridge tests: an rclpy node that does what the stock
ros2_controllers JTC documents for its topic interface, written here without crtraj's controller model.

- Subscribes ``/<name>/joint_trajectory`` (reliable). Each message is checked on receipt: joint names (all
  of the controller's, no others), at least one point, positions of every joint at every point,
  velocities / accelerations empty or one per joint, no efforts, strictly increasing time_from_start, a
  non-zero stamp whose last point is in the past, and (unless ``allow_nonzero_velocity_at_trajectory_end``)
  non-zero velocity at the last point. Refusals are recorded in `rejected`.
- At its first control cycle at least `latency` s after receipt (0: the next cycle) an accepted message
  replaces the current trajectory at once. The point before the trajectory is the state as the controller
  reads it at the start of that update (perfect tracking: the command of `lag` s before, one control period
  by default, as ros2_control reads state before it writes the command; with its velocity and
  acceleration), stamped with the cycle time; stamp 0 means the cycle time.
- Each cycle samples the trajectory: the segment before the first point from the point before, then the
  segment that contains the time; each segment linear, cubic or quintic by what both ends carry (its
  polynomial solved from the boundary conditions); after the end, the last point.
- It commands that (perfect tracking), records (time, positions) in `commanded`, and publishes
  sensor_msgs/JointState stamped with the cycle time.
- Its parameters (``joints``, ``interpolation_method``, ...) are declared, so ``/<name>/get_parameters``
  answers as the real controller's does.

Control cycles run on the test's virtual clock (`feed_clock.VirtualClock.every`), so what it commands
never depends on the machine's speed. Units: whatever the messages carry (rad, m), s.
"""

from __future__ import annotations

import itertools
import threading

import numpy as np


def _seconds(t) -> float:
    return float(t.sec) + 1e-9 * float(t.nanosec)


def _polynomial(t0: float, a: dict, t1: float, b: dict, kind: int) -> np.ndarray:
    """Coefficients (kind+1, n), lowest power first, in tau = t - t0, from position (and velocity, and
    acceleration) conditions at both ends, by solving the linear system."""
    h = t1 - t0
    rows, rhs = [], []
    for tau, s in ((0.0, a), (h, b)):
        for order, key in enumerate(("p", "v", "a")[: (kind + 1) // 2]):
            row = [0.0] * (kind + 1)
            for k in range(order, kind + 1):
                coef = 1.0
                for j in range(order):
                    coef *= k - j
                row[k] = coef * tau ** (k - order)
            rows.append(row)
            rhs.append(s[key])
    return np.linalg.solve(np.array(rows), np.array(rhs))


def _evaluate(c: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k = np.arange(len(c))
    p = (tau**k) @ c
    v = (k[1:] * tau ** (k[1:] - 1)) @ c[1:]
    a = (k[2:] * (k[2:] - 1) * tau ** (k[2:] - 2)) @ c[2:] if len(c) > 2 else np.zeros(c.shape[1])
    return p, v, a


def _segment(t0: float, a: dict, t1: float, b: dict, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One segment at time t, as the controller interpolates it."""
    if t1 - t0 <= 0.0:
        return b["p"], np.zeros_like(b["p"]), np.zeros_like(b["p"])
    tau = min(max(t - t0, 0.0), t1 - t0)
    if a.get("v") is not None and b.get("v") is not None:
        kind = 5 if a.get("a") is not None and b.get("a") is not None else 3
    else:
        kind = 1
    return _evaluate(_polynomial(t0, a, t1, b, kind), tau)


class JtcEmulator:
    """The emulated controller. joints: its joint names; start: the joints' positions at rest; clock: the
    test's `VirtualClock`; period: its control period (s)."""

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
        allow_nonzero_velocity_at_trajectory_end=False,
        lag=None,
        latency=0.0,
    ):
        import rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        self.joints, self.clock, self.period = tuple(joints), clock, float(period)
        self.lag = self.period if lag is None else float(lag)
        self.latency = float(latency)
        self.allow_nonzero_end = allow_nonzero_velocity_at_trajectory_end
        self.node = rclpy.create_node(name, context=ctx)
        for key, value in (
            ("joints", list(self.joints)),
            ("interpolation_method", "splines"),
            ("allow_nonzero_velocity_at_trajectory_end", allow_nonzero_velocity_at_trajectory_end),
            ("allow_partial_joints_goal", False),
            ("open_loop_control", True),
            ("state_interfaces", ["position", "velocity"]),
        ):
            self.node.declare_parameter(key, value)
        self.lock = threading.Condition()
        self.received, self.rejected, self.accepted = [], [], 0
        self.commanded: list[tuple[float, np.ndarray]] = []
        self.adopted: list[tuple[float, dict]] = []  # (cycle time, the message as adopted)
        self._pending: list = []  # (receipt time, message)
        self._history: list = []  # (cycle time, state commanded then), the last few cycles
        self._active = None  # (time before, state before, start time, points)
        self._state = {"p": np.asarray(start, dtype=float), "v": np.zeros(len(start)), "a": np.zeros(len(start))}
        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.js = self.node.create_publisher(JointState, joint_state_topic, reliable)
        self.node.create_subscription(JointTrajectory, f"/{name}/joint_trajectory", self._on_trajectory, reliable)
        self._js_type = JointState
        self._running = True
        clock.every(self.period, self._cycle)

    # ------------------------------------------------------------------ input
    def _on_trajectory(self, msg) -> None:
        why = self._refusal(msg, self.clock())
        with self.lock:
            self.received.append(msg)
            if why is None:
                self.accepted += 1
                self._pending.append((self.clock(), msg))
            else:
                self.rejected.append(why)
            self.lock.notify_all()

    def _refusal(self, msg, now: float) -> str | None:
        names, n = list(msg.joint_names), len(self.joints)
        if not names or len(names) != n or sorted(names) != sorted(self.joints):
            return f"joints {names} do not match {list(self.joints)}"
        if not msg.points:
            return "empty trajectory"
        stamp = _seconds(msg.header.stamp)
        if stamp != 0.0 and stamp + _seconds(msg.points[-1].time_from_start) < now:
            return "ends in the past"
        for k, p in enumerate(msg.points):
            if len(p.positions) != n or len(p.velocities) not in (0, n) or len(p.accelerations) not in (0, n):
                return f"point {k}: wrong sizes"
            if len(p.effort):
                return f"point {k}: effort"
            if k and not _seconds(p.time_from_start) > _seconds(msg.points[k - 1].time_from_start):
                return f"point {k}: time_from_start not strictly increasing"
        last = msg.points[-1].velocities
        if not self.allow_nonzero_end and len(last) and any(v != 0.0 for v in last):
            return "non-zero velocity at the end"
        return None

    # ---------------------------------------------------------------- control
    def _cycle(self, now: float) -> bool:
        with self.lock:
            if not self._running:
                return False
            due = [m for r, m in self._pending if r + self.latency <= now + 1e-12]
            self._pending = [(r, m) for r, m in self._pending if r + self.latency > now + 1e-12]
        if due:
            self._adopt(due[-1], now)  # several due at once: the last replaces the others
        if self._active is not None:
            p, v, a = self._sample(now)
            self._state = {"p": p, "v": v, "a": a}
        self._history = [*self._history[-64:], (now, dict(self._state))]
        with self.lock:
            self.commanded.append((now, self._state["p"].copy()))
            self.lock.notify_all()
        self.publish_state(now)
        return True

    def publish_state(self, now: float) -> None:
        """Publish the joints' state (the current command) stamped `now` (s)."""
        js = self._js_type(name=list(self.joints), position=[float(x) for x in self._state["p"]])
        ns = round(now * 1e9)
        js.header.stamp.sec, js.header.stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        self.js.publish(js)

    def _adopt(self, msg, now: float) -> None:
        order = [list(msg.joint_names).index(j) for j in self.joints]
        stamp = _seconds(msg.header.stamp)
        start = now if stamp == 0.0 else stamp
        points = []
        for p in msg.points:
            pt = {"t": start + _seconds(p.time_from_start), "p": np.array(p.positions)[order]}
            pt["v"] = np.array(p.velocities)[order] if len(p.velocities) else None
            pt["a"] = np.array(p.accelerations)[order] if len(p.accelerations) else None
            points.append(pt)
        before = self._state_read(now)
        self._active = (now, before, points)
        self.adopted.append((now, {"before": before, "points": points}))

    def _state_read(self, now: float) -> dict:
        """The state the controller reads at the start of its update at `now`: the command of `lag` s before
        (the newest cycle at or before then; the start state before the first cycle). Lag 0: the old
        trajectory's command at `now` itself (an idealised controller)."""
        if self.lag <= 0.0 and self._active is not None:
            p, v, a = self._sample(now)
            return {"p": p, "v": v, "a": a}
        old = [st for t, st in self._history if t <= now - self.lag + 1e-12]
        return dict(old[-1]) if old else dict(self._state if not self._history else self._history[0][1])

    def _sample(self, t: float):
        t_before, before, points = self._active
        if t < points[0]["t"]:
            return _segment(t_before, before, points[0]["t"], points[0], t)
        for a, b in itertools.pairwise(points):
            if a["t"] <= t < b["t"]:
                return _segment(a["t"], a, b["t"], b, t)
        last = points[-1]
        zero = np.zeros_like(last["p"])
        return last["p"], (zero if last["v"] is None else last["v"]), zero

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
