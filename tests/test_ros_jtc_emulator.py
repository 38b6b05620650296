"""`crtraj ros-bridge` against an emulated stock joint_trajectory_controller (`jtc_emulator.JtcEmulator`) in a
real rclpy graph on loopback: the controller's own semantics (replacement on arrival, the point before the
trajectory, splines, rejection rules) decide what the robot does, and an independent dense check of what it
commanded finds no contact. The bridge and the emulator share a virtual clock, so what is commanded never
depends on the machine's speed; waits have generous hang bounds only.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import PAPER, paper_copy, require_module
from feed_clock import VirtualClock
from jtc_emulator import JtcEmulator

from crtraj.app.devices import RosBridgeRequest, run_ros_bridge
from crtraj.control.loop import ClosedLoop
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.ros._messages import si_scale
from crtraj.hardware.ros._node import ros_environment
from crtraj.hardware.ros._options import RosOptions
from crtraj.io.problem import Problem
from crtraj.io.results import read_result

HANG = 60.0  # s: a guard against hangs, never a timing window
DOMAIN = 10 + (os.getpid() + 37) % 90
GOAL = np.array([10.0, -120.0, 170.0])  # the paper's simulation 2 goal (mm)


@pytest.fixture(scope="module")
def paper():
    """(problem, actuators, scene, model, the robot's start values) of the paper's simulation 2."""
    require_module("rclpy", "pip install -e '.[ros]'")
    problem = Problem.load(PAPER)
    loop = ClosedLoop.from_problem(problem)
    acts = Actuators.from_robot(problem.robot)
    start = acts.command(loop.start_command())
    return problem, acts, loop.scene, loop.model, start


def _problem(tmp_path: Path, acts: Actuators, joints: dict[str, str], loop: dict | None = None, **ros) -> Path:
    """paper_dynamic.toml without its deadline, on this run's domain, with [ros.joints] = `joints` (and [loop]
    values `loop`)."""
    values = {"domain_id": DOMAIN, "max_age": 0.35, "joint_state_timeout": HANG, "start_timeout": HANG, **ros}
    table = {("ros", k): v for k, v in values.items()} | {("loop", k): v for k, v in (loop or {}).items()}
    p = paper_copy(tmp_path, "paper_ros_jtc.toml", table)
    p.write_text(p.read_text() + "\n[ros.joints]\n" + "".join(f'{a} = "{j}"\n' for a, j in joints.items()))
    return p


class Graph:
    """The robot's side: an emulated controller and a world node publishing the true obstacles (SPHERE markers,
    every 0.05 s of virtual time) and taking the bridge's tip paths."""

    def __init__(self, ros: RosOptions, joints, start, scene, clock: VirtualClock, **emulator):
        rclpy = require_module("rclpy")
        from nav_msgs.msg import Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile
        from rclpy.signals import SignalHandlerOptions
        from test_ros_bridge import spheres
        from visualization_msgs.msg import MarkerArray

        ros_environment(ros)
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=ros.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.jtc = JtcEmulator(self.ctx, ros.domain_id, joints, start, clock, name=ros.controller, **emulator)
        self.world = rclpy.create_node("world", context=self.ctx)
        qos = QoSProfile(depth=ros.depth)
        self.mk = self.world.create_publisher(MarkerArray, ros.obstacle_topic, qos)
        self.paths: list = []
        self.world.create_subscription(PathMsg, ros.path_topic, self.paths.append, qos)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.jtc.node)
        self.executor.add_node(self.world)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.scene, self.frame = scene, ros.frame_id
        self.spheres_sent = 0
        self._spheres = spheres

    def publish_obstacles(self, t: float) -> bool:
        self.mk.publish(self._spheres(self.frame, self.scene, t))
        self.spheres_sent += len(self.scene.obstacles)
        return True

    def wait_matched(self) -> None:
        for _ in range(int(HANG / 0.02)):
            if self.jtc.js.get_subscription_count() and self.mk.get_subscription_count():
                return
            threading.Event().wait(0.02)
        raise AssertionError("the bridge never subscribed")

    def close(self) -> None:
        self.jtc.stop()
        self.executor.shutdown(timeout_sec=5.0)
        self.thread.join(HANG)
        self.jtc.destroy()
        self.world.destroy_node()
        rclpy = require_module("rclpy")
        rclpy.try_shutdown(context=self.ctx)


def _run(path: Path, acts, scene, start, tmp_path: Path, joints, record: Path | None = None, lateness=None, **emulator):
    """`run_ros_bridge` on a virtual clock against the emulated controller (`emulator`: its lag, latency):
    (exit code, the graph). lateness: a function giving s of virtual time that pass after each of the bridge's
    sleeps (a step computed that late), or None."""
    ros = Problem.load(path).options(RosOptions, "ros")
    clock = VirtualClock()
    graphs, nodes, feeds = [], [], []

    def ready(node, feed):
        nodes.append(node)
        feeds.append(feed)
        g = Graph(ros, joints, start * si_scale(acts.units), scene, clock, **emulator)
        graphs.append(g)
        g.wait_matched()
        g.publish_obstacles(0.0)
        clock.every(0.05, g.publish_obstacles, start=0.05)
        g.jtc.publish_state(0.0)

    def sleep(dt: float) -> None:
        # the controller takes each message before the clock moves on, and the bridge has every obstacle state and
        # joint state of the time passed before it goes on (as fast as real time): the run never depends on speed
        if graphs and nodes:
            assert graphs[0].jtc.wait_received(nodes[0].published, HANG)
        clock.sleep(dt + (lateness() if lateness is not None and nodes else 0.0))
        if graphs and nodes:
            assert feeds[0].wait_for(graphs[0].spheres_sent, HANG)
            assert nodes[0].wait_joint_state(graphs[0].jtc.commanded[-1][0] - 1e-6, HANG) is not None  # stamps: ns

    req = RosBridgeRequest(path, out=tmp_path / "run", html=False, quiet=True, record=record)
    try:
        code = run_ros_bridge(req, clock=clock, sleep=sleep, ready=ready)
    finally:
        for g in graphs:
            g.close()
    return code, graphs[0] if graphs else None


def _contact_distance(model, scene, acts, T: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Independent: the smallest distance (mm) between the body surface (backbone points of the robot model, the
    body radius) and the true obstacle spheres at each time T, by brute force over every point pair."""
    X = model.robot.config(acts.actuation(values))
    B = model.points(X, 80)  # (S, 80, 3)
    C, R = scene.states(T)  # (S, m, 3), (S, m)
    gap = np.sqrt(((B[:, :, None, :] - C[:, None, :, :]) ** 2).sum(axis=-1)) - R[:, None, :]
    return gap.min(axis=(1, 2)) - model.robot.body_radius


LAG_PERIODS = 3  # the emulated controller reads its state this many control periods late (default: one)


def _snapshots(monkeypatch) -> list:
    """(clock time, loop-time origin, committed curve) after every message the bridge sends (a step or a hold):
    the curve it verified, as the controller executes it."""
    from crtraj.hardware.ros._device import RosDevice

    snaps: list = []
    for name in ("move", "hold"):
        original = getattr(RosDevice, name)

        def wrapped(self, *args, _original=original, **kw):
            try:
                return _original(self, *args, **kw)
            finally:
                snaps.append((self.clock(), self._origin, self.committed))

        monkeypatch.setattr(RosDevice, name, wrapped)
    return snaps


@pytest.mark.slow
@pytest.mark.parametrize(
    ("distro", "settings"),
    [("humble", {}), ("jazzy", {}), ("rolling", {"allow_trajectory_replacement": False})],
)
def test_a_stock_controller_executes_simulation_2_as_verified(tmp_path, paper, monkeypatch, distro, settings):
    """Simulation 2 through the emulated JTC of each release with its defaults (Rolling: without its blend, which
    the bridge refuses; Jazzy and Rolling command one update period ahead, read from its update_rate), reading its
    state 3 periods late, taking each message up to ros.arrival_margin after it was sent, and every step computed
    late by up to the bound ros.lead - ros.arrival_margin (injected on the virtual clock): no message rejected, no
    step refused, the goal reached; what the controller commanded at every control cycle is the curve the bridge
    verified (1e-9), although the lag changed the point before the trajectory; every commanded position is clear
    of the true obstacles (independent dense check); the run is recorded to MCAP."""
    _, acts, scene, model, start = paper
    joints = {a: f"robot/{a}_joint" for a in acts.names}
    # references planned inside the steps (no worker process beside the loop, whose paths would arrive at steps that
    # depend on the machine's load): on the virtual clock the whole run is then the same on any machine
    path = _problem(tmp_path, acts, joints, loop={"reference_delay": 0.0}, state_lag=LAG_PERIODS * 0.004)
    ros = Problem.load(path).options(RosOptions, "ros")
    bound = ros.lead - ros.arrival_margin
    rng = np.random.default_rng(5)
    draws: list[float] = []

    def lateness() -> float:  # uniform up to the bound, every fifth step exactly at it
        draws.append(bound if len(draws) % 5 == 4 else float(rng.uniform(0.0, bound)))
        return draws[-1]

    snaps = _snapshots(monkeypatch)
    record = tmp_path / "run.mcap"
    period = 0.004
    code, g = _run(
        path, acts, scene, start, tmp_path, list(joints.values()), record=record, lateness=lateness,
        lag=LAG_PERIODS * period, latency=ros.arrival_margin, period=period, distro=distro, params=settings,
    )  # fmt: skip
    assert code == 0 and len(draws) > 50 and max(draws) == bound
    res = read_result(tmp_path / "run" / "run.json")
    stream = res.data["stream"]
    assert g.jtc.rejected == [] and g.jtc.accepted == len(g.jtc.received) == stream["moves"] + stream["holds"]
    assert stream["refused_steps"] == 0 and stream["late_refused"] == 0 and stream["moves"] > 50, stream["refusal"]
    # every message ends at rest, as the default allow_nonzero_velocity_at_trajectory_end = false demands
    assert all(not any(m.points[-1].velocities) for m in g.jtc.received)
    T = np.array([t for t, _ in g.jtc.commanded])
    V = np.array([p for _, p in g.jtc.commanded]) / si_scale(acts.units)
    # what the controller commanded is what the bridge verified: at each cycle, the newest curve sent before it
    sent = np.array([c for c, _, _ in snaps])
    assert np.all(np.diff(sent) >= 0.0)
    worst = 0.0
    for k in np.flatnonzero(sent[0] <= T):
        _, origin, curve = snaps[int(np.searchsorted(sent, T[k], side="right")) - 1]
        worst = max(worst, float(np.max(np.abs(curve.at(T[k] - origin)[0] - V[k]))))
    assert worst <= 1e-9, worst
    # the lag changed the point before the trajectory (the state 3 cycles old, not the one at arrival) while moving
    cmd = dict(g.jtc.commanded)
    moved = [np.max(np.abs(a["before"]["p"] - cmd[t])) for t, a in g.jtc.adopted if t in cmd]
    assert max(moved) > 1e-6
    tip = model.tip_position(model.robot.config(acts.actuation(V[-1])))
    assert np.linalg.norm(tip - GOAL) <= 0.5 + 1e-6
    assert np.all(np.diff(T) > 0) and np.max(np.diff(T)) <= g.jtc.period + 1e-9
    d = _contact_distance(model, scene, acts, T, V)
    assert np.all(d > 0.0), f"contact: distance {d.min():.3f} mm at t={T[np.argmin(d)]:.3f} s"
    assert d.min() > scene.safety_distance - 1.0
    # the tip along each executed curve was published for RViz
    assert g.paths and all(p.header.frame_id == "world" and p.poses for p in g.paths)
    _check_record(record, g)


def _check_record(record: Path, g: Graph) -> None:
    """The MCAP file holds every trajectory sent (CDR, the ros2msg schema by name) and the joint states."""
    from mcap.reader import make_reader
    from rclpy.serialization import deserialize_message
    from trajectory_msgs.msg import JointTrajectory

    assert record.is_file() and not list(record.parent.glob(f".{record.name}*"))
    with open(record, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert topics["/joint_trajectory_controller/joint_trajectory"] == "trajectory_msgs/msg/JointTrajectory"
        assert topics["/joint_states"] == "sensor_msgs/msg/JointState"
        assert all(c.message_encoding == "cdr" for c in summary.channels.values())
        sent = [
            deserialize_message(m.data, JointTrajectory)
            for _, c, m in reader.iter_messages(topics=["/joint_trajectory_controller/joint_trajectory"])
        ]
    assert len(sent) == len(g.jtc.received)
    assert [list(m.joint_names) for m in sent] == [list(m.joint_names) for m in g.jtc.received]
    assert sent[-1].points[-1].positions == g.jtc.received[-1].points[-1].positions


def test_joint_names_the_robot_does_not_have_are_one_line_and_nothing_moves(tmp_path, paper):
    """[ros.joints] naming joints the JointState does not carry: one line naming ros.joints, no message sent, no
    run written."""
    _, acts, scene, _, start = paper
    joints = {a: f"robot/{a}_joint" for a in acts.names}
    path = _problem(tmp_path, acts, {a: f"wrong/{a}" for a in acts.names}, start_timeout=1.0)
    with pytest.raises(InputError, match=r"^ros\.joints: the robot's joint states name robot/") as exc:
        _run(path, acts, scene, start, tmp_path, list(joints.values()))
    assert "\n" not in str(exc.value) and "wrong/" in str(exc.value)
    assert not (tmp_path / "run").exists()


def _refused_at_start(tmp_path, paper, match: str, setup=None, joints=None, **emulator) -> list:
    """Run the bridge against an emulated controller (`emulator`: distro, params) that `setup(jtc)` may change, with
    [ros.joints] = `joints` (default: none): the start is refused with one line matching `match`, nothing sent, no
    run written. Returns the graphs."""
    _, acts, scene, _, start = paper
    joints = joints or {}
    names = [joints.get(a, a) for a in acts.names]
    path = _problem(tmp_path, acts, joints, start_timeout=5.0)
    ros = Problem.load(path).options(RosOptions, "ros")
    clock = VirtualClock()
    graphs = []

    def ready(node, feed):
        g = Graph(ros, names, start * si_scale(acts.units), scene, clock, **emulator)
        graphs.append(g)
        if setup is not None:
            setup(g.jtc)
        g.wait_matched()
        g.publish_obstacles(0.0)
        g.jtc.publish_state(0.0)

    req = RosBridgeRequest(path, out=tmp_path / "run", html=False, quiet=True)
    try:
        with pytest.raises(InputError, match=match) as exc:
            run_ros_bridge(req, clock=clock, sleep=clock.sleep, ready=ready)
    finally:
        for g in graphs:
            g.close()
    assert "\n" not in str(exc.value)
    assert graphs[0].jtc.received == [] and not (tmp_path / "run").exists()
    return graphs


def test_a_controller_with_other_joints_is_refused_from_its_parameters(tmp_path, paper):
    """The controller's `joints` parameter (read through /<controller>/get_parameters) lacks a commanded joint:
    one line naming it, before anything is sent."""
    last = paper[1].names[-1]
    names = list(paper[1].names)
    _refused_at_start(
        tmp_path, paper, rf"^joint_trajectory_controller\.joints: no {last} among",
        setup=lambda jtc: jtc.node.set_parameters([_parameter("joints", names[:-1])]),
    )  # fmt: skip


@pytest.mark.parametrize(
    ("distro", "params", "match"),
    [
        ("rolling", {}, r"allow_trajectory_replacement: true .* set allow_trajectory_replacement: false$"),
        ("humble", {"constraints.s2c1_joint.trajectory": 0.05}, r"constraints\.s2c1_joint\.trajectory: 0\.05;"),
        ("jazzy", {"speed_scaling.initial_scaling_factor": 0.5}, r"speed_scaling\.initial_scaling_factor: 0\.5;"),
    ],
)
def test_settings_that_change_the_executed_curve_are_refused_with_their_fix(tmp_path, paper, distro, params, match):
    """An emulated controller of each release whose parameter service answers as rclcpp's does (no values at all
    for a request naming an undeclared parameter, as open_loop_control is on Rolling): the bridge still reads its
    parameters, tells the release, and refuses in one line naming the parameter and the fix, before anything is
    sent: Rolling's default blend, a path tolerance (Humble), a speed scaling factor (Jazzy)."""
    joints = {a: f"{a}_joint" for a in paper[1].names}
    _refused_at_start(
        tmp_path, paper, r"^joint_trajectory_controller\." + match, joints=joints, distro=distro, params=params
    )


def test_a_controller_without_a_release_marker_is_named_and_still_checked(tmp_path, paper, caplog):
    """A controller that declares none of the release markers (open_loop_control undeclared on a Humble one): a
    warning names the unknown release and the assumption, and its parameters are still checked (cmd_timeout)."""

    def unmark(jtc):
        jtc.node.undeclare_parameter("open_loop_control")
        jtc.node.set_parameters([Parameter("cmd_timeout", Parameter.Type.DOUBLE, 0.5)])

    from rclpy.parameter import Parameter

    caplog.set_level("WARNING", logger="crtraj.app.ros_bridge")
    _refused_at_start(tmp_path, paper, r"^joint_trajectory_controller\.cmd_timeout: 0\.5 s;", setup=unmark)
    assert any("its release is unknown; the bridge assumes humble" in r.getMessage() for r in caplog.records)


def test_a_speed_scaling_publisher_is_refused_on_jazzy(tmp_path, paper):
    """A Jazzy controller with its defaults, and a node publishing on its ~/speed_scaling_input (any type; the real
    one is control_msgs/SpeedScalingFactor): one line naming the topic, before anything is sent."""
    from std_msgs.msg import Float64

    def scaler(jtc):
        jtc.node.create_publisher(Float64, "/joint_trajectory_controller/speed_scaling_input", 10)

    _refused_at_start(
        tmp_path, paper, r"^ros\.controller: something publishes on /joint_trajectory_controller/speed_scaling_input",
        setup=scaler, distro="jazzy",
    )  # fmt: skip


def _parameter(name: str, value):
    from rclpy.parameter import Parameter

    return Parameter(name, Parameter.Type.STRING_ARRAY, list(value))


def test_record_may_not_overwrite_an_input(tmp_path, capsys, paper):
    """--record naming the problem file: one line from the command line, the file unchanged, nothing written."""
    from crtraj.cli import main

    _, acts, *_ = paper
    path = _problem(tmp_path, acts, {})
    before = path.read_text()
    assert main(["ros-bridge", str(path), "--out", str(tmp_path / "run"), "--record", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--record:" in err[0] and "is also problem" in err[0]
    assert path.read_text() == before and not (tmp_path / "run").exists()


def test_no_controller_subscribed_is_one_line(tmp_path, paper):
    """Joint states and obstacles arrive, but nothing subscribes to /<controller>/joint_trajectory (the controller
    is another one): one line naming ros.controller after ros.start_timeout, nothing written."""
    _, acts, scene, _, start = paper
    path = _problem(tmp_path, acts, {}, start_timeout=1.0)
    ros = Problem.load(path).options(RosOptions, "ros")
    clock = VirtualClock()
    graphs = []

    def ready(node, feed):
        g = Graph(
            ros.with_(controller="other_controller"), list(acts.names), start * si_scale(acts.units), scene, clock
        )
        graphs.append(g)
        g.wait_matched()
        g.publish_obstacles(0.0)
        g.jtc.publish_state(0.0)

    req = RosBridgeRequest(path, out=tmp_path / "run", html=False, quiet=True)
    try:
        with pytest.raises(InputError, match=r"^ros\.controller: nothing subscribes to /joint_trajectory_controller/"):
            run_ros_bridge(req, clock=clock, sleep=clock.sleep, ready=ready)
    finally:
        for g in graphs:
            g.close()
    assert not (tmp_path / "run").exists()
