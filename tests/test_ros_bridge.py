"""`crtraj ros-bridge`: the ROS 2 bridge on a real rclpy context on loopback (the [ros] extra).

A second node in the same process plays the robot: it executes every JointTrajectory it receives
exactly (its JointState echoes the last point, stamped at its time) and publishes the scene's true
obstacles as SPHERE markers. The bridge runs on a virtual clock (`feed_clock.VirtualClock`), so no
outcome depends on the machine's speed; every wait has a generous hang bound only.
"""

from __future__ import annotations

import math
import os
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import require_module
from feed_clock import VirtualClock

from crtraj.app.replan import loop_from_problem
from crtraj.app.ros_bridge import RosBridgeRequest, run_ros_bridge
from crtraj.control.horizon import ReplanOptions
from crtraj.control.ports import DeviceError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.ros.device import RosDevice
from crtraj.hardware.ros.node import RosNode, ros_environment
from crtraj.hardware.ros.options import RosOptions
from crtraj.hardware.verify import FrameVerifier
from crtraj.io.problem import Problem
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model
from crtraj.world.feed import ObstacleFeed
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PAPER = ROOT / "problems" / "paper_dynamic.toml"
HANG = 60.0  # s: a guard against hangs, never a timing window
DOMAIN = 10 + os.getpid() % 90  # one ROS domain per test run


def _problem(tmp_path: Path, extra: str = "") -> Path:
    """paper_dynamic.toml with its robot path made absolute and a [ros] section on this run's domain."""
    text = PAPER.read_text().replace('robot = "robots/cdsr2.toml"', f'robot = "{ROOT / "problems/robots/cdsr2.toml"}"')
    text += f"\n[ros]\ndomain_id = {DOMAIN}\nmax_age = 0.35\njoint_state_timeout = {HANG}\nstart_timeout = {HANG}\n"
    p = tmp_path / "paper_dynamic_ros.toml"
    p.write_text(text + extra)
    return p


class RobotNode:
    """The robot side: executes each trajectory exactly and echoes its last point as a JointState stamped
    at that point's time; publishes the scene's true obstacles (stamped at each trajectory's start)
    until `stop_markers` s. Records every trajectory received: (start s, offsets s, positions, velocities)."""

    def __init__(self, ros: RosOptions, names, scene: Scene, start: np.ndarray, stop_markers: float = math.inf):
        rclpy = require_module("rclpy", "pip install -e '.[ros]'")
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory
        from visualization_msgs.msg import MarkerArray

        self.ros, self.names, self.scene, self.stop_markers = ros, tuple(names), scene, stop_markers
        self.position = np.asarray(start, dtype=float)
        self.received: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = []
        self.arrived = threading.Condition()
        self._last_marker = -math.inf
        ros_environment(ros)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=ros.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("robot", context=self.ctx)
        qos = QoSProfile(depth=ros.depth)
        self.js = self.node.create_publisher(JointState, ros.joint_state_topic, qos)
        self.mk = self.node.create_publisher(MarkerArray, ros.obstacle_topic, qos)
        self.node.create_subscription(JointTrajectory, ros.trajectory_topic, self._on_trajectory, qos)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def wait_matched(self, obstacles: bool = True) -> None:
        """Block until the bridge subscribes (a hang bound only), then publish the state at time 0."""
        done = threading.Event()
        for _ in range(int(HANG / 0.02)):
            if self.js.get_subscription_count() and (not obstacles or self.mk.get_subscription_count()):
                done.set()
                break
            done.wait(0.02)
        assert done.is_set(), "the bridge never subscribed"
        if obstacles:
            self.publish_obstacles(0.0)
        self.publish_state(0.0)

    def publish_state(self, t: float) -> None:
        from sensor_msgs.msg import JointState

        msg = JointState(name=list(self.names), position=[float(v) for v in self.position])
        msg.header.stamp = _stamp(t)
        self.js.publish(msg)

    def publish_obstacles(self, t: float) -> None:
        if t <= self._last_marker or t >= self.stop_markers:
            return
        self._last_marker = t
        self.mk.publish(spheres(self.ros.frame_id, self.scene, t))

    def _on_trajectory(self, msg) -> None:
        start = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        offs = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec for p in msg.points])
        P = np.array([list(p.positions) for p in msg.points])
        V = np.array([list(p.velocities) for p in msg.points])
        assert list(msg.joint_names) == list(self.names)
        self.publish_obstacles(start)
        self.position = P[-1]
        self.publish_state(start + offs[-1])
        with self.arrived:
            self.received.append((start, offs, P, V))
            self.arrived.notify_all()

    def wait_received(self, n: int) -> bool:
        with self.arrived:
            return self.arrived.wait_for(lambda: len(self.received) >= n, HANG)

    def close(self) -> None:
        import rclpy

        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(HANG)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _stamp(t: float):
    from builtin_interfaces.msg import Time

    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def spheres(frame: str, scene: Scene, t: float, **override):
    """The scene's obstacles at t as SPHERE markers (ns = name, metres)."""
    from visualization_msgs.msg import Marker, MarkerArray

    centers, radii = scene.states(t)
    out = []
    for o, c, r in zip(scene.obstacles, centers, radii, strict=True):
        m = Marker(ns=o.name, id=0, type=2, action=0)
        m.header.frame_id, m.header.stamp = frame, _stamp(t)
        m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) / 1000.0 for v in c)
        m.scale.x = m.scale.y = m.scale.z = 2.0 * float(r) / 1000.0
        for k, v in override.items():
            setattr(m, k, v)
        out.append(m)
    return MarkerArray(markers=out)


@pytest.fixture(scope="module")
def paper():
    """(problem, actuators, scene, model, the robot's start values) of the paper's simulation 2."""
    require_module("rclpy", "pip install -e '.[ros]'")
    problem = Problem.load(PAPER)
    loop = loop_from_problem(problem)
    acts = Actuators.from_robot(problem.robot)
    start = acts.command(loop.tracker.initial_command(loop.x_start))
    return problem, acts, loop.scene, loop.model, start


def _body_distance(model: Model, scene: Scene, acts: Actuators, T: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Independent dense check: distance (mm) of the body surface to the true obstacles at each (T, values)."""
    X = model.robot.config(acts.actuation(values))
    P = model.points(X, 60)  # (S, 60, 3)
    C, R = scene.states(T)  # (S, m, 3), (S, m)
    d = np.linalg.norm(P[:, :, None, :] - C[:, None, :, :], axis=-1) - R[:, None, :] - model.robot.body_radius
    return d.min(axis=(1, 2))


def _executed(robot: RobotNode, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every commanded point from `start`, 8 linear sub-samples between consecutive points: (times, values)."""
    T = [robot.received[0][0]]
    V = [start]
    for start, offs, P, _ in robot.received:
        for t1, p1 in zip(start + offs, P, strict=True):
            s = np.linspace(0, 1, 9)[1:]
            T.extend(T[-1] + s * (t1 - T[-1]))
            V.extend(V[-1] + s[:, None] * (p1 - V[-1]))
    return np.array(T), np.array(V)


@pytest.mark.slow
def test_round_trip_reaches_the_goal_without_collision(tmp_path, paper):
    problem, acts, scene, model, start = paper
    path = _problem(tmp_path)
    ros = Problem.load(path).options(RosOptions, "ros")
    clock = VirtualClock()
    robots = []

    def ready(node, feed):
        robots.append(RobotNode(ros, acts.names, scene, start))
        robots[0].wait_matched()

    try:
        code = run_ros_bridge(
            RosBridgeRequest(path, out=tmp_path / "run", html=False, quiet=True),
            clock=clock,
            sleep=clock.sleep,
            ready=ready,
        )
    finally:
        for r in robots:
            r.close()
    robot = robots[0]
    assert code == 0
    res = read_result(tmp_path / "run" / "run.json")
    assert res.success and res.collisions == 0 and res.data["device"]["moves"] == len(
        [r for r in robot.received if len(r[1]) == ros.points_per_step]
    )
    moves = [r for r in robot.received if len(r[1]) == ros.points_per_step]
    assert len(moves) > 50
    # the trajectories carry the verified timing: points every dt / points_per_step, velocities of the servo model
    dt = problem.options(ReplanOptions, "replan").dt
    for _, offs, P, V in moves:
        assert np.allclose(offs, dt * np.arange(1, ros.points_per_step + 1) / ros.points_per_step)
        assert np.all(np.isfinite(V)) and P.shape == V.shape == (ros.points_per_step, acts.n)
    # the echoed motion reaches the goal ...
    tip = model.tip_position(model.robot.config(acts.actuation(robot.position)))
    goal = np.array([10.0, -120.0, 170.0])
    assert np.linalg.norm(tip - goal) <= 0.5 + 1e-6
    # ... and, densely checked against the true breathing spheres, never touches them
    T, V = _executed(robot, start)
    d = _body_distance(model, scene, acts, T, V)
    assert np.all(d > 0.0), f"collision: min distance {d.min():.3f} mm at t={T[np.argmin(d)]:.2f} s"
    assert d.min() > scene.safety_distance - 1.0
    assert len(threading.enumerate()) >= 1
    assert not [t for t in threading.enumerate() if t.name == "crtraj-ros-spin"]
