"""Robot and problem files: valid ones load, bad ones give one clear line naming the field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from crtraj.cli import main
from crtraj.errors import InputError
from crtraj.fields import Table
from crtraj.problem import Problem, load_robot
from crtraj.robot import Robot

GOOD = """
[robot]
name = "r"
cable_radius = 2.5
z_range = [-150.0, 100.0]
coupling = 0.0
[[robot.segment]]
length = 200.0
[[robot.segment]]
length = 180.0
theta_max = 2.0
"""


def write(tmp_path, text, name="robot.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_good_file_loads_with_defaults(tmp_path):
    r = load_robot(write(tmp_path, GOOD))
    assert r.n_segments == 2 and r.nx == 5 and r.nq == 7
    assert r.segments[0].theta_max == pytest.approx(math.pi)
    assert r.segments[1].theta_max == 2.0
    assert r.cable_stroke(1) == pytest.approx(2 * 2.5 * 2.0)
    assert r.body_radius == 3.0 and r.collision_points == 10


def test_to_dict_round_trips(robot):
    again = Robot.from_table(Table(robot.to_dict(), "robot"))
    assert again == robot


def test_default_robot_reaches_paper_sim1_points(robot):
    # the reason for the default's z stroke: the sim-1 goal needs the base retracted
    assert robot.z_range[0] <= -150.0
    assert robot.coupling == -1.0


BAD = [
    (GOOD.replace("coupling = 0.0", "coupling = 0.0\ncoupling_gain = 1"), "robot.coupling_gain: unknown key"),
    (
        GOOD.replace("[[robot.segment]]\nlength = 200.0\n[[robot.segment]]\nlength = 180.0\ntheta_max = 2.0\n", ""),
        "robot.segment: missing",
    ),
    (GOOD.replace("length = 200.0", "length = -3"), "robot.segment[0].length: must be >= 0.001"),
    (GOOD.replace("cable_radius = 2.5", "cable_radius = 0"), "robot.cable_radius: must be >= 0.001"),
    (GOOD.replace("cable_radius = 2.5", "cable_radius = 1e-300"), "robot.cable_radius: must be >= 0.001"),
    (GOOD.replace("length = 200.0", "length = 1e308"), "robot.segment[0].length: must be within +-1e+06"),
    (GOOD.replace("coupling = 0.0", "coupling = 1e300"), "robot.coupling: must be within +-10"),
    (
        GOOD.replace("coupling = 0.0", "coupling = 0.0\ncollision_points = 100000"),
        "robot.collision_points: must be <= 200",
    ),
    (
        GOOD.replace("coupling = 0.0", "coupling = 0.0\ncollision_points = 99999999999999999999999"),
        "robot.collision_points: must be <= 200, got 99999999999999999999999",
    ),
    (GOOD + "[[robot.segment]]\nlength = 1.0\n" * 16, "robot.segment: at most 16 entries, got 18"),
    (GOOD.replace('name = "r"', 'name = "../../x"'), "robot.name: '../../x' cannot be part of a file name"),
    (GOOD.replace("z_range = [-150.0, 100.0]", "z_range = [-1e300, 100.0]"), "robot.z_range[0]: must be within"),
    (GOOD.replace("z_range = [-150.0, 100.0]", "z_range = [100.0, -150.0]"), "robot.z_range: must be [low, high]"),
    (GOOD.replace("z_range = [-150.0, 100.0]", "z_range = [1.0]"), "robot.z_range: expected 2 numbers"),
    (GOOD.replace("theta_max = 2.0", 'theta_max = "big"'), "robot.segment[1].theta_max: expected a number"),
    (GOOD.replace("theta_max = 2.0", "theta_max = nan"), "robot.segment[1].theta_max: must be finite"),
    (GOOD.replace("theta_max = 2.0", "thetamax = 2.0"), "robot.segment[1].thetamax: unknown key"),
    (GOOD.replace('name = "r"', ""), "robot.name: missing"),
    ("[robot\nname=1", "not valid TOML"),
    ("[robots]\nname='x'", "robots: unknown key"),
]


@pytest.mark.parametrize("text,msg", BAD)
def test_bad_robot_file_one_clear_line(tmp_path, capsys, text, msg):
    path = write(tmp_path, text)
    with pytest.raises(InputError) as exc:
        load_robot(path)
    assert msg in str(exc.value)
    assert "\n" not in str(exc.value)
    out = tmp_path / "out"
    assert main(["export", "--robot", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("crtraj: error:") and msg in err[0]
    assert not out.exists()


def test_missing_file(tmp_path, capsys):
    assert main(["export", "--robot", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "nope.toml: no such file" in capsys.readouterr().err


def test_bad_export_does_not_clobber_previous(tmp_path):
    out = tmp_path / "out"
    assert main(["export", "--out", str(out), "--no-compile"]) == 0
    before = (out / "manifest.json").read_bytes()
    bad = write(tmp_path, GOOD.replace("length = 200.0", "length = -1"))
    assert main(["export", "--robot", str(bad), "--out", str(out)]) == 2
    assert (out / "manifest.json").read_bytes() == before


def test_problem_file_robot_reference_and_task(tmp_path):
    write(tmp_path, GOOD, "r.toml")
    p = write(tmp_path, 'robot = "r.toml"\nseed = 4\n[task]\nstart = [0, 0, 380]\ngoal = [10, 20, 300]\n', "p.toml")
    prob = Problem.load(p)
    assert prob.robot.name == "r" and prob.seed == 4
    np.testing.assert_array_equal(prob.task.goal, [10, 20, 300])
    bad = write(tmp_path, 'robot = "r.toml"\n[tsak]\nstart = [0, 0, 1]\n', "bad.toml")
    with pytest.raises(InputError, match="tsak: unknown section"):
        Problem.load(bad)
    bad2 = write(tmp_path, 'robot = "r.toml"\n[task]\nstart = [0, 0]\ngoal = [1, 2, 3]\n', "bad2.toml")
    with pytest.raises(InputError, match=r"task.start: expected 3 numbers"):
        Problem.load(bad2)
