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
from conftest import PAPER, paper_copy, require_module
from feed_clock import VirtualClock

from crtraj.app.devices import RosBridgeRequest, run_ros_bridge
from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import ClosedLoop
from crtraj.control.ports import DeviceError
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.ros._device import RosDevice
from crtraj.hardware.ros._messages import si_scale
from crtraj.hardware.ros._node import RosNode, ros_environment
from crtraj.hardware.ros._options import RosOptions
from crtraj.hardware.verify import FrameVerifier
from crtraj.io.problem import Problem
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model
from crtraj.world.feed import ObstacleFeed
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
HANG = 60.0  # s: a guard against hangs, never a timing window
DOMAIN = 10 + os.getpid() % 90  # one ROS domain per test run


def _problem(tmp_path: Path, duration: float = 60.0) -> Path:
    """paper_dynamic.toml without its step deadline (`paper_copy`), a [ros] section on this run's domain (hang
    bounds only, and one more step of obstacle age than the robot's one-step latency needs) and a [loop]
    duration of `duration` s."""
    ros = {"domain_id": DOMAIN, "max_age": 0.35, "joint_state_timeout": HANG, "start_timeout": HANG}
    values = {("loop", "duration"): duration, **{("ros", k): v for k, v in ros.items()}}
    return paper_copy(tmp_path, "paper_dynamic_ros.toml", values)


class RobotNode:
    """The robot side, on the bridge's (virtual) clock: executes each trajectory exactly from its start stamp
    (a new one replaces the rest of the current one from its start, linear between points, as a trajectory
    controller does), and on each arrival publishes its joint state at that moment (in ROS units, rad and
    m) and the scene's true obstacles then, until `stop_markers` s. Records every trajectory received:
    (start s, offsets s, positions, velocities); `knots` (times, values) is the motion it executed."""

    def __init__(
        self, ros: RosOptions, names, scene: Scene, start: np.ndarray, clock=None, stop_markers: float = math.inf
    ):
        rclpy = require_module("rclpy", "pip install -e '.[ros]'")
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory
        from visualization_msgs.msg import MarkerArray

        self.ros, self.names, self.scene, self.stop_markers = ros, tuple(names), scene, stop_markers
        self.clock = clock if clock is not None else (lambda: 0.0)
        self.knots_t, self.knots_v = [0.0], [np.asarray(start, dtype=float)]
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
        self.node.create_subscription(JointTrajectory, ros.trajectory_topic_name, self._on_trajectory, qos)
        self.view: list = []  # the bridge's RViz markers
        self.node.create_subscription(MarkerArray, ros.markers_topic, self._on_view, qos)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def position_at(self, t) -> np.ndarray:
        """The executed position(s) at time(s) t (s)."""
        T, V = np.array(self.knots_t), np.array(self.knots_v)
        return np.stack([np.interp(t, T, V[:, i]) for i in range(V.shape[1])], axis=-1)

    @property
    def position(self) -> np.ndarray:
        return self.knots_v[-1]

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

        msg = JointState(name=list(self.names), position=[float(v) for v in self.position_at(t)])
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
        now = self.clock()
        with self.arrived:
            at_start = self.position_at(start)
            keep = [k for k, t in enumerate(self.knots_t) if t < start]
            self.knots_t = [self.knots_t[k] for k in keep] + [start, *(start + offs)]
            self.knots_v = [self.knots_v[k] for k in keep] + [at_start, *P]
            self.received.append((start, offs, P, V))
            self.arrived.notify_all()
        self.publish_obstacles(now)
        self.publish_state(now)

    def _on_view(self, msg) -> None:
        with self.arrived:
            self.view.append(msg)
            self.arrived.notify_all()

    def wait_view(self, stamp: float) -> bool:
        """Block until an RViz MarkerArray stamped `stamp` (s) arrived (a hang bound only)."""

        def seen() -> bool:
            return any(
                abs(m.markers[0].header.stamp.sec + 1e-9 * m.markers[0].header.stamp.nanosec - stamp) < 1e-6
                for m in self.view
            )

        with self.arrived:
            return self.arrived.wait_for(seen, HANG)

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
    """(problem, actuators, scene, model, the robot's start values, servo model) of the paper's simulation 2."""
    require_module("rclpy", "pip install -e '.[ros]'")
    problem = Problem.load(PAPER)
    loop = ClosedLoop.from_problem(problem)
    acts = Actuators.from_robot(problem.robot)
    start = acts.command(loop.start_command())
    return problem, acts, loop.scene, loop.model, start, loop.servo


def _body_distance(model: Model, scene: Scene, acts: Actuators, T: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Independent dense check: distance (mm) of the body surface to the true obstacles at each (T, values)."""
    X = model.robot.config(acts.actuation(values))
    P = model.points(X, 60)  # (S, 60, 3)
    C, R = scene.states(T)  # (S, m, 3), (S, m)
    d = np.linalg.norm(P[:, :, None, :] - C[:, None, :, :], axis=-1) - R[:, None, :] - model.robot.body_radius
    return d.min(axis=(1, 2))


def _executed(robot: RobotNode) -> tuple[np.ndarray, np.ndarray]:
    """The robot's executed motion, 8 linear sub-samples between its knots: (times, values) in ROS units."""
    T = np.array(robot.knots_t)
    s = np.linspace(0.0, 1.0, 9)[:-1]
    dense = np.append((T[:-1, None] + s * np.diff(T)[:, None]).ravel(), T[-1])
    return dense, robot.position_at(dense)


def _in_step(robots, nodes, clock: VirtualClock, dt: float) -> None:
    """The bridge's sleep on virtual time: the robot takes each trajectory before the clock moves on (a
    robot as fast as real time), so every run is the same whatever the machine's load."""
    if robots and nodes:
        assert robots[0].wait_received(nodes[0].published)
    clock.sleep(dt)


def _bridge_with_robot(path, ros, acts, scene, start, tmp_path, **robot_options):
    """`run_ros_bridge` on a virtual clock against a `RobotNode` started once the bridge's node is up:
    (exit code, the robot node)."""
    clock = VirtualClock()
    robots, nodes = [], []

    def ready(node, feed):
        nodes.append(node)
        robots.append(RobotNode(ros, acts.names, scene, start * si_scale(acts.units), clock, **robot_options))
        robots[0].wait_matched()

    try:
        code = run_ros_bridge(
            RosBridgeRequest(path, out=tmp_path / "run", html=False, quiet=True),
            clock=clock,
            sleep=lambda dt: _in_step(robots, nodes, clock, dt),
            ready=ready,
        )
    finally:
        for r in robots:
            r.close()
    return code, robots[0]


@pytest.mark.slow
def test_round_trip_reaches_the_goal_without_collision(tmp_path, paper):
    problem, acts, scene, model, start, _ = paper
    path = _problem(tmp_path)
    ros = Problem.load(path).options(RosOptions, "ros")
    code, robot = _bridge_with_robot(path, ros, acts, scene, start, tmp_path)
    assert code == 0
    res = read_result(tmp_path / "run" / "run.json")
    stream = res.data["stream"]
    assert res.success and res.collisions == 0 and stream["moves"] + stream["holds"] == len(robot.received)
    assert stream["moves"] > 50
    # the run's limit figures are those of the curves published (each passed the verifier's limits)
    s = res.data["summary"]
    assert 0.0 < s["max_velocity_fraction"] <= 1.0 + 1e-9 and 0.0 < s["max_acceleration_fraction"] <= 1.0 + 1e-9
    # every message starts at its stamp, its points strictly increasing in time, and ends at rest (the stop tail)
    dt = problem.options(ReplanOptions, "replan").dt
    for _, offs, P, V in robot.received:
        assert offs[0] == 0.0 and np.all(np.diff(offs) > 0.0) and np.all(V[-1] == 0.0)
        assert np.all(np.isfinite(V)) and P.shape == V.shape
    moves = [r for r in robot.received if len(r[1]) >= ros.points_per_step + 2]
    # a step's points are dt / points_per_step apart
    assert any(np.allclose(np.diff(r[1])[-ros.points_per_step - 1 : -1], dt / ros.points_per_step) for r in moves)
    # the echoed motion reaches the goal ...
    tip = model.tip_position(model.robot.config(acts.actuation(robot.position / si_scale(acts.units))))
    goal = np.array([10.0, -120.0, 170.0])
    assert np.linalg.norm(tip - goal) <= 0.5 + 1e-6
    # ... and, densely checked against the true breathing spheres, never touches them
    T, V = _executed(robot)
    d = _body_distance(model, scene, acts, T, V / si_scale(acts.units))
    assert np.all(d > 0.0), f"collision: min distance {d.min():.3f} mm at t={T[np.argmin(d)]:.2f} s"
    assert d.min() > scene.safety_distance - 1.0
    print(f"executed: {len(moves)} steps, min body-obstacle distance {d.min():.2f} mm over {len(T)} samples")
    assert not [t for t in threading.enumerate() if t.name == "crtraj-ros-spin"]
    # RViz: the last step's body (a line strip as thick as the body, m) ends at the tip; one sphere per obstacle
    t_end = moves[-1][0] + moves[-1][1][-2]  # the end of the last step (its stop tail follows)
    assert robot.wait_view(t_end)
    view = next(
        m
        for m in robot.view
        if abs(m.markers[0].header.stamp.sec + 1e-9 * m.markers[0].header.stamp.nanosec - t_end) < 1e-6
    )
    body = [m for m in view.markers if m.type == 4]
    spheres_ = [m for m in view.markers if m.type == 2]
    assert len(body) == 1 and len(spheres_) == len(scene.obstacles)
    assert all(m.header.frame_id == ros.frame_id for m in view.markers)
    end = body[0].points[-1]
    # the body drawn for the last step ends where the robot came to rest (its stop tail settles within 0.01 mm)
    assert np.allclose(1000.0 * np.array([end.x, end.y, end.z]), tip, atol=1e-2)
    assert body[0].scale.x == pytest.approx(2e-3 * model.robot.body_radius)


def _children() -> list[int]:
    """Pids of this process's child processes."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == os.getpid():
                out.append(int(d))
    return out


def test_stale_markers_hold_the_robot(tmp_path, paper):
    _, acts, scene, _, start, _ = paper
    path = _problem(tmp_path, duration=2.0)
    ros = Problem.load(path).options(RosOptions, "ros")
    stop = 0.5  # the obstacles go silent here
    code, robot = _bridge_with_robot(path, ros, acts, scene, start, tmp_path, stop_markers=stop)
    assert code == 1  # the goal was not reached: the robot was held
    res = read_result(tmp_path / "run" / "run.json")
    status = [w.get("status") for w in res.data["waypoints"][1:]]
    t = np.array([w["t"] for w in res.data["waypoints"][1:]]) - 0.1  # each step's start
    stale = t >= stop + ros.max_age + 0.1 + 1e-9  # a state measured before `stop` is too old from here on
    assert all(s == "stale" for s in np.array(status)[stale]) and stale.sum() >= 5
    assert all(s != "stale" for s in np.array(status)[t < stop + ros.max_age - 0.1])
    # held: from the first stale step on, nothing but holds: the last move's curve to its stop tail's rest point
    first = float(t[np.argmax(stale)]) + ros.lead  # when that step would have started (it is sent lead s ahead)
    k = res.data["stream"]["moves"]
    moves, holds = robot.received[:k], robot.received[k:]
    assert all(t0 < first - 1e-9 for t0, *_ in moves)
    rest = moves[-1][2][-1]  # where the last move's stop tail comes to rest
    assert np.all(moves[-1][3][-1] == 0.0)
    assert len(holds) >= stale.sum()
    assert all(np.all(V[-1] == 0.0) and np.allclose(P[-1], rest, rtol=1e-12, atol=1e-15) for _, _, P, V in holds)
    assert res.data["stream"]["holds"] >= stale.sum()


def test_unsafe_steps_are_refused_and_never_published(paper):
    problem, acts, scene, model, start, servo = paper
    ros = RosOptions(domain_id=DOMAIN, joint_state_timeout=HANG, start_timeout=HANG)
    node = RosNode(ros, acts)
    robot = RobotNode(ros, acts.names, scene, start * si_scale(acts.units))
    try:
        robot.wait_matched(obstacles=False)
        tip = model.tip_position(model.robot.config(acts.actuation(start)))
        on_tip = scene.with_obstacles([Obstacle(center=tuple(tip), radius=10.0, name="on_tip")])
        free = scene.with_obstacles(())
        clock = VirtualClock()

        def device(sc, lead=0.0):
            ver = FrameVerifier(problem.robot, acts, sc, 0.1 / ros.points_per_step, model=model)
            return RosDevice(node, acts, model, servo, 0.1, ver, lambda: sc, clock=clock, sleep=clock.sleep, lead=lead)

        blocked, fast, late, ahead = device(on_tip), device(free), device(free, 0.1), device(free, 1.0)
        si = si_scale(acts.units)
        q0 = blocked.start_actuation()
        assert np.allclose(acts.command(q0), start)
        for d in (fast, late, ahead):
            d.start_actuation()
        still = np.repeat(q0[None], 5, axis=0)
        # 1. the body would come closer than D_sf to an obstacle
        with pytest.raises(DeviceError, match="body closer than the safety distance"):
            blocked.move(0.0, q0, still, 0.02)
        # 2. too fast for the servos
        jump = q0.copy()
        jump[0] += 5.0  # mm of cable in one step, within the position limits: beyond the servo's speed limit
        if np.any(acts.position_violation(acts.command(jump)) > 0):
            jump[0] -= 10.0
        with pytest.raises(DeviceError, match=r"velocity|acceleration"):
            fast.move(0.0, q0, np.repeat(jump[None], 5, axis=0), 0.02)
        # 3. not ready before its start time
        clock.sleep(0.5)
        with pytest.raises(DeviceError, match=r"ready 0\.600 s late, beyond the bound .*\(\+0\.500 s from its start"):
            late.move(0.0, q0, still, 0.02)
        # a step is sent `lead` s ahead of its start
        ahead.begin(0.0)
        ahead.move(0.0, q0, still, 0.02)
        assert robot.wait_received(4)
        assert blocked.refused_steps == fast.refused_steps == late.refused_steps == 1 and ahead.refused_steps == 0
        assert node.published == 4
        for _, offs, P, V in robot.received[:3]:  # the three refusals' holds, at rest where the robot is
            assert len(offs) == 1 and np.allclose(P[0], start * si, rtol=1e-12, atol=0) and np.all(V == 0.0)
        t0, offs, P, _ = robot.received[3]  # the last one published: nothing of the refused steps came before it
        # the state at the step's start, its points, the stop tail's rest point
        assert len(robot.received) == 4 and len(offs) == ros.points_per_step + 2 and t0 == pytest.approx(1.5, abs=1e-9)
    finally:
        robot.close()
        node.close()


def test_hostile_messages_are_counted_and_ignored(paper):
    from sensor_msgs.msg import JointState

    _, acts, scene, _, start, _ = paper
    ros = RosOptions(domain_id=DOMAIN)
    clock = VirtualClock()
    feed = ObstacleFeed(max_age=1.0, expected=("upper", "lower"), clock=clock)
    node = RosNode(ros, acts, feed)
    robot = RobotNode(ros, acts.names, scene, start * si_scale(acts.units))
    try:
        robot.wait_matched(obstacles=False)
        assert node.wait_joint_state(0.0, HANG) is not None
        names = list(acts.names)
        bad_states = [
            JointState(name=names, position=[math.nan] + [0.0] * (len(names) - 1)),  # invalid
            JointState(name=[*names[:-1], "elbow"], position=[0.0] * len(names)),  # unknown_name
            JointState(name=[f"j{i}" for i in range(300)], position=[0.0] * 300),  # oversize
            JointState(name=names, position=[0.0]),  # invalid: lengths differ
            JointState(name=names + names[:1], position=[0.0] * (len(names) + 1)),  # invalid: repeated
        ]
        for k, m in enumerate(bad_states):
            m.header.stamp = _stamp(1.0 + k)
            robot.js.publish(m)
        good = acts.command(acts.actuation(start)) + 0.001
        si = si_scale(acts.units)  # on the wire: rad and m
        m = JointState(name=names[::-1], position=[float(v) for v in (good * si)[::-1]])  # any order of names
        m.header.stamp = _stamp(10.0)
        robot.js.publish(m)
        assert node.wait_joint_state(10.0, HANG) is not None
        values, stamp = node.joint_state()
        assert stamp == 10.0 and np.allclose(values, good)
        assert node.counts == {"invalid": 3, "unknown_name": 1, "oversize": 1}
        # markers: too many, wrong frame, wrong type, NaN, an unknown obstacle; then the good ones
        from visualization_msgs.msg import MarkerArray

        many = MarkerArray(markers=spheres(ros.frame_id, scene, 0.0).markers * 150)
        robot.mk.publish(many)  # oversize
        robot.mk.publish(spheres("camera", scene, 0.1))  # 2 x frame
        robot.mk.publish(spheres(ros.frame_id, scene, 0.2, type=1))  # 2 x type (CUBE)
        bad = spheres(ros.frame_id, scene, 0.3)
        bad.markers[0].pose.position.x = math.nan
        bad.markers[1].ns = "intruder"
        robot.mk.publish(bad)  # 1 x invalid, 1 x the feed's unknown_id
        robot.mk.publish(spheres(ros.frame_id, scene, 0.4))
        assert feed.wait_for(3, HANG)  # the three valid spheres reached the feed (one message each)
        assert node.marker_arrays == 5
        assert node.counts == {"invalid": 4, "unknown_name": 1, "oversize": 2, "frame": 2, "type": 2}
        assert feed.counts == {"unknown_id": 1}
        st = feed.latest(0.4)
        c, r = scene.states(0.4)
        assert not st.stale and np.allclose(st.centers, c[[1, 0]]) and np.allclose(st.radii, r[[1, 0]])
        # the UDP JSON feed goes into the same tracks
        ObstacleFeed.send(feed.address, [{"id": "upper", "center": [1.0, 2.0, 3.0], "radius": 40.0, "timestamp": 0.5}])
        assert feed.wait_for(4, HANG)
        st = feed.latest(0.5)
        assert np.allclose(st.centers[st.ids.index("upper")], [1.0, 2.0, 3.0]) and feed.accepted == 3
        assert node.alive
    finally:
        robot.close()
        node.close()
        feed.close()


def test_close_leaves_no_threads_or_processes(paper):
    _, acts, *_ = paper
    before = set(threading.enumerate())
    children = set(_children())  # earlier tests of the session may have their own children still exiting
    node = RosNode(RosOptions(domain_id=DOMAIN), acts)
    assert node.alive
    node.close()
    node.close()  # idempotent
    assert not node.alive and not node.context_ok
    assert set(threading.enumerate()) <= before
    assert set(_children()) <= children


def test_ros_section_is_checked_in_one_line(tmp_path):
    base = _problem(tmp_path).read_text()
    assert Problem.load(_problem(tmp_path)).options(RosOptions, "ros").domain_id == DOMAIN
    for bad, field in (
        ('trajectory_topic = "/a b"', "ros.trajectory_topic"),
        ("depth = 0", "ros.depth"),
        ('discovery = "everywhere"', "ros.discovery"),
        ("points_per_step = 101", "ros.points_per_step"),
        ("colour = 1", "ros.colour"),
        ('reliability = "best_effort"', "ros.reliability"),
        ('controller = "/x y"', "ros.controller"),
        ('joints = { q1 = "" }', "ros.joints.q1"),
    ):
        p = tmp_path / "bad.toml"
        p.write_text(base + bad + "\n")
        with pytest.raises(InputError, match=field.replace(".", r"\.")) as exc:
            Problem.load(p).options(RosOptions, "ros")
        assert "\n" not in str(exc.value)
    assert RosOptions().domain_id is None
    assert RosOptions.from_table(Table(RosOptions().to_dict(), "ros")) == RosOptions()


def test_no_robot_on_the_graph_is_one_line(tmp_path, capsys, paper):
    from crtraj.cli import main

    p = _problem(tmp_path)
    p.write_text(p.read_text().replace(f"start_timeout = {HANG}", "start_timeout = 0.5"))
    before = set(threading.enumerate())
    assert main(["ros-bridge", str(p), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ros.joint_state_topic: no sensor_msgs/JointState" in err[0]
    assert not (tmp_path / "run").exists()  # nothing written
    assert set(threading.enumerate()) <= before  # the node and the feed were closed
