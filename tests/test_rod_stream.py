"""`crtraj stream` of a plan made for the rod's body (``--model rod``): its commanded cable lengths hold the rod
where it was planned only under the mechanics it was planned with, so a robot file whose [robot.mechanics] differs
(any value, the actuation mode, or none at all) is refused in one line with exit code 1 before anything is sent;
the same robot file streams it, and a PCC plan streams whatever the mechanics (`crtraj.planning.body.body_mismatch`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj import cli
from crtraj.io.problem import load_robot
from crtraj.model.mechanics import Mechanics
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
ROBOT_FILE = ROOT / "problems" / "robots" / "cdsr1_side.toml"


def _result(tmp_path: Path, body: dict | None) -> Path:
    """A small plan result of cdsr1_side over 2 s (within its limits), recording `body` as the plan's body."""
    robot = load_robot(ROBOT_FILE)
    X = np.linspace(0.0, 1.0, 5)[:, None] * np.array([0.3, 0.1, 10.0])
    wps = [{"t": 0.5 * i, "x": X[i].tolist(), "q": robot.cables(X[i]).tolist()} for i in range(5)]
    res = {"kind": "plan", "success": True, "status": "success", "waypoints": wps}
    res["robot"] = json.loads(json.dumps(robot.to_dict(), default=float))
    res["scene"] = json.loads(json.dumps(Scene(safety_distance=5.0).to_dict(), default=float))  # no obstacles
    if body is not None:
        res["options"] = {"body": body}
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(res, default=lambda o: o.tolist()))
    return p


def _robot(tmp_path: Path, old: str, new: str) -> Path:
    """cdsr1_side.toml with `old` replaced by `new` (which must occur once)."""
    text = ROBOT_FILE.read_text()
    assert text.count(old) == 1, old
    p = tmp_path / "robot.toml"
    p.write_text(text.replace(old, new))
    return p


def _stream(capsys, tmp_path: Path, result: Path, robot: Path) -> tuple[int, str, Path]:
    frames = tmp_path / "frames.bin"
    capsys.readouterr()
    argv = ["stream", str(result), "--robot", str(robot), "--dry-run", str(frames)]
    rc = cli.main([*argv, "--log", str(tmp_path / "log.jsonl")])
    return rc, capsys.readouterr().err, frames


MECH = json.loads(json.dumps(Mechanics.from_robot(load_robot(ROBOT_FILE)).to_dict()))
ROD = {"kind": "rod", "surrogate": "0123456789abcdef01234567", "actuation": "cable_length", "mechanics": MECH}


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("youngs_modulus = 60000.0", "youngs_modulus = 50000.0", "robot.mechanics.youngs_modulus: the rod plan"),
        ('actuation = "cable_length"', 'actuation = "tension"', "robot.mechanics.actuation: the rod plan was made with "
                                                                "'cable_length'"),
        ("[robot.mechanics]", "[robot.other_mechanics]", "has no [robot.mechanics]"),
    ],
)  # fmt: skip
def test_a_rod_plan_is_refused_by_a_robot_file_with_other_mechanics(old, new, needle, capsys, tmp_path):
    robot = _robot(tmp_path, old, new)
    if "other_mechanics" in new:  # a robot file without the table (the rest of it removed too)
        text = robot.read_text()
        robot.write_text(text[: text.index("[robot.other_mechanics]")])
    rc, err, frames = _stream(capsys, tmp_path, _result(tmp_path, ROD), robot)
    assert rc == 1 and err.count("\n") == 1 and err.startswith("crtraj: error: "), err
    assert needle in err and "re-plan it with --model rod" in err, err
    assert not frames.exists()  # nothing sent


def test_the_same_mechanics_stream_a_rod_plan_and_a_pcc_plan_streams_with_any(capsys, tmp_path):
    rc, err, frames = _stream(capsys, tmp_path, _result(tmp_path, ROD), ROBOT_FILE)
    assert rc == 0 and frames.stat().st_size > 0, err
    other = _robot(tmp_path, "youngs_modulus = 60000.0", "youngs_modulus = 50000.0")
    for body in ({"kind": "pcc"}, None):
        frames.unlink()
        rc, err, frames = _stream(capsys, tmp_path, _result(tmp_path, body), other)
        assert rc == 0 and frames.stat().st_size > 0, err
    # a rod plan whose recorded actuation mode is not its robot's own (an edited result) is refused too
    rc, err, _ = _stream(capsys, tmp_path, _result(tmp_path, dict(ROD, actuation="tension")), ROBOT_FILE)
    assert rc == 1 and "robot.mechanics.actuation: the rod plan was made with 'tension'" in err, err
    # and one that records no mechanics (made before they were recorded) cannot be checked: refused
    rc, err, _ = _stream(capsys, tmp_path, _result(tmp_path, {k: v for k, v in ROD.items() if k != "mechanics"}),
                         ROBOT_FILE)  # fmt: skip
    assert rc == 1 and "records no mechanics" in err, err
