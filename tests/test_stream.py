"""Streamer: end to end against the simulated device, faults, watchdog, e-stop, limits, bad input, CLI."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import default_sigint
from devlink import CoreLink
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_device import hostile_datagrams

from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.core.errors import AdmissionError, InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import atomic_write_json, to_jsonable
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.protocol import ESTOP, HOLD, MOVE, PING, Frame, Telemetry, read_stream_file
from crtraj.hardware.sim import DeviceCore, Faults, SimDevice
from crtraj.hardware.stream._options import StreamOptions
from crtraj.hardware.stream._state import StreamError
from crtraj.hardware.stream._streamer import Streamer
from crtraj.hardware.transport import Transport
from crtraj.io.results import read_result
from crtraj.world.scene import Scene

pytestmark = pytest.mark.timeout(120)
ROOT = Path(__file__).resolve().parent.parent
ROBOT_FILE = ROOT / "problems" / "robots" / "cdsr2.toml"
# Tests that are not about the watchdog use a longer one, so a loaded CI machine that
# delays a telemetry packet by 100 ms cannot turn them into false "telemetry lost" failures;
# likewise for the acknowledgement and following-error checks (tested on the virtual clock).
ROBUST = StreamOptions(watchdog=0.5, connect_timeout=5.0, ack_timeout=0.5, following_tolerance=20.0)


# ------------------------------------------------------------------ helpers
@pytest.fixture(scope="module")
def acts(robot):
    return Actuators.from_robot(robot)


def make_result(robot, model, x1, duration, n=11, z0=0.0):
    """A result file dict (the common format) for a smooth configuration path from the straight pose at z0."""
    x0 = robot.straight(z0)
    s = np.linspace(0.0, 1.0, n)
    X = x0 + (np.asarray(x1) - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    assert np.all(robot.limit_violation(X) <= 0)
    Q, P, B = model.cables(X), model.tip_position(X), model.points(X)
    wps = [
        {"t": float(duration * si), "tip": P[k], "x": X[k], "q": Q[k], "backbone": B[k], "obstacles": {}}
        for k, si in enumerate(s)
    ]
    doc = {"kind": "plan", "robot": robot.to_dict(), "scene": Scene().to_dict(), "status": "success", "success": True}
    return to_jsonable(doc | {"waypoints": wps})


def admitted(result, acts, time_scale=1.0):
    """The result's motion as admission lets it through (what `crtraj stream` streams)."""
    return admit(read_result(result).motion_record(), acts, time_scale=time_scale)


X1 = np.array([0.3, -0.2, 0.1, 0.4, -8.0])


@pytest.fixture(scope="module")
def result(robot, model):
    return make_result(robot, model, X1, 1.5)


def tx_frames(log: Path) -> list[dict]:
    return [r for r in map(json.loads, log.read_text().splitlines()) if r["type"] == "tx" and r["kind"] != "ping"]


def events(rep) -> dict[str, float]:
    out: dict[str, float] = {}
    for wall, name, _ in rep.events:
        out.setdefault(name, wall)
    return out


def assert_applied_frames_are_sent_frames(dev: SimDevice, log: Path) -> list[dict]:
    sent = {r["seq"]: r for r in tx_frames(log)}
    seqs = [a.seq for a in dev.applied]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), "device applied frames out of order"
    for a in dev.applied:
        r = sent[a.seq]
        assert (Frame(a.kind, 0, 0, a.values).kind_name, a.stamp) == (r["kind"], r["stamp"])
        np.testing.assert_array_equal(a.values, r["values"])
    return list(sent.values())


# ------------------------------------------------------------ end to end
def test_streamed_trajectory_arrives_in_order_and_device_ends_at_final_setpoint(acts, result, tmp_path):
    log = tmp_path / "run.jsonl"
    path = admitted(result, acts)
    with SimDevice(acts) as dev:
        rep = Streamer.open(dev.url, acts, ROBUST, log=log).run_path(path)
        time.sleep(0.2)
        final = dev.state()["positions"]
    assert rep.ok, rep.message
    sent = assert_applied_frames_are_sent_frames(dev, log)
    moves = [r for r in sent if r["kind"] == "move"]
    assert len(moves) == 151 and rep.moves == 151  # 1.5 s at 100 Hz, both ends included
    assert [r["stamp"] for r in moves] == pytest.approx(np.linspace(0.0, 1.5, 151), abs=1e-12)
    # loopback UDP without faults loses nothing
    assert sum(a.kind == MOVE for a in dev.applied) == 151
    goal = acts.command(np.asarray(result["waypoints"][-1]["q"]))
    np.testing.assert_allclose(moves[-1]["values"], goal, atol=1e-12)
    np.testing.assert_allclose(final, goal, atol=1e-3)
    # the interpolated set-points pass through every waypoint (time stamps on the 10 ms grid)
    for w in result["waypoints"]:
        k = round(w["t"] * 100)
        np.testing.assert_allclose(moves[k]["values"], acts.command(np.asarray(w["q"])), atol=1e-9)
    # the record is complete JSON lines: header first, report last
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    assert lines[0]["type"] == "header" and lines[-1]["type"] == "report" and lines[-1]["status"] == "done"
    assert sum(r["type"] == "rx" for r in lines) == rep.telemetry > 50


def test_lossy_corrupting_link_keeps_streaming_and_never_applies_a_damaged_frame(acts, result, tmp_path):
    log = tmp_path / "run.jsonl"
    path = admitted(result, acts)
    with SimDevice(acts, faults=Faults(drop=0.1, corrupt=0.05), seed=7) as dev:
        rep = Streamer.open(dev.url, acts, ROBUST, log=log).run_path(path)
        time.sleep(0.2)
        st = dev.state()
    assert rep.ok, rep.message
    assert st["dropped_in"] > 5 and st["corrupted_in"] > 2 and st["crc_errors"] == st["corrupted_in"]
    assert st["dropped_out"] > 5 and rep.telemetry_errors > 0  # telemetry was damaged too, and rejected
    assert st["refused"] == 0
    assert_applied_frames_are_sent_frames(dev, log)
    goal = acts.command(np.asarray(result["waypoints"][-1]["q"]))
    np.testing.assert_allclose(st["positions"], goal, atol=1e-3)


# --------------------------------------------------------------- watchdog
def test_stalled_source_holds_within_the_watchdog_time(acts, tmp_path):
    log = tmp_path / "run.jsonl"
    opts = StreamOptions(watchdog=0.1, prebuffer=0.05)
    with SimDevice(acts) as dev:
        s = Streamer.open(dev.url, acts, opts, log=log)
        s.start()
        p0 = s.position
        t0 = time.monotonic()
        for k in range(31):  # a live source at 100 Hz for 0.3 s, at rest (the last frame repeated), then it stalls
            s.send_values(0.01 * k, p0 + 1e-4 * (1 - np.cos(np.pi * min(k, 29) / 29)))
            time.sleep(max(0.0, t0 + 0.01 * (k + 1) - time.monotonic()))
        time.sleep(0.5)
        assert s.state == "held" and s.reason.startswith("source stalled")
        with pytest.raises(StreamError, match="held"):
            s.send_values(1.0, p0)
        # resume: a new sequence from the hold position streams again
        s.resume()
        here = s.position
        s.send_path(np.arange(5) * 0.01 + 2.0, np.tile(here, (5, 1)))
        s.finish()
        assert s.wait(5.0)
        rep = s.close()
    ev = events(rep)
    assert rep.status == "done"
    assert ev["stalled"] - ev["underrun"] >= 0.1 - 1e-9
    assert ev["stalled"] - ev["underrun"] <= 0.1 + 0.1  # one watchdog period + generous scheduling margin
    kinds = [r["kind"] for r in tx_frames(log)]
    first_hold_after_moves = kinds.index("hold", kinds.index("move"))
    assert set(kinds[first_hold_after_moves : first_hold_after_moves + 5]) == {"hold"}


def _braked_then_held(lines: list[dict], event: str, acts, dt: float) -> None:
    """The frames logged after `event`: a stop (move frames) whose accelerations, by finite differences from
    the last two frames before it, stay within the limits and that ends at rest, then hold frames only."""
    at = next(i for i, r in enumerate(lines) if r["type"] == "event" and r["event"] == event)
    before = [r for r in lines[:at] if r["type"] == "tx" and r["kind"] == "move"][-2:]
    after = [r for r in lines[at:] if r["type"] == "tx"]
    kinds = [r["kind"] for r in after]
    m = kinds.count("move")
    assert kinds == ["move"] * m + ["hold"] * (len(kinds) - m) and len(kinds) > m, kinds
    V = np.array([r["values"] for r in before + after[:m]])
    vel = np.diff(V, axis=0) / dt
    acc = np.diff(vel, axis=0) / dt
    assert np.all(np.abs(acc) <= np.asarray(acts.amax) * (1 + 1e-6))
    assert np.all(vel[-1] == 0.0) and np.array_equal(after[-1]["values"], V[-1])  # at rest, held there


def test_silent_device_triggers_hold_within_the_watchdog_time(acts, result, tmp_path):
    log = tmp_path / "run.jsonl"
    path = admitted(result, acts)
    with SimDevice(acts, faults=Faults(disconnect_after=0.5, disconnect_for=30.0)) as dev:
        rep = Streamer.open(dev.url, acts, log=log).run_path(path)
    assert rep.status == "telemetry-lost", rep.message
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    last_rx = max(r["wall"] for r in lines if r["type"] == "rx")
    lost = next(r["wall"] for r in lines if r["type"] == "event" and r["event"] == "telemetry-lost")
    assert 0.1 - 1e-9 <= lost - last_rx <= 0.1 + 0.1
    _braked_then_held(lines, "telemetry-lost", acts, StreamOptions().dt)


def test_estop_stops_at_once_and_latches(acts, result, tmp_path):
    log = tmp_path / "run.jsonl"
    path = admitted(result, acts)
    with SimDevice(acts) as dev:
        s = Streamer.open(dev.url, acts, ROBUST, log=log)
        timer = threading.Timer(0.5, s.estop)
        timer.start()
        rep = s.run_path(path)
        timer.join()
        time.sleep(0.05)
        st = dev.state()
    assert rep.status == "estop" and rep.estops >= 1
    kinds = [r["kind"] for r in tx_frames(log)]
    k = kinds.index("estop")
    assert set(kinds[k:]) == {"estop"} and 20 < k < 140
    assert st["status"] & 2  # STATUS_ESTOP
    assert [a.kind for a in dev.applied][-1] == ESTOP


def test_transport_errors_stop_and_report(acts, result, tmp_path):
    path = admitted(result, acts)
    # nothing listens: ICMP port unreachable surfaces as a transport error
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    rep = Streamer.open(f"udp://127.0.0.1:{port}", acts).run_path(path)
    assert rep.status == "error" and rep.moves == 0
    assert "transport error" in rep.message or "no telemetry" in rep.message
    # the device vanishes mid-stream
    log = tmp_path / "run.jsonl"
    dev = SimDevice(acts).start()
    timer = threading.Timer(0.5, dev.stop)
    timer.start()
    rep = Streamer.open(dev.url, acts, log=log).run_path(path)
    timer.join()
    assert rep.status in ("error", "telemetry-lost"), rep.message
    assert 20 < rep.moves < 151


def test_device_with_stricter_limits_refusal_is_reported(robot, acts, result, tmp_path):
    d = robot.to_dict()
    d["actuators"] = Actuators.from_robot(robot).to_dict()  # every servo written out
    d["actuators"]["servo"]["s2c2"]["position_limits"] = [-0.01, 0.01]
    strict = Actuators.from_robot(type(robot).from_table(Table(d, "robot")))
    path = admitted(result, acts)
    with SimDevice(strict) as dev:
        rep = Streamer.open(dev.url, acts, ROBUST).run_path(path)
    assert rep.status == "refused" and "device refused" in rep.message


# ------------------------------------------------------- limits, refusal
def test_too_fast_path_is_refused_before_anything_is_sent(robot, model, acts, tmp_path):
    """Admission checks the set-points as sent: a path too fast for the z stage is refused (nothing can be
    streamed) with the time scale that makes it pass, and slowed by that scale it streams."""
    fast = make_result(robot, model, X1, 0.3)
    with pytest.raises(AdmissionError, match=r"refused: z .* exceeds limit .* at t=") as exc:
        admitted(fast, acts)
    scale = float(str(exc.value).split("--time-scale ")[1])
    dry = tmp_path / "frames.bin"
    rep2 = Streamer.open(f"file://{dry}", acts).run_path(admitted(fast, acts, time_scale=scale))
    assert rep2.ok, rep2.message
    assert dry.stat().st_size > 0


def test_path_away_from_the_device_needs_an_approach(robot, model, acts, tmp_path):
    res = make_result(robot, model, X1, 1.0, z0=-5.0)  # starts 5 mm below the device's z = 0
    path = admitted(res, acts)
    with SimDevice(acts) as dev:
        rep = Streamer.open(dev.url, acts, ROBUST).run_path(path)
        assert rep.status == "refused" and "--approach" in rep.message and rep.moves == 0
        rep = Streamer.open(dev.url, acts, ROBUST).run_path(path, approach=True)
        time.sleep(0.2)
        final = dev.state()["positions"]
    assert rep.ok, rep.message
    np.testing.assert_allclose(final, acts.command(np.asarray(res["waypoints"][-1]["q"])), atol=1e-3)


class _Capture(Transport):
    has_telemetry = False
    description = "capture"

    def __init__(self) -> None:
        self.frames: list[Frame] = []

    def send(self, frame: bytes) -> None:
        self.frames.append(Frame.decode(frame))

    def receive(self) -> list[bytes]:
        return []


def _check_frames(frames, acts, start, dt):
    """Independent re-computation of every limit over the frames that left."""
    tol = 1e-9
    prev, vprev = np.asarray(start, dtype=float), np.zeros(acts.n)
    for f in frames:
        p = f.values
        assert np.all(p >= acts.lower - tol * np.maximum(np.abs(acts.lower), 1))
        assert np.all(p <= acts.upper + tol * np.maximum(np.abs(acts.upper), 1))
        if f.kind == MOVE:
            v = (p - prev) / dt
            a = (v - vprev) / dt
            assert np.all(np.abs(v) <= acts.vmax * (1 + tol)), (f.seq, v)
            assert np.all(np.abs(a) <= acts.amax * (1 + tol)), (f.seq, a)
            vprev = v
        else:
            np.testing.assert_array_equal(p, prev)
            vprev = np.zeros(acts.n)
        prev = p


steps = st.lists(
    st.lists(st.floats(-1.0, 1.0), min_size=7, max_size=7),
    min_size=2,
    max_size=25,
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    steps=steps,
    gaps=st.lists(st.floats(0.001, 0.6), min_size=25, max_size=25),
    scale=st.sampled_from([0.001, 0.02, 0.3, 3.0]),
    start=st.lists(st.floats(-2.5, 2.5), min_size=7, max_size=7),
)
def test_no_frame_ever_leaves_outside_its_limits(robot, acts, steps, gaps, scale, start):
    """Whatever the set-points (random walks of any speed, even outside the limits), every frame that
    leaves respects position, velocity and acceleration limits; refused set-points stop the motion."""
    start_v = np.clip(np.array(start) * np.r_[[1.0] * 6, [40.0]], acts.lower, acts.upper)
    vals = start_v + scale * np.cumsum(np.array(steps) * np.r_[[1.0] * 6, [40.0]], axis=0)
    stamps = np.cumsum(gaps[: len(steps)])
    dt = 0.01
    # live source: no preflight, the runtime gate alone
    cap, clock = _Capture(), VirtualClock()
    s = Streamer(cap, acts, StreamOptions(), None, clock=clock)
    s.start(start_v, background=False)
    s.send_path(stamps, vals)
    s.finish()
    s.run()
    rep = s.close()
    assert rep.status in ("done", "refused")
    _check_frames(cap.frames, acts, start_v, dt)
    # whole path: preflight refuses (nothing sent) or every frame is within limits
    cap2 = _Capture()
    t, v = np.r_[0.0, stamps], np.vstack([start_v, vals])
    record = MotionRecord("", "plan", "success", True, True, 0, 0, robot, Scene(), t, acts.actuation(v))
    try:  # admission verifies the set-points as sent: a refusal there sends nothing either
        rep2 = Streamer(cap2, acts, StreamOptions()).run_path(admit(record, acts))
    except AdmissionError:
        rep2 = None
    assert rep2 is None or rep2.status in ("done", "refused")
    if rep2 is None or rep2.status == "refused":
        assert cap2.frames == []
    _check_frames(cap2.frames, acts, start_v, dt)


# -------------------------------------------------------------- bad input
def _write(tmp_path, res, name="r.json"):
    p = tmp_path / name
    atomic_write_json(p, res)
    return str(p)


def _run_cli(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda r: r["waypoints"][3]["q"].__setitem__(2, None), "waypoints[3].q[2]: must be finite"),
        (lambda r: r["waypoints"][4].__setitem__("t", 0.1), "waypoints[4].t: time goes backwards"),
        (lambda r: r["waypoints"][4].__setitem__("t", r["waypoints"][3]["t"]), "waypoints[4].t: time must increase"),
        (lambda r: r["waypoints"][0]["q"].pop(), "waypoints[0].q: expected 7 values (3 cables per segment"),
        (lambda r: r["waypoints"][1].pop("t"), "waypoints[1].t: missing (required)"),
        (lambda r: r["waypoints"][2].pop("q"), "waypoints[2].q: missing (required)"),
        (lambda r: r.__setitem__("waypoints", []), "waypoints: expected a non-empty list"),
        (lambda r: r["robot"].pop("actuators"), "robot.actuators: the result's robot has no [robot.actuators]"),
    ],
)
def test_bad_results_give_one_line_errors(result, tmp_path, capsys, mutate, message):
    res = json.loads(json.dumps(result))
    mutate(res)
    code, _, err = _run_cli(["stream", _write(tmp_path, res), "--dry-run", str(tmp_path / "f.bin")], capsys)
    assert code == 2
    assert message in err
    assert err.count("\n") == 1


def test_unknown_actuator_in_robot_file(result, tmp_path, capsys):
    text = ROBOT_FILE.read_text() + "\n[robot.actuators.servo.s3c1]\nsign = -1\n"
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    code, _, err = _run_cli(
        ["stream", _write(tmp_path, result), "--dry-run", str(tmp_path / "f.bin"), "--robot", str(bad)], capsys
    )
    assert code == 2 and "robot.actuators.servo.s3c1: unknown actuator (known: s1c1" in err


def test_bad_live_setpoints(acts):
    cap = _Capture()
    s = Streamer(cap, acts, StreamOptions())
    with pytest.raises(StreamError, match="not started"):
        s.send_values(0.0, np.zeros(7))
    s.start(np.zeros(7), background=False)
    s.send_values(0.0, np.zeros(7))
    with pytest.raises(InputError, match=r"t: set-point times must increase \(got 0 s after 0 s\)"):
        s.send_values(0.0, np.zeros(7))
    with pytest.raises(InputError, match="s1c2: must be finite, got nan"):
        s.send_values(1.0, [0, np.nan, 0, 0, 0, 0, 0])
    with pytest.raises(InputError, match=r"values: expected 7 \(s1c1"):
        s.send_values(1.0, np.zeros(6))
    with pytest.raises(InputError, match="t: must be finite"):
        s.send_values(float("nan"), np.zeros(7))
    with pytest.raises(InputError, match=r"q: expected shape \(N, 7\)"):
        s.send_setpoint(1.0, np.zeros(5))
    s.finish()
    with pytest.raises(StreamError, match="finish"):
        s.send_values(2.0, np.zeros(7))
    s.close()


def test_stream_options_from_table():
    o = StreamOptions.from_table(Table({"rate": 200, "watchdog": 0.05}, "stream"))
    assert (o.rate, o.watchdog, o.dt) == (200.0, 0.05, 0.005)
    assert (o.ack_timeout, o.following_tolerance) == (0.25, 5.0)  # the documented defaults
    o = StreamOptions.from_table(Table({"ack_timeout": 0.4, "following_tolerance": 0.5}, "stream"))
    assert (o.ack_timeout, o.following_tolerance) == (0.4, 0.5)
    with pytest.raises(InputError, match=r"stream\.following_tolerance: must be > 0"):
        StreamOptions.from_table(Table({"following_tolerance": -1}, "stream"))
    with pytest.raises(InputError, match=r"stream\.rte: unknown key"):
        StreamOptions.from_table(Table({"rte": 1}, "stream"))
    with pytest.raises(InputError, match=r"stream\.watchdog: must be > 0"):
        StreamOptions.from_table(Table({"watchdog": 0}, "stream"))


# -------------------------------------------------------------------- CLI
def test_cli_dry_run_writes_the_frames_and_the_log(result, tmp_path, capsys, acts):
    frames, log = tmp_path / "frames.bin", tmp_path / "run.jsonl"
    res = _write(tmp_path, result)
    code, out, _ = _run_cli(["stream", res, "--dry-run", str(frames), "--log", str(log), "--rate", "50"], capsys)
    assert code == 0, out
    assert out.startswith(f"streaming {res} (11 waypoints, 1.50 s, ~76 set-points at 50 Hz)")
    decoded = read_stream_file(frames.read_bytes())
    moves = [f for f in decoded if f.kind == MOVE]
    assert len(moves) == 76 and decoded[-1].kind == HOLD
    assert [f.seq for f in decoded] == list(range(1, len(decoded) + 1))
    assert [r["seq"] for r in tx_frames(log)] == [f.seq for f in decoded]
    np.testing.assert_allclose(moves[-1].values, acts.command(np.asarray(result["waypoints"][-1]["q"])))


def test_cli_streams_to_sim_device_subprocess(result, tmp_path, capsys):
    cmd = [sys.executable, "-m", "crtraj.cli", "sim-device", "--udp", "127.0.0.1:0", "--duration", "600"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True, cwd=ROOT, preexec_fn=default_sigint)
    try:
        line = proc.stdout.readline()
        assert line.startswith("sim-device listening on udp://127.0.0.1:")
        addr = line.split("udp://")[1].split()[0]
        log = tmp_path / "run.jsonl"
        # a 1 s watchdog: this test is about the CLI, not about a loaded machine starving the device process
        argv = ["stream", _write(tmp_path, result), "--udp", addr, "--log", str(log), "--watchdog", "1.0"]
        code, out, _ = _run_cli(argv, capsys)
        assert code == 0, out
        assert out.splitlines()[1] == "done: completed"
        # crash safety: kill a streaming CLI mid-run; the record holds complete lines up to the kill
        log2 = tmp_path / "killed.jsonl"
        slow = _write(tmp_path, result, "slow.json")
        sp = subprocess.Popen(
            # the device now stands at the path's end: --approach brings it back to the start first
            [
                sys.executable,
                "-m",
                "crtraj.cli",
                "stream",
                slow,
                "--udp",
                addr,
                "--log",
                str(log2),
                "--time-scale",
                "10",
                "--approach",
                "--watchdog",
                "1.0",
            ],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + 300  # a hang bound only: the outcome is the log's content, not its speed
        while time.monotonic() < deadline and (not log2.exists() or log2.read_text().count('"kind":"move"') < 30):
            assert sp.poll() is None, "the streaming CLI ended early"
            time.sleep(0.05)
        os.kill(sp.pid, signal.SIGKILL)
        sp.wait()
        lines = log2.read_text().splitlines()
        complete = [json.loads(x) for x in lines[:-1]]
        assert sum(r.get("kind") == "move" for r in complete) >= 29
        assert not any(r["type"] == "report" for r in complete)
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=300)  # a hang bound only
    assert "sim-device stopped: received" in out


# ------------------------------------------- acknowledgements, following error, sessions (virtual clock)
def core_run(acts, path, *, core=None, opts=None, log=None, intercept=None, approach=False, **kw):
    """Stream `path` to an in-process DeviceCore on the streamer's own virtual clock."""
    clock = VirtualClock()
    link = CoreLink(core or DeviceCore(acts), clock)
    link.intercept = intercept
    s = Streamer(link, acts, opts or StreamOptions(), log, realtime=True, clock=clock, **kw)
    return s, link, s.run_path(path, approach=approach)


def test_core_link_run_is_done_and_frames_carry_one_random_session(acts, result, tmp_path):
    path = admitted(result, acts)
    s, link, rep = core_run(acts, path, log=tmp_path / "run.jsonl")
    assert rep.ok, rep.message
    frames = [Frame.decode(b) for b in link.sent]
    assert frames[0].kind == PING and frames[0].values.tolist() == [0.01]
    assert {f.session for f in frames} == {s.session} and 0 < s.session < 2**32
    assert rep.device["limited"] == 0 and rep.device["stale"] == 0  # a gated path never trips the device
    s2, _, _ = core_run(acts, path)
    assert s2.session != s.session  # random per run (a collision has probability 2^-32)


def test_forged_max_sequence_frame_does_not_lock_out_the_run(acts, result, tmp_path):
    """Issue 11: one MOVE frame with seq 0xFFFFFFFF locked the host out for the rest of the run."""
    path = admitted(result, acts)
    state = {"n": 0}
    holder: dict = {}

    def forge(frame: bytes) -> bytes:
        state["n"] += 1
        if state["n"] == 50:
            link, sess = holder["link"], Frame.decode(frame).session
            for forged_session in (sess, sess ^ 1, 0):
                link.inject(Frame(MOVE, 0xFFFFFFFF, 9.0, acts.upper, forged_session).encode())
        return frame

    clock = VirtualClock()
    link = CoreLink(DeviceCore(acts), clock)
    holder["link"] = link
    link.intercept = forge
    rep = Streamer(link, acts, StreamOptions(), tmp_path / "r.jsonl", realtime=True, clock=clock)
    rep = rep.run_path(path)
    assert rep.ok, rep.message
    assert rep.device["stale"] == 1 and rep.device["foreign"] == 2
    assert sum(a.kind == MOVE for a in link.core.applied) == 151  # every legitimate MOVE applied
    assert all(a.seq != 0xFFFFFFFF for a in link.core.applied)


def test_sequence_numbers_wrap_and_a_restarted_streamer_is_not_locked_out(acts, result):
    """A run whose sequence numbers wrap past 0xFFFFFFFF completes, and so does the next run
    (a new session) on the same device, whatever sequence numbers the first one left behind."""
    path = admitted(result, acts)
    core = DeviceCore(acts)
    _, _, rep = core_run(acts, path, core=core, first_seq=0xFFFFFFFF - 40)
    assert rep.ok, rep.message
    seqs = [a.seq for a in core.applied]
    assert 0xFFFFFFFF in seqs and 0 in seqs and core.counts["stale"] == 0
    n1 = len(seqs)
    # the device stands at the path's end: the next run approaches the start first
    _, _, rep2 = core_run(acts, path, core=core, approach=True)
    assert rep2.ok, rep2.message
    assert core.counts["sessions"] == 2 and core.counts["stale"] == 0
    assert [a.seq for a in core.applied][n1:] == list(range(1, len(core.applied) - n1 + 1))


def test_device_that_stops_acknowledging_is_held_at_once(acts, result, tmp_path):
    """The device stops applying set-points (as it did after the forged frame): the streamer holds
    within ack_timeout of the first unacknowledged frame and reports why, not `not-settled` at the end."""
    log = tmp_path / "run.jsonl"
    path = admitted(result, acts)
    opts = StreamOptions(ack_timeout=0.2)
    sent = {"n": 0}

    def deaf_after_40(frame: bytes) -> bytes | None:
        sent["n"] += 1
        return frame if sent["n"] <= 40 else None

    _, _, rep = core_run(acts, path, opts=opts, log=log, intercept=deaf_after_40)
    assert rep.status == "ack-stalled", rep.message
    assert rep.message.startswith("device stopped acknowledging: set-point seq ") and "\n" not in rep.message
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    tx = [r for r in lines if r["type"] == "tx"]
    first_lost = tx[40]["wall"]  # tx[0] is the PING
    held = next(r["wall"] for r in lines if r["type"] == "event" and r["event"] == "ack-stalled")
    assert 0.2 < held - first_lost <= 0.2 + 2 * opts.dt + 1e-9
    _braked_then_held(lines, "ack-stalled", acts, opts.dt)
    assert rep.moves < 151


def test_device_that_does_not_follow_is_held_with_a_following_error(robot, acts, result, tmp_path):
    """A device whose z stage is 10 times slower than the robot file says acknowledges every frame
    but falls behind: the streamer holds at the first telemetry whose error exceeds the tolerance."""
    log = tmp_path / "run.jsonl"
    d = robot.to_dict()
    d["actuators"]["z"]["velocity_limit"] = 2.0
    slow = Actuators.from_robot(type(robot).from_table(Table(d, "robot")))
    opts = StreamOptions(following_tolerance=0.5)
    path = admitted(result, acts)
    _, _, rep = core_run(acts, path, core=DeviceCore(slow), opts=opts, log=log)
    assert rep.status == "following-error", rep.message
    assert rep.message.startswith("following error: z measured ") and "> following_tolerance 0.5" in rep.message
    # independent re-computation from the run record: |measured - acknowledged set-point| per rx line
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    sent = {r["seq"]: np.array(r["values"]) for r in lines if r["type"] == "tx" and r["kind"] != "ping"}
    over = [r["wall"] for r in lines if r["type"] == "rx" and r["ack"] in sent
            and np.max(np.abs(np.array(r["positions"]) - sent[r["ack"]])) > 0.5]  # fmt: skip
    held = next(r["wall"] for r in lines if r["type"] == "event" and r["event"] == "following-error")
    assert over and held == over[0]
    assert rep.device["limited"] > 0  # the device also flagged the steps it could not follow


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_hostile_telemetry_never_crashes_or_stops_the_streamer(acts, result, data):
    """Garbage, truncated and re-sealed datagrams, and well-formed telemetry of another session, mixed
    into the device's telemetry: the run still completes, and every bad datagram is counted."""
    path = admitted(result, acts)
    junk = data.draw(st.lists(hostile_datagrams(acts), min_size=1, max_size=8))
    foreign = Telemetry(10**6, 0.0, 3, 0, acts.upper, session=1).encode()
    clock = VirtualClock()
    link = CoreLink(DeviceCore(acts), clock)
    s = Streamer(link, acts, StreamOptions(), None, realtime=True, clock=clock, session=2)
    real_receive = link.receive
    calls = {"n": 0}

    def receive() -> list[bytes]:
        calls["n"] += 1
        out = real_receive()
        return [*junk, foreign, *out] if calls["n"] % 10 == 0 else out

    link.receive = receive
    rep = s.run_path(path)
    assert rep.ok, rep.message
    assert rep.telemetry_errors >= calls["n"] // 10  # at least the foreign telemetry, every time


def test_ctrl_c_brakes_within_the_limits_and_reports_the_frames_sent(acts, result):
    """Issue 36: Ctrl-C while the device moves. The stream brakes to rest within the acceleration limits before it
    closes (it used to close after one frame of its stop, latching the last set-point: a stop as hard as the device
    can), and the figures it reports are those of every frame that left, the holds included, recomputed here from
    the wire by finite differences from rest."""
    path = admitted(result, acts)
    clock = VirtualClock()
    link = CoreLink(DeviceCore(acts), clock)
    s = Streamer(link, acts, StreamOptions(), None, realtime=True, clock=clock)
    real_receive, calls = link.receive, {"n": 0}

    def receive() -> list[bytes]:
        calls["n"] += 1
        if calls["n"] == 120:  # well into the motion
            raise KeyboardInterrupt
        return real_receive()

    link.receive = receive
    rep = s.run_path(path)
    assert rep.status == "interrupted" and rep.brakes == 1 and rep.latched == 0, (rep, calls)
    frames = [Frame.decode(b) for b in link.sent]
    frames = [f for f in frames if f.kind in (MOVE, HOLD, ESTOP)]
    assert frames[-1].kind == HOLD
    P = np.array([f.values for f in frames])
    V = np.diff(P, axis=0) / 0.01
    A = np.diff(np.vstack([np.zeros(acts.n), V]), axis=0) / 0.01
    moving = np.abs(V[-40:-20]).max(axis=0) / acts.vmax
    assert moving.max() > 0.05  # interrupted while moving: a latch would have stopped in one period
    got = s.limit_fractions()
    assert got["max_acceleration_fraction"] == pytest.approx(np.max(np.abs(A) / acts.amax), rel=1e-9)
    assert got["max_velocity_fraction"] == pytest.approx(np.max(np.abs(V) / acts.vmax), rel=1e-9)
    assert got["max_acceleration_fraction"] <= 1.0 + 1e-9


def test_a_late_source_while_moving_brakes_within_the_limits_and_never_gets_refused(acts):
    """The live loop late under load (an underrun shorter than the watchdog) while the device moves: the stream
    used to send HOLD frames, a stop in one period that zeroes the gate's velocity, so the late set-points that then
    arrived were refused for an acceleration of v/dt ("set-point refused: z acceleration ... exceeds limit").
    Now the stream cannot stop in one period within the limits, so it latches the recoverable ``source stalled``
    hold at once and brakes; every frame that leaves is within the limits (recomputed independently)."""
    clock, cap = VirtualClock(), _Capture()
    dt = 0.01
    s = Streamer(cap, acts, StreamOptions(watchdog=0.1, prebuffer=0.05), None, clock=clock)
    start = np.zeros(acts.n)
    s.start(start, background=False)
    z = acts.n - 1
    v = 0.5 * acts.vmax[z]
    k_ramp = int(np.ceil(v / (0.5 * acts.amax[z]) / dt))  # reach speed v at half the acceleration limit
    speed = np.minimum(np.arange(1, 60) / k_ramp, 1.0) * v
    path = np.tile(start, (speed.size, 1))
    path[:, z] = np.cumsum(speed) * dt

    def tick() -> None:
        s._step(clock.now(), False)
        clock.advance(dt)

    s.send_path(dt * np.arange(40), path[:40])  # the source queues up to t = 0.39 s, then is late
    while s.buffer.sent_stamp < 0.39 - 1e-9:
        tick()
    assert s.state == "streaming" and s.position[z] > 0.0
    tick()  # one period late (well inside the watchdog): moving, the stream cannot just stop
    with pytest.raises(StreamError, match="held"):  # braking already: the late set-points are not taken
        s.send_path(dt * np.arange(40, 59), path[40:59])
    assert s.state == "held" and s.reason.startswith("source stalled"), s.reason
    with pytest.raises(StreamError, match="resume: stream is still braking to rest"):
        s.resume()  # resetting the gate at rest mid-stop would let the next frame stop in one period
    for _ in range(40):
        tick()
    assert s.state == "held" and s.reason.startswith("source stalled"), s.reason
    s.resume()  # at rest: the source starts again from where the stop ended
    here = s.position
    s.send_path(1.0 + dt * np.arange(8), np.tile(here, (8, 1)))
    s.finish()
    for _ in range(20):
        tick()
    rep = s.close()
    assert rep.status == "done", rep.message
    assert "refused" not in [e[1] for e in rep.events], rep.events
    assert rep.brakes == 1 and rep.brake_frames > 0
    _check_frames(cap.frames, acts, start, dt)
