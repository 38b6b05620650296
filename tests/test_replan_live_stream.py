"""`crtraj replan --feed --stream`: live streaming to a simulated device on 127.0.0.1 while the loop runs."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import free_udp_port
from feed_clock import VirtualClock

from crtraj.cli import main
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.control.loop._run_record import RunStatus
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.link import DeviceLink
from crtraj.hardware.protocol import HOLD, MOVE
from crtraj.hardware.sim import SimDevice
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.world.feed import ObstacleFeed
from crtraj.world.obstacle import Obstacle

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "problems" / "robots" / "cdsr2.toml"
XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([0.15, 0.12, -0.05, 0.05, -4.0])  # a nearby goal: about a second of motion
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=2.0, name="ball")


def _problem(tmp_path: Path, model, duration: float) -> Path:
    start, goal = model.tip_position(XS), model.tip_position(XG)
    vec = lambda a: "[" + ", ".join(f"{v:.12g}" for v in a) + "]"  # noqa: E731
    text = f"""
name = "live"
robot = "{ROBOT}"
seed = 1
[task]
start = {vec(start)}
goal = {vec(goal)}
start_config = {vec(XS)}
goal_tolerance = 0.5
[scene]
safety_distance = 5.0
[[scene.obstacle]]
name = "ball"
center = {vec(BALL.center)}
radius = {{ mean = 30.0, amplitude = 8.0, omega = 2.0, phase = 0.0 }}
[replan]
horizon = 6
points = 12
solver = "sqp"
[loop]
duration = {duration}
planner_time = 0.5
settle_time = 0.3
[stream]
watchdog = 0.5
prebuffer = 0.2
connect_timeout = 2.0
settle_timeout = 4.0
"""
    p = tmp_path / "live.toml"
    p.write_text(text)
    return p


class _Sender:
    """A motion-capture bridge for the command-line runs: the ball's state at about 100 Hz of wall time
    (those runs use a generous --feed-max-age, so a starved sender thread cannot change their outcome)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self.stop.is_set():
            s = time.monotonic() - t0
            r = BALL.radius + BALL.amplitude * np.sin(BALL.omega * s)
            msg = [{"id": "ball", "center": list(BALL.center), "radius": float(r), "timestamp": s}]
            ObstacleFeed.send(("127.0.0.1", self.port), msg)
            self.stop.wait(0.01)

    def __enter__(self) -> _Sender:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(1.0)


def _actuators(robot):
    return Actuators.from_robot(robot)


def _device(robot, x0) -> SimDevice:
    acts = _actuators(robot)
    return SimDevice(acts, 0, initial=acts.command(robot.cables(x0)))


def _log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _assert_frames_within_limits(lines: list[dict], acts, dt: float) -> None:
    """Independent re-check of every sent frame: positions, and velocity/acceleration of consecutive MOVEs."""
    tx = [x for x in lines if x["type"] == "tx" and x["kind"] in ("move", "hold", "estop")]
    V = np.array([x["values"] for x in tx])
    assert np.all((acts.lower - 1e-9 <= V) & (acts.upper + 1e-9 >= V))
    kinds = [x["kind"] for x in tx]
    v_prev = np.zeros(acts.n)
    for k in range(1, len(tx)):
        if kinds[k] != "move":
            v_prev = np.zeros(acts.n)
            continue
        v = (V[k] - V[k - 1]) / dt
        assert np.all(np.abs(v) <= acts.vmax * (1 + 1e-6)), k
        assert np.all(np.abs(v - v_prev) / dt <= acts.amax * (1 + 1e-6)), k
        v_prev = v
    assert not [x for x in lines if x["type"] == "event" and x["event"] == "refused"]


def test_live_stream_reaches_the_goal_and_the_device_ends_there(tmp_path, robot, model, capsys):
    port = free_udp_port()
    acts = _actuators(robot)
    out = tmp_path / "o"
    with _device(robot, XS) as dev, _Sender(port):
        rc = main(["replan", str(_problem(tmp_path, model, 6.0)), "--out", str(out), "--no-html",
                   "--feed", f"udp://127.0.0.1:{port}", "--feed-max-age", "1.0", "--stream", dev.url])  # fmt: skip
        time.sleep(0.2)
        final = dev.state()
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "live stream done" in text
    res = json.loads((out / "run.json").read_text())
    assert res["status"] == "reached" and res["summary"]["safety_violations"] == 0
    stream = res["stream"]["stream"]
    assert stream["status"] == "done" and stream["moves"] > 50
    # in order: the device applied strictly increasing sequence numbers and non-decreasing stamps
    applied = list(dev.applied)
    seqs = np.array([a.seq for a in applied])
    assert np.all(np.diff(seqs) > 0)
    moves = [a for a in applied if a.kind == MOVE]
    assert len(moves) > 50
    assert np.all(np.diff([a.stamp for a in moves]) > 0)
    # played in real time: the device's wall clock and the stamps advance together
    lag = np.array([a.wall - a.stamp for a in moves])
    assert np.ptp(lag) < 1.0
    # the device ends at the run's final actuation
    q_end = np.array(res["waypoints"][-1]["q"])
    np.testing.assert_allclose(final["positions"], acts.command(q_end), atol=0.01)
    _assert_frames_within_limits(_log(out / "stream.jsonl"), acts, 0.01)


def test_stale_feed_holds_the_device_with_hold_frames_only(tmp_path, robot, model):
    """The feed runs on the loop's own time (a virtual clock set to each step's time), and the bridge is the
    loop's progress callback: it sends one state per step, received before the next step, until the device has
    applied moves; then it falls silent. The feed is then stale exactly max_age of loop time later, however
    loaded the machine is."""
    from crtraj.io.problem import Problem

    problem = Problem.load(_problem(tmp_path, model, 2.8))
    acts = _actuators(robot)
    clock = VirtualClock(50.0)
    t0 = clock()
    with _device(robot, XS) as dev, ObstacleFeed(0, max_age=0.25, expected=["ball"], clock=clock) as feed:
        sent = [0]

        def send(t: float) -> None:
            r = BALL.radius + BALL.amplitude * np.sin(BALL.omega * t)
            ObstacleFeed.send(feed.address, [{"id": "ball", "center": list(BALL.center), "radius": r, "timestamp": t}])
            sent[0] += 1
            assert feed.wait_for(sent[0])

        send(0.0)
        sopts = problem.options(StreamOptions, "stream")
        loop = ClosedLoop.from_problem(problem, feed=feed, lead=sopts.prebuffer)
        streamer = Streamer.open(dev.url, acts, sopts, tmp_path / "stream.jsonl")
        streamer.start()
        link = DeviceLink(streamer, loop.servo, loop.options.dt, lead=sopts.prebuffer)
        statuses: list[str] = []
        stopped: dict[str, float] = {}

        def bridge(k: int, t: float, status: str) -> None:
            clock.advance_to(t0 + t)
            statuses.append(status)
            if not stopped:
                applied = sum(a.kind == MOVE for a in list(dev.applied))
                if statuses.count("move") >= 3 and applied >= 10:
                    stopped.update(t=t, wall=time.monotonic(), applied=applied)
                    return
                send(t)

        run = loop.run(device=link, progress=bridge)
        time.sleep(0.2)  # let the last telemetry arrive (the device holds still: nothing depends on it)
        final = dev.state()
        t_dev0 = dev.clock_origin  # the device's clock origin (monotonic)
    assert stopped, statuses  # the device applied moves while the feed was live: streamed during the run
    assert run.status is RunStatus.TIMEOUT and not run.reached  # the feed went silent before the goal: reported
    st = list(run.step_status)
    # the last state was sent at stopped t - 0.1 s: stale exactly from the first step whose feed state is older
    # than max_age (0.25 s) of loop time, the step starting 0.3 s after it
    k_stale = round((stopped["t"] + 0.2) / 0.1)
    assert all(s != "stale" for s in st[:k_stale]) and all(s == "stale" for s in st[k_stale:]), (stopped, st)
    assert st.count("move") >= 3
    applied = list(dev.applied)
    moves = [a for a in applied if a.kind == MOVE]
    assert sum(a.wall + t_dev0 < stopped["wall"] for a in moves) >= stopped["applied"] >= 10
    # once the loop held on the stale feed, the device got the planned stop (move frames within the limits,
    # checked below with every frame) and then HOLD frames only, and it holds still
    lines = _log(tmp_path / "stream.jsonl")
    held = [x for x in lines if x["type"] == "event" and x["event"] == "held" and "stale" in x["message"]]
    assert held, [x for x in lines if x["type"] == "event"]
    t_held = held[0]["wall"]
    after = [x for x in lines if x["type"] == "tx" and x["wall"] > t_held + 1e-3]
    kinds = [x["kind"] for x in after]
    m = kinds.count("move")
    assert kinds == ["move"] * m + ["hold"] * (len(kinds) - m) and len(kinds) > m
    assert len({tuple(x["values"]) for x in after[m:]}) == 1
    assert link.report.status == "held" and run.device["stream"]["status"] == "held"
    # the device ends where the run says it is (its telemetry became the measured configuration)
    np.testing.assert_allclose(final["positions"], acts.command(run.q[-1]), atol=0.01)
    _assert_frames_within_limits(lines, acts, 0.01)
    assert all(a.kind in (MOVE, HOLD) for a in applied)
    assert run.feed["rejected"] == 0 and run.feed["accepted"] == sent[0]


def test_device_away_from_the_start_is_refused_unless_approach(tmp_path, robot, model, capsys):
    port = free_udp_port()
    problem = _problem(tmp_path, model, 0.6)
    acts = _actuators(robot)
    with SimDevice(acts, 0) as dev, _Sender(port):  # the device rests in the straight pose
        rc = main(["replan", str(problem), "--out", str(tmp_path / "a"), "--no-html",
                   "--feed", f"udp://127.0.0.1:{port}", "--feed-max-age", "1.0", "--stream", dev.url])  # fmt: skip
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2
        assert len(err) == 1 and "--stream" in err[0] and "--approach" in err[0] and "s1c1" in err[0]
        rc = main(["replan", str(problem), "--out", str(tmp_path / "b"), "--no-html", "--quiet",
                   "--feed", f"udp://127.0.0.1:{port}", "--feed-max-age", "1.0", "--stream", dev.url,
                   "--approach"])  # fmt: skip
    capsys.readouterr()
    assert rc == 1  # 0.6 s is not enough to reach the goal
    res = json.loads((tmp_path / "b" / "run.json").read_text())
    # the run started where the device was: the straight pose, not the task's start
    np.testing.assert_allclose(res["waypoints"][0]["x"], np.zeros(5), atol=1e-9)


def test_ctrl_c_holds_the_device_and_ends_the_run(tmp_path, robot, model):
    from crtraj.io.problem import Problem

    problem = Problem.load(_problem(tmp_path, model, 5.0))
    acts = _actuators(robot)
    clock = VirtualClock(0.0)  # the feed on loop time: one state per step, received before the next step
    with _device(robot, XS) as dev, ObstacleFeed(0, max_age=0.2, expected=["ball"], clock=clock) as feed:

        def send(t: float, n: int) -> None:
            r = BALL.radius + BALL.amplitude * np.sin(BALL.omega * t)
            ObstacleFeed.send(feed.address, [{"id": "ball", "center": list(BALL.center), "radius": r, "timestamp": t}])
            assert feed.wait_for(n)

        send(0.0, 1)
        opts = StreamOptions(watchdog=0.5, prebuffer=0.2, connect_timeout=2.0)
        loop = ClosedLoop.from_problem(problem, feed=feed, lead=0.2)
        streamer = Streamer.open(dev.url, acts, opts, tmp_path / "s.jsonl")
        streamer.start()
        link = DeviceLink(streamer, loop.servo, loop.options.dt)

        def interrupt(k: int, t: float, status: str) -> None:
            if k == 8:
                raise KeyboardInterrupt
            clock.advance_to(t)
            send(t, k + 2)

        run = loop.run(device=link, progress=interrupt)
    assert run.status is RunStatus.INTERRUPTED and run.steps == 9
    assert "stale" not in run.step_status
    assert link.report.status == "held" and "Ctrl-C" in link.report.message
    lines = _log(tmp_path / "s.jsonl")
    kinds = [x["kind"] for x in lines if x["type"] == "tx"]
    assert kinds[-1] == "hold" and "move" in kinds
    # the device stopped within its limits: every frame it was sent, the hold's included (a hold commands rest, so
    # one right after a moving frame is a stop in one period), by finite differences from rest; the stream braked
    # before it closed, and the run reports exactly these frames' figures
    tx = [x for x in lines if x["type"] == "tx" and x["kind"] in ("move", "hold", "estop")]
    V = np.diff(np.array([x["values"] for x in tx]), axis=0) / 0.01
    A = np.diff(np.vstack([np.zeros(acts.n), V]), axis=0) / 0.01
    peak = float(np.max(np.abs(A) / acts.amax))
    assert 0.5 < peak <= 1.0 + 1e-9 and any(x["type"] == "event" and x["event"] == "brake" for x in lines)
    assert run.summary()["max_acceleration_fraction"] == pytest.approx(peak, rel=1e-9)
