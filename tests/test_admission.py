"""Admission (crtraj.hardware.admission): failed, colliding, --no-safety, scene-less and other-robot results
are refused in the library, from Python (Streamer directly, nothing sent) and from the CLI (nothing sent, exit 1)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.cli import main
from crtraj.core.errors import AdmissionError
from crtraj.core.fields import Table
from crtraj.core.fileio import to_jsonable
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion, admit
from crtraj.hardware.protocol import MOVE, read_stream_file
from crtraj.hardware.setpoints import SetpointPath
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.hardware.transport import Transport
from crtraj.io.results import read_result
from crtraj.model.robot import Robot
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

X1 = np.array([0.3, -0.2, 0.1, 0.4, -8.0])


class _Capture(Transport):
    """A fake link that records every frame handed to it."""

    has_telemetry = False
    description = "capture"

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def send(self, frame: bytes) -> None:
        self.frames.append(frame)

    def receive(self) -> list[bytes]:
        return []


def good_result(robot, model) -> dict:
    """A successful 2 s plan of `robot` among one fixed obstacle far from the body."""
    s = np.linspace(0.0, 1.0, 11)
    x0 = robot.straight(0.0)
    X = x0 + (X1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    scene = Scene(obstacles=(Obstacle(center=(120.0, 120.0, 400.0), radius=5.0),))
    C, R = scene.states(2.0 * s)
    wps = [
        {"t": 2.0 * s[k], "x": X[k], "q": model.cables(X[k]), "tip": model.tip_position(X[k]),
         "obstacles": {"centers": C[k], "radii": R[k]}}
        for k in range(len(s))
    ]  # fmt: skip
    doc = {"kind": "plan", "schema": 1, "robot": robot.to_dict(), "scene": scene.to_dict(), "status": "exact"}
    return to_jsonable(doc | {"success": True, "summary": {"min_clearance_mm": 50.0}, "waypoints": wps})


def failed(r: dict) -> None:
    r.update(success=False, status="timeout")


def colliding(r: dict) -> None:
    r.update(kind="replan", summary={"collisions": 7, "safety_violations": 9, "safety": True})


def no_safety(r: dict) -> None:
    r.update(kind="replan", summary={"collisions": 0, "safety_violations": 0, "safety": False})
    r["options"] = {"replan": {"safety": False}}


def no_scene(r: dict) -> None:
    r.pop("scene")


REFUSALS = [
    (failed, "success: false (status timeout)"),
    (colliding, "summary.collisions: 7 steps touch an obstacle"),
    (no_safety, "safety: false: made without the collision-free terms (--no-safety)"),
    (no_scene, "scene: missing"),
]


def other_robot(robot) -> Robot:
    d = robot.to_dict()
    d["segment"][1]["length"] = 150.0
    return Robot.from_table(Table(d, "robot"))


# ----------------------------------------------------------------- Python
def test_a_good_result_is_admitted_and_its_set_points_are_its_actuation(robot, model):
    res = good_result(robot, model)
    acts = Actuators.from_robot(robot)
    motion = admit(read_result(res).motion_record(), acts)
    q = np.array([w["q"] for w in res["waypoints"]])
    np.testing.assert_allclose(motion.path.values, acts.command(q), atol=1e-12)
    np.testing.assert_array_equal(motion.path.t, [w["t"] for w in res["waypoints"]])


@pytest.mark.parametrize(("mutate", "message"), REFUSALS, ids=["failed", "colliding", "no-safety", "no-scene"])
def test_admission_refuses_unsafe_results(robot, model, mutate, message):
    res = good_result(robot, model)
    mutate(res)
    with pytest.raises(AdmissionError, match="^" + message.replace("(", r"\(").replace(")", r"\)")):
        admit(read_result(res).motion_record(), Actuators.from_robot(robot))


def test_admission_refuses_a_result_for_another_robot(robot, model):
    other = other_robot(robot)
    record = read_result(good_result(robot, model)).motion_record()
    # each robot's name is followed by its own value (issue 36: it was "the device is 'x' (200, not 150)")
    match = r"^robot: made for robot '\w+' \(segment\[1\]\.length 200\), the device is robot '\w+' "
    match += r"\(segment\[1\]\.length 150\); a result for another robot is never sent: plan it again with"
    with pytest.raises(AdmissionError, match=match):
        admit(record, Actuators.from_robot(other), robot=other)


def test_streamer_sends_nothing_that_admission_did_not_let_through(robot, model):
    """The Streamer itself refuses: a raw set-point path, a hand-made AdmittedMotion and a motion admitted
    for another robot's actuators never produce a frame (checked on a fake transport)."""
    res = good_result(robot, model)
    acts = Actuators.from_robot(robot)
    q = np.array([w["q"] for w in res["waypoints"]])
    raw = SetpointPath.from_actuation([w["t"] for w in res["waypoints"]], q, acts)
    cap = _Capture()
    with pytest.raises(AdmissionError, match=r"^run_path: streams only a motion admitted by"):
        Streamer(cap, acts, StreamOptions()).run_path(raw)
    with pytest.raises(TypeError, match=r"made only by crtraj\.hardware\.admission\.admit"):
        AdmittedMotion(raw, robot, acts)
    motion = admit(read_result(res).motion_record(), acts)
    other = Actuators.from_robot(other_robot(robot))
    with pytest.raises(AdmissionError, match=r"^run_path: the motion was admitted for other actuators"):
        Streamer(cap, other, StreamOptions()).run_path(motion)
    assert cap.frames == []
    # the control: the admitted motion streams, every sampled set-point as a MOVE
    rep = Streamer(cap, acts, StreamOptions()).run_path(motion)
    assert rep.ok, rep.message
    assert rep.moves == round(motion.path.duration * 100) + 1 and len(cap.frames) == rep.frames


@pytest.mark.parametrize(("mutate", "message"), REFUSALS, ids=["failed", "colliding", "no-safety", "no-scene"])
def test_unsafe_results_never_reach_the_streamer_from_python(robot, model, mutate, message):
    """The Python path a user takes (read, admit, stream) stops at admission: the fake link gets nothing."""
    res = good_result(robot, model)
    mutate(res)
    cap = _Capture()
    acts = Actuators.from_robot(robot)
    with pytest.raises(AdmissionError):
        Streamer(cap, acts, StreamOptions()).run_path(admit(read_result(res).motion_record(), acts))
    assert cap.frames == []


# -------------------------------------------------------------------- CLI
def _stream(tmp_path: Path, res: dict, capsys, *extra: str) -> tuple[int, list[str]]:
    src = tmp_path / "r.json"
    src.write_text(json.dumps(res))
    argv = ["stream", str(src), "--dry-run", str(tmp_path / "f.bin"), "--log", str(tmp_path / "l.jsonl"), *extra]
    rc = main(argv)
    return rc, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize(("mutate", "message"), REFUSALS, ids=["failed", "colliding", "no-safety", "no-scene"])
def test_cli_refuses_unsafe_results_with_exit_1_and_sends_nothing(robot, model, tmp_path, capsys, mutate, message):
    res = good_result(robot, model)
    mutate(res)
    rc, err = _stream(tmp_path, res, capsys)
    assert rc == 1 and len(err) == 1 and message in err[0] and err[0].startswith("crtraj: error: ")
    assert not (tmp_path / "f.bin").exists() and not (tmp_path / "l.jsonl").exists()


def test_cli_refuses_a_result_for_another_robot(robot, model, tmp_path, capsys):
    text = (Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml").read_text()
    distal = "[[robot.segment]]\nlength = 200.0\n"
    assert text.count(distal) == 1
    other = tmp_path / "other.toml"  # the same file with the distal segment 50 mm longer
    other.write_text(text.replace(distal, "[[robot.segment]]\nlength = 250.0\n"))
    rc, err = _stream(tmp_path, good_result(robot, model), capsys, "--robot", str(other))
    assert (
        rc == 1
        and len(err) == 1
        and "robot: made for robot" in err[0]
        and "(segment[1].length 200), the device is robot 'cdsr2' (segment[1].length 250)" in err[0]
    ), err
    assert not (tmp_path / "f.bin").exists()
    # the control: the same result streams (exit 0) with the robot it was made for
    rc, err = _stream(tmp_path, good_result(robot, model), capsys)
    assert rc == 0, err
    frames = read_stream_file((tmp_path / "f.bin").read_bytes())
    assert sum(f.kind == MOVE for f in frames) == 201  # 2 s at 100 Hz, both ends
