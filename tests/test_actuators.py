"""Actuators: the [robot.actuators] schema, cable <-> servo conversion and its errors."""

from __future__ import annotations

import copy
import json
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import read_toml
from crtraj.hardware.actuators import Actuators
from crtraj.io.problem import Problem, load_robot
from crtraj.model.robot import Robot

ROOT = Path(__file__).resolve().parent.parent


def _table(robot: Robot) -> dict:
    """The robot's table with every servo written out (Actuators.to_dict), ready to patch."""
    d = copy.deepcopy(robot.to_dict())
    d["actuators"] = Actuators.from_robot(robot).to_dict()
    return d


def test_cdsr2_actuators_match_the_robot_file(robot):
    a = Actuators.from_robot(robot)
    assert a.names == ("s1c1", "s1c2", "s1c3", "s2c1", "s2c2", "s2c3", "z")
    assert a.units == ("rad",) * 6 + ("mm",)
    np.testing.assert_array_equal(a.spool_radius, 10.0)
    np.testing.assert_array_equal(a.lower, [-2.0] * 6 + [-200.0])
    np.testing.assert_array_equal(a.upper, [2.0] * 6 + [100.0])
    np.testing.assert_array_equal(a.vmax, [5.0] * 6 + [20.0])
    np.testing.assert_array_equal(a.amax, [50.0] * 6 + [100.0])
    # the full cable stroke of every segment fits the servo range
    strokes = np.array([robot.cable_stroke(k) for k in range(robot.n_segments)])
    assert np.all(strokes / 10.0 < 2.0)


def test_command_closed_form_and_round_trip(robot):
    d = _table(robot)
    d["actuators"]["servo"]["s2c1"].update(sign=-1, zero_offset=0.25, spool_radius=8.0)
    d["actuators"]["z"].update(sign=-1, zero_offset=5.0)
    r = Robot.from_table(Table(d, "robot"))
    a = Actuators.from_robot(r)
    rng = np.random.default_rng(3)
    X = rng.uniform(-0.3, 0.3, size=(20, r.nx))
    X[:, -1] = rng.uniform(-100, 50, 20)
    Q = r.cables(X)
    V = a.command(Q)
    # independent closed form: angle = a0 + s (q - L) / r_s, stage = z0 + s z
    L = np.array([200.0] * 6)
    expect = (Q[:, :6] - L) / 10.0
    expect[:, 3] = 0.25 - (Q[:, 3] - 200.0) / 8.0
    np.testing.assert_allclose(V[:, :6], expect, atol=1e-12)
    np.testing.assert_allclose(V[:, 6], 5.0 - X[:, -1], atol=1e-12)
    np.testing.assert_allclose(a.actuation(V), Q, atol=1e-10)
    np.testing.assert_allclose(a.command(Q[0]), V[0])  # single vector


def test_to_dict_round_trips(robot):
    d = _table(robot)
    d["actuators"]["servo"]["s1c3"]["position_limits"] = [-1.5, 1.0]
    r = Robot.from_table(Table(d, "robot"))
    parsed = Actuators.from_robot(r)
    again = Actuators.from_table(Table(parsed.to_dict(), "robot.actuators"), 2)
    for name in ("spool_radius", "sign", "zero_offset", "lower", "upper", "vmax", "amax"):
        np.testing.assert_array_equal(getattr(again, name), getattr(parsed, name))
    assert again.lower[2] == -1.5 and again.upper[2] == 1.0
    assert Robot.from_table(Table(r.to_dict(), "robot")).to_dict() == r.to_dict()


def _servo_defaults() -> dict:
    return {
        "spool_radius": 10.0,
        "position_limits": [-2.0, 2.0],
        "velocity_limit": 5.0,
        "acceleration_limit": 50.0,
        "z": {"position_limits": [0.0, 0.0], "velocity_limit": 1.0, "acceleration_limit": 1.0},
    }


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        ({"servo": {"s3c1": {"sign": -1}}}, "robot.actuators.servo.s3c1: unknown actuator (known: s1c1"),
        ({"servo": {"s1c1": {"sign": 2}}}, "robot.actuators.servo.s1c1.sign: must be 1 or -1, got 2"),
        ({"position_limits": [1.0, -1.0]}, "robot.actuators.position_limits: must be [low, high]"),
        ({"velocity_limit": float("nan")}, "robot.actuators.velocity_limit: must be finite"),
        ({"acceleration_limit": -1.0}, "robot.actuators.acceleration_limit: must be > 0"),
        ({"spool_radius": 0.0}, "robot.actuators.spool_radius: must be >= 0.001"),
        ({"velocity_limit": 1e300}, "robot.actuators.velocity_limit: must be within +-1e+06"),
        ({"torque": 1.0}, "robot.actuators.torque: unknown key"),
        ({"z": None}, "robot.actuators.z: missing"),
        ({"servo": {"s1c2": {"gear": 2}}}, "robot.actuators.servo.s1c2.gear: unknown key"),
    ],
)
def test_bad_actuator_tables_give_one_line_errors(patch, message):
    d = _servo_defaults()
    for k, v in patch.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    with pytest.raises(InputError) as exc:
        Actuators.from_table(Table(d, "robot.actuators"), 1)
    assert message in str(exc.value)
    assert "\n" not in str(exc.value)


def test_missing_limit_names_the_key():
    d = _servo_defaults()
    d.pop("velocity_limit")
    with pytest.raises(InputError, match=r"robot\.actuators\.servo\.s1c1\.velocity_limit: missing"):
        Actuators.from_table(Table(d, "robot.actuators"), 1)
    d["servo"] = {n: {"velocity_limit": 3.0} for n in ("s1c1", "s1c2", "s1c3")}
    a = Actuators.from_table(Table(d, "robot.actuators"), 1)
    np.testing.assert_array_equal(a.vmax, [3.0, 3.0, 3.0, 1.0])


def test_conversion_errors(robot):
    a = Actuators.from_table(Table(robot.actuators, "robot.actuators"), robot.n_segments)
    with pytest.raises(InputError, match="not bound to a robot"):
        a.command(np.zeros(7))
    b = a.for_robot(robot)
    with pytest.raises(InputError, match=r"q: expected shape \(N, 7\)"):
        b.command(np.zeros(6))
    q = robot.cables(robot.straight())
    q[2] = np.nan
    with pytest.raises(InputError, match="q: contains NaN"):
        b.command(q)
    with pytest.raises(InputError, match="'s9c9': unknown"):
        b.index("s9c9")
    one = Actuators.from_table(Table(_servo_defaults(), "robot.actuators"), 1)
    with pytest.raises(InputError, match="written for 1 segments"):
        one.for_robot(robot)


def test_robot_keeps_the_raw_table_read_only(robot):
    # the model layer holds the table as written, never parsed, and nobody can change it under the streamer
    raw = robot.actuators
    assert isinstance(raw, Mapping) and set(raw) == {
        "spool_radius",
        "zero_offset",
        "sign",
        "position_limits",
        "velocity_limit",
        "acceleration_limit",
        "ticks_per_rev",
        "model",
        "max_tension",
        "servo",
        "z",
    }
    with pytest.raises(TypeError):
        raw["sign"] = -1  # type: ignore[index]
    with pytest.raises(TypeError):
        raw["z"]["sign"] = -1  # type: ignore[index]
    assert raw["position_limits"] == (-2.0, 2.0)
    # written back as plain data (JSON-able) that parses to the same actuators
    d = robot.to_dict()
    assert json.loads(json.dumps(d)) == d
    again = Robot.from_table(Table(d, "robot"))
    for name in ("spool_radius", "sign", "zero_offset", "lower", "upper", "vmax", "amax", "rest"):
        np.testing.assert_array_equal(
            getattr(Actuators.from_robot(again), name), getattr(Actuators.from_robot(robot), name)
        )
    with pytest.raises(InputError, match=r"robot\.actuators: expected a table, got list"):
        replace(robot, actuators=[1, 2])
    with pytest.raises(InputError, match=r"robot\.actuators: missing"):
        Actuators.from_robot(replace(robot, actuators=None))


def test_a_bad_actuator_key_fails_at_load_time(tmp_path):
    # io.problem parses the table when the file is loaded: one line naming the key, before any planning
    text = (ROOT / "problems" / "robots" / "cdsr2.toml").read_text() + "\n[robot.actuators.servo.s3c1]\nsign = -1\n"
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(InputError) as exc:
        load_robot(bad)
    assert str(exc.value).startswith("robot.actuators.servo.s3c1: unknown actuator (known: s1c1")
    assert "\n" not in str(exc.value)
    inline = {"robot": read_toml(bad)["robot"], "task": {"start": [0, 0, 400], "goal": [0, 0, 390]}}
    with pytest.raises(InputError, match=r"^robot\.actuators\.servo\.s3c1: unknown actuator"):
        Problem.from_dict(inline)
    # a robot without actuators still loads (planning needs none)
    del inline["robot"]["actuators"]
    assert Problem.from_dict(inline).robot.actuators is None
