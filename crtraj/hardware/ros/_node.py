"""The ROS 2 node of the bridge: one private rclpy context, its publishers and subscriptions, spun on a thread.

`RosNode` sets up what the pip wheels need (`ros_environment`), starts its own `rclpy` context on the
``[ros]`` domain (localhost-only discovery by default) and spins it on one background thread until
`close`. It publishes trajectories and RViz markers, keeps the newest joint state (waiters block on
a condition, never poll), and hands live obstacles (SPHERE markers) to the same
`crtraj.world.feed.ObstacleFeed` that takes the UDP JSON feed, so staleness, velocity fits and the
message checks are one code path. Every callback treats its message as hostile: a bad one is
counted and recorded (`events`), never raised. Units: s, actuator values in rad / mm.
"""

from __future__ import annotations

import json
import os
import threading
import time
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.ros._messages import (
    MAX_JOINTS,
    MAX_NAME,
    RejectedError,
    joint_state_values,
    marker_obstacles,
    parameter_value,
    si_scale,
    tip_path,
    trajectory,
)
from crtraj.hardware.ros._options import RosOptions

MAX_EVENTS = 1000  # rejected messages kept (the counts stay exact beyond it)
DEFAULT_RMW = "rmw_fastrtps_cpp"  # the RMW wheel the [ros] extra installs
# parameter requests in flight at once: a service's default QoS keeps the last 10 requests and drops older ones
PARAMETER_WINDOW = 8


def ros_environment(options: RosOptions) -> dict[str, str]:
    """Set the environment rclpy reads at init (only what is not set already, except the discovery
    range, which follows ``ros.discovery``); returns what it set. LD_LIBRARY_PATH needs no help: the
    wheels' bootstrapper sets it when Python starts."""
    want = {
        "RMW_IMPLEMENTATION": os.environ.get("RMW_IMPLEMENTATION") or DEFAULT_RMW,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST" if options.discovery == "localhost" else "SUBNET",
    }
    changed = {k: v for k, v in want.items() if os.environ.get(k) != v}
    os.environ.update(changed)
    return changed


# The highest ROS domain id (as ``[ros] domain_id`` is bounded): Fast DDS derives UDP ports from it and
# ends the process, in C, on one beyond its port range.
MAX_DOMAIN_ID = 232


def domain_id(options: RosOptions, environ: Any = None) -> int | None:
    """The domain the node joins: ``ros.domain_id``, else ``$ROS_DOMAIN_ID`` checked to be an integer in
    0..`MAX_DOMAIN_ID` (one-line `InputError` naming it otherwise), else None (rclpy's default, 0)."""
    if options.domain_id is not None:
        return options.domain_id
    raw = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return None
    # isascii + isdecimal: int() takes other scripts' digits, which ROS's own reader does not
    if not (raw.isascii() and raw.isdecimal() and len(raw) <= 3 and int(raw) <= MAX_DOMAIN_ID):
        raise InputError(f"ROS_DOMAIN_ID: must be an integer in 0..{MAX_DOMAIN_ID}, got {raw[:20]!r}")
    return int(raw)


class RosNode:
    """The bridge's node. actuators: the robot's `crtraj.hardware.actuators.Actuators` (their names are
    the joint names); feed: the `ObstacleFeed` that live SPHERE markers go to (None: markers are not
    subscribed). Joint values on the wire are in SI units as ROS expects (rad for the servos, m for
    the base stage); this class converts to and from crtraj's (rad, mm). Joint names on the wire are
    the robot's (``ros.joints`` maps the actuators' names to them). recorder: an object with
    ``write(topic, msg, ns)`` (`crtraj.hardware.ros._record.McapRecorder`) that gets every message sent
    and received. Raises `InputError` (one line) when rclpy or the message packages are missing or the
    context cannot start."""

    def __init__(
        self, options: RosOptions, actuators: Any, feed: Any = None, name: str = "crtraj", recorder: Any = None
    ) -> None:
        self.options = options
        self.names = tuple(options.joint_name(a) for a in actuators.names)
        self.recorder = recorder
        self.seen_names: tuple[str, ...] | None = None  # of the last JointState refused for its names
        self.si = si_scale(actuators.units)
        self.feed = feed
        ros_environment(options)
        domain = domain_id(options)
        try:
            import rclpy
            from nav_msgs.msg import Path
            from rclpy.executors import SingleThreadedExecutor
            from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
            from rclpy.signals import SignalHandlerOptions
            from sensor_msgs.msg import JointState
            from trajectory_msgs.msg import JointTrajectory
            from visualization_msgs.msg import MarkerArray
        except ImportError as exc:
            raise InputError(f"ros: needs the [ros] extra (pip install -e '.[ros]'): {exc}") from None
        self._lock = threading.Lock()
        self._fresh = threading.Condition(self._lock)
        self.counts: dict[str, int] = {}
        self._events: list[dict[str, Any]] = []
        self.joint_states = 0  # accepted
        self.marker_arrays = 0  # received
        self.published = 0  # trajectories
        self._state: tuple[np.ndarray, float] | None = None
        self._stop = threading.Event()
        self._ctx = rclpy.Context()
        try:
            # Ctrl-C stays a KeyboardInterrupt of the main thread: the loop holds the robot on it
            rclpy.init(context=self._ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
            self.node = rclpy.create_node(name, context=self._ctx)
            rel = ReliabilityPolicy.RELIABLE if options.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=options.depth, reliability=rel)
            n = self.node
            self._traj = n.create_publisher(JointTrajectory, options.trajectory_topic_name, qos)
            self._markers = n.create_publisher(MarkerArray, options.markers_topic, qos)
            self._path = n.create_publisher(Path, options.path_topic, qos)
            n.create_subscription(JointState, options.joint_state_topic, self._on_joint_state, qos)
            if feed is not None:
                n.create_subscription(MarkerArray, options.obstacle_topic, self._on_markers, qos)
            self._executor = SingleThreadedExecutor(context=self._ctx)
            self._executor.add_node(n)
        except Exception as exc:
            rclpy.try_shutdown(context=self._ctx)
            raise InputError(f"ros: cannot start the node: {str(exc).splitlines()[0][:200]}") from None
        self._thread = threading.Thread(target=self._spin, name="crtraj-ros-spin", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------- lifetime
    def _spin(self) -> None:
        while not self._stop.is_set() and self._ctx.ok():
            try:
                self._executor.spin_once(timeout_sec=0.05)
            except Exception as exc:  # a shut-down context ends the spin; anything else is recorded
                if self._stop.is_set() or not self._ctx.ok():
                    return
                self._reject("internal", f"spin: {type(exc).__name__}")

    def close(self) -> None:
        """Stop spinning, destroy the node and shut the context down (idempotent)."""
        import rclpy

        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(10.0)
        self._executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self._ctx)
        with self._fresh:
            self._fresh.notify_all()

    def __enter__(self) -> RosNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def domain_id(self) -> int:
        """The ROS domain the node joined (``ros.domain_id``, else ROS_DOMAIN_ID, else 0)."""
        return int(self._ctx.get_domain_id())

    @property
    def alive(self) -> bool:
        """The spin thread runs."""
        return self._thread.is_alive()

    @property
    def context_ok(self) -> bool:
        """The node's rclpy context is still up (False after `close`)."""
        return bool(self._ctx.ok())

    # ------------------------------------------------------------- input
    def _reject(self, kind: str, message: str) -> None:
        with self._lock:
            self.counts[kind] = self.counts.get(kind, 0) + 1
            if len(self._events) < MAX_EVENTS:
                self._events.append({"received": time.monotonic(), "kind": kind, "message": message})

    def _record(self, topic: str, msg: Any) -> None:
        if self.recorder is not None:
            self.recorder.write(topic, msg, time.time_ns())

    def _on_joint_state(self, msg: Any) -> None:
        self._record(self.options.joint_state_topic, msg)
        try:
            values, stamp = joint_state_values(msg, self.names)
            values = values / self.si
        except RejectedError as exc:
            if exc.kind == "unknown_name" and len(msg.name) <= MAX_JOINTS:
                self.seen_names = tuple(str(n)[:MAX_NAME] for n in msg.name)
            self._reject(exc.kind, str(exc))
            return
        except Exception as exc:  # the node must outlive any message
            self._reject("internal", f"joint_state: {type(exc).__name__} while reading it")
            return
        with self._fresh:
            if self._state is not None and stamp < self._state[1]:
                self.counts["out_of_order"] = self.counts.get("out_of_order", 0) + 1
                return
            self._state = (values, stamp)
            self.joint_states += 1
            self._fresh.notify_all()

    def _on_markers(self, msg: Any) -> None:
        self._record(self.options.obstacle_topic, msg)
        self.marker_arrays += 1
        try:
            states, refused = marker_obstacles(msg, self.options.frame_id)
        except RejectedError as exc:
            self._reject(exc.kind, str(exc))
            return
        except Exception as exc:
            self._reject("internal", f"markers: {type(exc).__name__} while reading them")
            return
        for r in refused:
            self._reject(r.kind, str(r))
        for state in states:
            # one message per sphere (a whole array could exceed the feed's datagram limit): the UDP
            # feed's own gate checks it again and keeps the tracks (one code path)
            self.feed.ingest(json.dumps(state, allow_nan=True).encode("utf-8"), self.feed.clock())

    def joint_state(self) -> tuple[np.ndarray, float] | None:
        """(actuator values, stamp s) of the newest accepted joint state, or None."""
        with self._lock:
            return None if self._state is None else (self._state[0].copy(), self._state[1])

    def wait_joint_state(self, newer_than: float, timeout: float) -> tuple[np.ndarray, float] | None:
        """Block until a joint state stamped at or after `newer_than` (s) arrives; None after `timeout`
        wall-clock seconds (a hang bound) or on close."""
        with self._fresh:
            self._fresh.wait_for(
                lambda: self._stop.is_set() or (self._state is not None and self._state[1] >= newer_than), timeout
            )
            st = self._state
            if st is None or st[1] < newer_than:
                return None
            return st[0].copy(), st[1]

    # ------------------------------------------------------------- output
    def publish_trajectory(self, stamp: float, offsets: np.ndarray, values: np.ndarray, velocities: np.ndarray) -> None:
        """Publish a JointTrajectory starting at `stamp` (s): points at `offsets` (s after it) with actuator
        values (N, n) rad / mm and velocities rad/s, mm/s (sent in SI units)."""
        msg = trajectory(self.names, stamp, offsets, values * self.si, velocities * self.si)
        self._traj.publish(msg)
        self._record(self.options.trajectory_topic_name, msg)
        self.published += 1

    def publish_markers(self, msg: Any) -> None:
        self._markers.publish(msg)
        self._record(self.options.markers_topic, msg)

    def publish_path(self, stamp: float, tips: np.ndarray) -> None:
        """Publish the tip along an executed, verified curve (tips (M, 3) mm, from clock time `stamp` s) as a
        nav_msgs/Path in metres."""
        msg = tip_path(self.options.frame_id, stamp, tips)
        self._path.publish(msg)
        self._record(self.options.path_topic, msg)

    def wait_subscribers(self, timeout: float) -> bool:
        """Block until something subscribes to the trajectory topic (True), at most `timeout` wall-clock s."""
        end = time.monotonic() + timeout
        while self._traj.get_subscription_count() == 0:
            if time.monotonic() >= end or self._stop.wait(0.05):
                return self._traj.get_subscription_count() > 0
        return True

    def get_parameters(
        self, node_name: str, names: list[str], timeout: float, answer_timeout: float | None = None
    ) -> dict[str, Any] | None:
        """The values of parameters `names` of node `node_name` through its ``get_parameters`` service (None for a
        parameter it does not declare); None when the service is not found within `timeout` s, or does not answer
        every request within `answer_timeout` s more (default `timeout`). One request per name, `PARAMETER_WINDOW`
        in flight at once: rclcpp's service answers a request naming one undeclared parameter with no values at
        all, and which ones a controller declares differs per release."""
        from rcl_interfaces.srv import GetParameters

        client = self.node.create_client(GetParameters, f"/{node_name}/get_parameters")
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                return None
            end = time.monotonic() + (timeout if answer_timeout is None else answer_timeout)
            out: dict[str, Any] = {}
            for k in range(0, len(names), PARAMETER_WINDOW):
                batch = names[k : k + PARAMETER_WINDOW]
                answers = self._ask(client, batch, end)
                if answers is None:
                    return None
                out.update(zip(batch, answers, strict=True))
            return out
        finally:
            self.node.destroy_client(client)

    def _ask(self, client: Any, names: list[str], end: float) -> list[Any] | None:
        """One request per name of `names`, all in flight at once: their values (None: not declared), or None when
        they are not all answered by monotonic time `end`."""
        from rcl_interfaces.srv import GetParameters

        pending = threading.Semaphore(0)
        futures = [client.call_async(GetParameters.Request(names=[n])) for n in names]
        for f in futures:
            f.add_done_callback(lambda _: pending.release())
        for _ in futures:
            if not pending.acquire(timeout=max(end - time.monotonic(), 0.0)):
                return None
        values = [[] if f.result() is None else list(f.result().values) for f in futures]
        return [parameter_value(v[0]) if v else None for v in values]

    def matched(self) -> tuple[int, int]:
        """(subscribers of the trajectory topic, publishers of the joint-state topic) seen so far."""
        return self._traj.get_subscription_count(), self.node.count_publishers(self.options.joint_state_topic)

    def events(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self._events)

    def describe(self) -> dict[str, Any]:
        """Counters and rejected messages, as plain data for the run record."""
        with self._lock:
            return {
                "joint_states": self.joint_states,
                "marker_arrays": self.marker_arrays,
                "trajectories": self.published,
                "rejected": dict(sorted(self.counts.items())),
                "events": list(self._events),
                "options": self.options.to_dict(),
            }
