"""Verified as sent (crtraj.hardware.verify): what admission accepts passes an independent dense check of the
frames themselves; what it refuses has a real violation; a planned approach goes around an obstacle; a slowed
replay among moving obstacles streams when it stays safe and is refused when it does not.

The independent checks below share no code with the library's: they convert actuator values back to
configurations with their own least squares, sample the body at many backbone points along the straight
frame-to-frame motions, and measure point-to-centre distances against the scene's true obstacle functions.
Devices are in-process (`tests/devlink.py`) on the streamer's virtual clock: no wall clock, no sockets.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from devlink import CoreLink
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crtraj.app.devices import plan_approach
from crtraj.cli import main
from crtraj.control.ports import DeviceError
from crtraj.control.tracking import ServoModel
from crtraj.core.clock import VirtualClock
from crtraj.core.errors import AdmissionError
from crtraj.core.fileio import to_jsonable
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.link import DeviceLink
from crtraj.hardware.protocol import MOVE, Frame, read_stream_file
from crtraj.hardware.setpoints import SetpointPath
from crtraj.hardware.sim import DeviceCore
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.hardware.verify import FrameVerifier
from crtraj.io.results import read_result
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def acts(robot):
    return Actuators.from_robot(robot)


# ------------------------------------------------------------ independent checks
def limit_violation(acts, values, dt, start=None) -> bool:
    """True when any frame breaks a position, velocity or acceleration limit (own finite differences)."""
    P = np.asarray(values)
    p0 = P[0] if start is None else np.asarray(start)
    tol = 1e-9
    lo = acts.lower - tol * np.maximum(np.abs(acts.lower), 1)
    hi = acts.upper + tol * np.maximum(np.abs(acts.upper), 1)
    if np.any((lo > P) | (hi < P)):
        return True
    V = np.diff(np.vstack([p0, P]), axis=0) / dt
    A = np.diff(np.vstack([np.zeros(P.shape[1]), V]), axis=0) / dt
    return bool(np.any(np.abs(V) > acts.vmax * (1 + tol)) or np.any(np.abs(A) > acts.amax * (1 + tol)))


def configs_of(robot, acts, values) -> tuple[np.ndarray, np.ndarray]:
    """Configurations of actuator values by this test's own inversion, and each frame's cable misfit (mm)."""
    scale = np.concatenate([acts.sign[:-1] / acts.spool_radius, acts.sign[-1:]])
    q = acts.rest + (np.asarray(values) - acts.zero_offset) / scale
    A, q0 = robot.cable_matrix()
    X = np.linalg.lstsq(A, (q - q0).T, rcond=None)[0].T
    return X, np.max(np.abs(X @ A.T + q0 - q), axis=1)


def dense_clearance(model, scene, stamps, X, sub=4, points=60) -> float:
    """Smallest body clearance beyond D_sf (mm) along the straight motions between frames, sampled `sub`
    times per frame period at `points` backbone points, against the obstacles at each sample's own time."""
    if scene.n_obstacles == 0:
        return np.inf
    if len(X) == 1:
        XS, TS = X, np.asarray(stamps)
    else:
        u = np.arange(sub) / sub
        XS = (X[:-1, None, :] + u[None, :, None] * (X[1:] - X[:-1])[:, None, :]).reshape(-1, X.shape[1])
        TS = (stamps[:-1, None] + u[None, :] * np.diff(stamps)[:, None]).ravel()
        XS, TS = np.vstack([XS, X[-1:]]), np.append(TS, stamps[-1])
    P = model.points(XS, points)  # (N, points, 3)
    C, R = scene.states(TS)  # (N, M, 3), (N, M)
    d = np.linalg.norm(P[:, :, None, :] - C[:, None, :, :], axis=-1) - R[:, None, :]
    return float(np.min(d) - model.robot.body_radius - scene.safety_distance)


# --------------------------------------------------------------- (a) property
def _record(robot, model, scene, t, X) -> MotionRecord:
    return MotionRecord("", "plan", "exact", True, True, 0, 0, robot, scene, np.asarray(t), model.cables(X))


obstacle = st.fixed_dictionaries(
    {
        "c": st.tuples(st.floats(-90, 90), st.floats(-90, 90), st.floats(150, 450)),
        "r": st.floats(4.0, 25.0),
        "to": st.one_of(st.none(), st.tuples(st.floats(-90, 90), st.floats(-90, 90), st.floats(150, 450))),
        "dur": st.floats(0.5, 4.0),
        "amp": st.floats(0.0, 1.0),
        "omega": st.floats(0.0, 4.0),
    }
)


def _scene(obs) -> Scene:
    return Scene(obstacles=tuple(_obstacle(o) for o in obs))


def _obstacle(o) -> Obstacle:
    amp = o["amp"] * o["r"] * 0.5
    return Obstacle(center=o["c"], radius=o["r"], amplitude=amp, omega=o["omega"], to=o["to"], duration=o["dur"])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    way=st.lists(st.tuples(*[st.floats(-0.9, 0.9)] * 4, st.floats(-60.0, 40.0)), min_size=2, max_size=4),
    gaps=st.lists(st.floats(0.3, 4.0), min_size=3, max_size=3),
    obs=st.lists(obstacle, min_size=1, max_size=2),
    scale=st.sampled_from([1.0, 1.7]),
)
def test_accepted_frames_pass_an_independent_check_and_refused_ones_have_a_real_violation(
    robot, model, acts, way, gaps, obs, scale
):
    X = np.array(way, dtype=float)
    X[:, :4] *= 0.45  # bending within limits for both segments (coupled)
    if np.any(robot.limit_violation(X) > 0):
        return
    t = np.concatenate([[0.0], np.cumsum(gaps[: len(X) - 1])])
    scene = _scene(obs)
    rate = 50.0
    try:
        motion = admit(_record(robot, model, scene, t, X), acts, time_scale=scale, rate=rate)
    except AdmissionError as exc:
        refused = str(exc)
        # what would have been sent (the path's own sampling), searched for a violation by this test
        path = SetpointPath.from_actuation(t, model.cables(X), acts)
        stamps, values = (path.scaled(scale) if scale != 1.0 else path).sample(rate)
        Xs, misfit = configs_of(robot, acts, values)
        # the library's check is conservative by at most `slack` mm (sagitta, sample spacing, one frame of
        # obstacle motion); the test's own sampling adds at most 0.3 mm here
        slack = FrameVerifier(robot, acts, scene, 1 / rate).slack
        real = (
            limit_violation(acts, values, 1 / rate)
            or np.max(misfit) > 0.05
            or np.any(robot.limit_violation(Xs) > 1e-9)
            or dense_clearance(model, scene, stamps, Xs) < slack + 0.3
        )
        assert real, f"refused without a violation the independent check can find: {refused}"
        return
    Xs, misfit = configs_of(robot, acts, motion.values)
    assert not limit_violation(acts, motion.values, 1 / rate)
    assert np.max(misfit) <= 0.05 and np.all(robot.limit_violation(Xs) <= 1e-9)
    assert dense_clearance(model, scene, motion.stamps, Xs) >= -1e-6


# --------------------------------------------- (b) a result whose set-points, as sent, hit an obstacle
XB = np.array([0.8, 0.0, 0.8, 0.0, 0.0])  # bent towards +x: tip near (75.8, 0, 379) mm


def _result(robot, model, scene, t, X) -> dict:
    """A result document that claims success (summary clean) for the timed configurations X."""
    wps = [
        {"t": float(t[k]), "x": X[k], "q": model.cables(X[k]), "tip": model.tip_position(X[k])} for k in range(len(t))
    ]
    doc = {"kind": "plan", "schema": 1, "robot": robot.to_dict(), "scene": scene.to_dict(), "status": "exact"}
    return to_jsonable(doc | {"success": True, "summary": {"min_clearance_mm": 10.0}, "waypoints": wps})


def _stream_cli(tmp_path: Path, res: dict, capsys, *extra: str) -> tuple[int, list[str]]:
    src = tmp_path / "r.json"
    src.write_text(json.dumps(res))
    argv = ["stream", str(src), "--dry-run", str(tmp_path / "f.bin"), "--log", str(tmp_path / "l.jsonl"), *extra]
    rc = main(argv)
    return rc, capsys.readouterr().err.strip().splitlines()


def test_a_result_whose_set_points_hit_an_obstacle_is_refused_from_python_and_the_cli(
    robot, model, acts, tmp_path, capsys
):
    """The result's own summary says safe; its motion (straight -> bent) sweeps through a sphere. The
    library finds it from the frames themselves: refused with the time, nothing sent, exit 1."""
    X = np.stack([robot.straight(0.0), XB])
    mid = model.points(0.5 * XB, 11)[-1]  # the tip half way
    scene = Scene(obstacles=(Obstacle(center=tuple(mid), radius=6.0),))
    res = _result(robot, model, scene, [0.0, 3.0], X)
    rate = 100.0
    stamps, values = SetpointPath.from_actuation([0.0, 3.0], model.cables(X), acts).sample(rate)
    assert dense_clearance(model, scene, stamps, configs_of(robot, acts, values)[0]) < 0  # really hits
    with pytest.raises(AdmissionError, match=r"refused: body closer than the safety distance .* t=1\.\d+ s"):
        admit(read_result(res).motion_record(), acts)
    rc, err = _stream_cli(tmp_path, res, capsys)
    assert rc == 1 and len(err) == 1 and "body closer than the safety distance" in err[0]
    assert not (tmp_path / "f.bin").exists()
    # the control: without the obstacle it streams, and the frames sent are exactly the verified ones
    res_ok = _result(robot, model, Scene(), [0.0, 3.0], X)
    rc, err = _stream_cli(tmp_path, res_ok, capsys)
    assert rc == 0, err
    sent = np.array([f.values for f in read_stream_file((tmp_path / "f.bin").read_bytes()) if f.kind == MOVE])
    motion = admit(read_result(res_ok).motion_record(), acts)
    np.testing.assert_array_equal(sent, motion.values)


def test_a_no_safety_replan_result_is_refused_from_the_streamer_and_the_cli(robot, model, acts, tmp_path, capsys):
    """A --no-safety run (its frames harmless here) never reaches a device: Python and CLI, nothing sent."""
    X = np.stack([robot.straight(0.0), 0.2 * XB])
    res = _result(robot, model, Scene(), [0.0, 3.0], X)
    res.update(kind="replan", summary={"collisions": 0, "safety_violations": 0, "safety": False})
    clock = VirtualClock()
    link = CoreLink(DeviceCore(acts), clock)
    with pytest.raises(AdmissionError, match="--no-safety"):
        Streamer(link, acts, clock=clock).run_path(admit(read_result(res).motion_record(), acts))
    assert link.sent == []
    rc, err = _stream_cli(tmp_path, res, capsys)
    assert rc == 1 and len(err) == 1 and "--no-safety" in err[0] and not (tmp_path / "f.bin").exists()


# ------------------------------------------------------------- (c) planned approach
def _core_stream(acts, motion, **kw):
    clock = VirtualClock()
    link = CoreLink(DeviceCore(acts), clock)  # the device starts straight at z = 0
    s = Streamer(link, acts, StreamOptions(), None, realtime=True, clock=clock)
    rep = s.run_path(motion, approach=True, **kw)
    moves = [f for f in map(Frame.decode, link.sent) if f.kind == MOVE]
    return rep, moves, link


def test_an_approach_through_an_obstacle_is_planned_around_it(robot, model, acts):
    """The device is straight, the result starts bent; a sphere sits on the straight move between them.
    The straight approach is refused; the planned one streams, and every frame sent (approach and motion)
    keeps D_sf by the test's own dense check."""
    mid = model.points(0.5 * XB, 11)[-1]
    scene = Scene(obstacles=(Obstacle(center=tuple(mid), radius=6.0),))
    X = np.stack([XB, XB + np.array([0.0, 0.1, 0.0, 0.1, -5.0])])
    motion = admit(read_result(_result(robot, model, scene, [0.0, 2.0], X)).motion_record(), acts)
    rep, moves, _ = _core_stream(acts, motion)  # default: the straight move, verified
    assert rep.status == "refused" and "approach: body closer than the safety distance" in rep.message
    assert moves == []
    rep, moves, link = _core_stream(acts, motion, plan_approach=plan_approach)
    assert rep.ok, rep.message
    values = np.array([f.values for f in moves])
    stamps = np.array([f.stamp for f in moves])
    np.testing.assert_array_equal(values[-len(motion.values) :], motion.values)  # the motion as verified
    assert len(values) > len(motion.values) and np.all(stamps[: -len(motion.values)] < 0.0)  # ends at t = 0
    start = acts.zero_offset
    assert not limit_violation(acts, values, 0.01, start=start)
    Xs, misfit = configs_of(robot, acts, np.vstack([start, values]))
    assert np.max(misfit) <= 0.05
    assert dense_clearance(model, scene, np.append(stamps[0] - 0.01, stamps), Xs) >= 0.0
    np.testing.assert_allclose(link.core.telemetry(link.clock.now()).positions, values[-1], atol=0.02)


def test_an_approach_that_cannot_be_made_safe_is_refused_and_nothing_is_sent(robot, model, acts, tmp_path, capsys):
    """The device's own pose is inside a sphere (its tip): no safe approach exists; one line, no MOVE."""
    scene = Scene(obstacles=(Obstacle(center=(0.0, 0.0, 400.0), radius=8.0),))
    X = np.stack([XB, XB + np.array([0.0, 0.1, 0.0, 0.1, -5.0])])
    motion = admit(read_result(_result(robot, model, scene, [0.0, 2.0], X)).motion_record(), acts)
    rep, moves, _ = _core_stream(acts, motion, plan_approach=plan_approach)
    assert rep.status == "refused" and "no safe approach" in rep.message and "\n" not in rep.message
    assert moves == []


# ------------------------------------------------- (d) slowed replay among moving obstacles
def test_a_slowed_replay_streams_when_it_stays_safe_and_is_refused_when_it_does_not(
    robot, model, acts, tmp_path, capsys
):
    """The robot bends away from the straight pose in 1 s; a sphere arrives on the straight pose's tip at
    t = 2 s. Played as planned or 1.5 times slower the robot has left in time: it streams (CLI, exit 0)
    and the frames pass the test's dense check against the sphere's true motion. Ten times slower the
    robot is still there when the sphere arrives: refused, one line, nothing sent."""
    tip = model.points(robot.straight(0.0), 11)[-1]
    scene = Scene(obstacles=(Obstacle(center=(tip[0] - 150.0, tip[1], tip[2]), radius=10.0, to=tuple(tip),
                                      duration=2.0),))  # fmt: skip
    s = np.linspace(0.0, 1.0, 6)
    X = robot.straight(0.0) + (XB - robot.straight(0.0)) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    res = _result(robot, model, scene, 1.0 * s, X)
    for scale in ("1", "1.5"):
        rc, err = _stream_cli(tmp_path, res, capsys, "--time-scale", scale)
        assert rc == 0, err
        frames = [f for f in read_stream_file((tmp_path / "f.bin").read_bytes()) if f.kind == MOVE]
        stamps = np.array([f.stamp for f in frames])
        Xs, _ = configs_of(robot, acts, np.array([f.values for f in frames]))
        assert abs(stamps[-1] - float(scale)) < 1e-9
        assert dense_clearance(model, scene, stamps, Xs) >= 0.0
    (tmp_path / "f.bin").unlink()
    rc, err = _stream_cli(tmp_path, res, capsys, "--time-scale", "10")
    assert rc == 1 and len(err) == 1 and "slowed 10 times" in err[0] and "body closer than the safety" in err[0]
    assert not (tmp_path / "f.bin").exists()
    # the independent check agrees that the slowed motion is unsafe
    path = SetpointPath.from_actuation(1.0 * s, model.cables(X), acts).scaled(10.0)
    stamps, values = path.sample(100.0)
    assert dense_clearance(model, scene, stamps, configs_of(robot, acts, values)[0]) < 0.0


# ------------------------------------------------------------ live: each step verified as sent
def test_live_steps_are_verified_against_the_loops_scene_snapshot(robot, model, acts):
    """DeviceLink checks each step's frames (the follower's output) against the scene the loop used: a step
    into a sphere that the snapshot holds is not sent (DeviceError with the time, the link holds); the same
    step against an empty snapshot is sent, and what leaves equals what was checked."""
    clock = VirtualClock()
    link = CoreLink(DeviceCore(acts), clock)
    s = Streamer(link, acts, StreamOptions(prebuffer=0.1), None, realtime=True, clock=clock)
    s.start(background=False)
    tip = model.points(robot.straight(0.0), 11)[-1]
    # 0.2 mm of clearance beyond D_sf above the tip: the step's first half millimetre up breaks it
    above = tip + np.array([0.0, 0.0, 11.2])
    snapshot = {"scene": Scene(obstacles=(Obstacle(center=tuple(above), radius=3.0),))}
    verifier = FrameVerifier(robot, acts, Scene(), 0.01, model=model)
    dl = DeviceLink(s, ServoModel(robot, 0.05, 0.1), 0.1, verifier=verifier, scene_now=lambda: snapshot["scene"])
    dl.begin(0.0)
    q0 = robot.cables(robot.straight(0.0))
    cmds = np.repeat(robot.cables(robot.straight(8.0))[None], 5, axis=0)  # up 8 mm, into the sphere
    queued = len(s.buffer)
    with pytest.raises(DeviceError, match=r"step at t=0\.00 s refused before sending: body closer than"):
        dl.move(0.0, q0, cmds, 0.02)
    assert len(s.buffer) == queued and s.state == "held" and dl.refused_steps == 1
    snapshot["scene"] = Scene()
    dl.move(0.0, q0, cmds, 0.02)  # resumes from the hold; nothing in the way now
    values = np.array(s.buffer.values[-10:])
    assert verifier.failure(np.array(s.buffer.stamps[-10:]), values, start=acts.command(q0)) is None
