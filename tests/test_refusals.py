"""Issue 36: every non-zero exit of the command line has its reason as one line on stderr, with the code the
docs give (docs/getting-started.md, "Exit codes": 2 for bad input, ``crtraj: error: ...``; 1 for a well-formed
task that could not be done or a motion/device refusal), never a traceback; and the messages reviewers found
misleading name the right values, the file and the fix.

The refusal paths were enumerated from the raise sites of `InputError`, `AdmissionError` and `TransportError`
and the ``file=sys.stderr`` lines in crtraj/app and crtraj/cli; `test_every_refusing_use_case_is_exercised`
keeps the table below in step with them. Each case runs `crtraj.cli.main` in this process (capsys), so the
whole file runs in seconds; the few that need a rod solve, a plan or a simulated bus say so."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import PROBLEMS, require_module

from crtraj import cli
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.hardware.dynamixel import HomingState
from crtraj.hardware.ros import RosOptions
from crtraj.io.problem import load_robot
from crtraj.io.results import read_result

ROOT = PROBLEMS.parent
ROBOTS = PROBLEMS / "robots"
CDSR2, CDSR3 = ROBOTS / "cdsr2.toml", ROBOTS / "cdsr3.toml"
STATIC, DYNAMIC = PROBLEMS / "paper_static.toml", PROBLEMS / "paper_dynamic.toml"


def refused(capsys, argv: list[str], code: int, needle: str) -> str:
    """Run the CLI in-process: exit `code`, exactly one stderr line, in the form the docs give for that code,
    containing `needle`, and no traceback anywhere. Returns the line."""
    capsys.readouterr()
    try:
        rc = cli.main(argv)
    except SystemExit as exc:  # argparse's own exits (its errors go through `_Parser.error`)
        rc = exc.code
    got = capsys.readouterr()
    assert rc == code, (rc, got.err, got.out[-2000:])
    assert got.err.endswith("\n") and got.err.count("\n") == 1, got.err
    assert "Traceback" not in got.err + got.out
    line = got.err.rstrip("\n")
    if code == 2:  # bad input: the documented form
        assert line.startswith("crtraj: error: "), line
    else:  # a refused motion or device (`crtraj: error:`) or a task that could not be done (`<cmd> failed:`)
        assert re.match(r"crtraj: (error: |[a-z -]+ failed: )", line), line
    assert needle in line, line
    return line


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Inputs the cases share: sim 1's plan (`crtraj plan`, about 2 s), a copy for another robot, a failed
    result, a robot file without [robot.actuators], and an output folder."""
    d = tmp_path_factory.mktemp("refusals")
    plan = d / "plan.json"
    assert cli.main(["plan", str(STATIC), "--seed", "1", "--out", str(plan)]) == 0
    doc = json.loads(plan.read_text())
    other = json.loads(json.dumps(doc))
    other["robot"]["segment"][1]["length"] = 150.0
    (d / "other.json").write_text(json.dumps(other))
    failed = json.loads(json.dumps(doc))
    failed["success"], failed["status"] = False, "timeout"
    (d / "failed.json").write_text(json.dumps(failed))
    bare = "".join(CDSR3.read_text().partition("[robot.actuators]")[0])  # segments only
    (d / "bare.toml").write_text(bare)
    return {"plan": plan, "other": d / "other.json", "failed": d / "failed.json", "bare": d / "bare.toml", "dir": d}


# (case id, argv with {plan} {other} {failed} {bare} {dir} format fields, exit code, needle). Cheap: no solve.
CASES = [
    # the parser (every command): exit 2, one line with the command's --help
    ("no-such-command", ["fly"], 2, "invalid choice: 'fly'"),
    ("missing-positional", ["plan"], 2, "the following arguments are required: problem"),
    ("unknown-flag", ["plan", str(STATIC), "--fast"], 2, "unrecognized arguments: --fast"),
    ("bad-number", ["plan", str(STATIC), "--seed", "x"], 2, "--seed"),
    ("v-and-q-either-side", ["-v", "plan", "-q", str(STATIC)], 2, "-q: not allowed with argument -v"),
    # plan
    ("plan-no-file", ["plan", "{dir}/none.toml"], 2, "none.toml: no such file"),
    ("plan-seed", ["plan", str(STATIC), "--seed", "-1"], 2, "--seed: must be >= 0"),
    ("plan-time-limit", ["plan", str(STATIC), "--time-limit", "0"], 2, "--time-limit: must be a number > 0"),
    ("plan-html-is-out", ["plan", str(STATIC), "--out", "{dir}/a.json", "--html", "{dir}/a.json"], 2, "--html:"),
    # replan
    ("replan-seed", ["replan", str(DYNAMIC), "--seed", "-1"], 2, "--seed: must be >= 0"),
    ("replan-tip-feedback", ["replan", str(DYNAMIC), "--tip-feedback"], 2, "--tip-feedback: needs a tip"),
    (
        "replan-plant-live",
        ["replan", str(DYNAMIC), "--plant", "cosserat", "--feed", "udp://127.0.0.1:1"],
        2,
        "--plant:",
    ),
    (
        "replan-true-live",
        ["replan", str(DYNAMIC), "--true-robot", str(CDSR2), "--feed", "udp://127.0.0.1:1"],
        2,
        "--true-robot: a simulation",
    ),
    ("replan-mocap", ["replan", str(DYNAMIC), "--mocap-port", "9"], 2, "--mocap-port: a live run only"),
    ("replan-feed-host", ["replan", str(DYNAMIC), "--out", "{dir}/r", "--feed", "udp://10.0.0.1:5"], 2, "--feed:"),
    ("replan-plant-name", ["replan", str(DYNAMIC), "--out", "{dir}/r", "--plant", "rubber"], 2, "unknown plant"),
    (
        "replan-true-robot",
        ["replan", str(DYNAMIC), "--out", "{dir}/r", "--true-robot", str(CDSR3)],
        2,
        "--true-robot: robot 'cdsr3' has 3 segments, the problem's robot has 2",
    ),
    # export, build
    ("export-batch", ["export", "--batch", "0", "--out", "{dir}/x"], 2, "--batch: must be in [1,"),
    ("export-points", ["export", "--points", "1", "--out", "{dir}/x"], 2, "--points: must be in [2,"),
    ("build-points", ["build", "--check-points", "1"], 2, "--check-points: must be in [2,"),
    # view
    ("view-no-file", ["view", "{dir}/none.json", "--html", "{dir}/v.html"], 2, "none.json: no such file"),
    ("view-fps", ["view", "{plan}", "--mp4", "{dir}/v.mp4", "--fps", "0"], 2, "--fps: expected 0.5 to 60"),
    ("view-compare-served", ["view", "{plan}", "{plan}", "--no-browser"], 2, "COMPARE: a comparison is written"),
    (
        "view-compare-robot",
        ["view", "{plan}", "{other}", "--html", "{dir}/v.html"],
        2,
        "'cdsr2' (segment[1].length 150), but the result shown",
    ),
    # stream: bad input 2, a refused motion 1, a device that fails 1
    ("stream-no-file", ["stream", "{dir}/none.json", "--dry-run", "{dir}/f.bin"], 2, "none.json: no such file"),
    ("stream-time-scale", ["stream", "{plan}", "--dry-run", "{dir}/f.bin", "--time-scale", "0"], 2, "--time-scale"),
    (
        "stream-approach-dry",
        ["stream", "{plan}", "--dry-run", "{dir}/f.bin", "--approach", "--log", "{dir}/l.jsonl"],
        2,
        "--approach: this link reports no device position",
    ),
    (
        "stream-failed",
        ["stream", "{failed}", "--dry-run", "{dir}/f.bin", "--log", "{dir}/l.jsonl"],
        1,
        "success: false (status timeout)",
    ),
    (
        "stream-other-robot",
        ["stream", "{other}", "--robot", str(CDSR2), "--dry-run", "{dir}/f.bin"],
        1,
        "robot: made for robot",
    ),
    (
        "stream-no-device",
        ["stream", "{plan}", "--udp", "127.0.0.1:9", "--log", "{dir}/u.jsonl"],
        1,
        "crtraj: stream failed: error: transport error: udp://127.0.0.1:9",
    ),
    # verify (no rod solve: refused before)
    ("verify-model", ["verify", "{plan}"], 2, "--model"),
    (
        "verify-substeps",
        ["verify", "{plan}", "--model", "cosserat", "--robot", str(CDSR2), "--substeps", "0"],
        2,
        "--substeps: must be in [1,",
    ),
    (
        "verify-robot",
        ["verify", "{plan}", "--model", "cosserat", "--robot", str(CDSR3)],
        2,
        "was made for robot 'cdsr2' (segments 2), but --robot",
    ),
    # model compare
    ("compare-samples", ["model", "compare", str(CDSR2), "--samples", "0"], 2, "--samples: must be in [1,"),
    ("compare-seed", ["model", "compare", str(CDSR2), "--seed", "-1"], 2, "--seed: must be >= 0"),
    # the servo tools
    ("home-empty", ["home", "--dynamixel", "", "--robot", str(CDSR2)], 2, "--dynamixel"),
    ("home-no-actuators", ["home", "--dynamixel", "/dev/null", "--robot", "{bare}"], 2, "robot.actuators: missing"),
    (
        "home-no-ids",
        ["home", "--dynamixel", "/dev/null", "--robot", str(CDSR3)],
        2,
        "robot.actuators: no Dynamixel ids",
    ),
    (
        "sim-device-no-actuators",
        ["sim-device", "--udp", "127.0.0.1:0", "--robot", "{bare}"],
        2,
        "robot.actuators: missing",
    ),
    ("sim-dynamixel-fault", ["sim-dynamixel", "--pty", "--hardware-error", "3:melted"], 2, "--hardware-error:"),
    ("sim-dynamixel-missing", ["sim-dynamixel", "--pty", "--missing", "99"], 2, "--missing: 99 is not one of"),
    ("sim-dynamixel-no-ids", ["sim-dynamixel", "--pty", "--robot", str(CDSR3)], 2, "no Dynamixel ids"),
    ("feed-replay-host", ["feed-replay", str(DYNAMIC), "--udp", "10.0.0.1:5"], 2, "--udp: the replay sends"),
    ("feed-replay-port", ["feed-replay", str(DYNAMIC), "--udp", "127.0.0.1:0"], 2, "--udp: port must be"),
    # bench, record, calibrate, ros-bridge
    ("bench-workers", ["bench", "table1", "--workers", "-1", "--out", "{dir}/b"], 2, "--workers: must be >= 0"),
    ("bench-counts", ["bench", "table1", "--counts", "a", "--out", "{dir}/b"], 2, "--counts:"),
    ("bench-modes", ["bench", "modes", "--out", "{dir}/b"], 2, "--runs: give the runs.csv"),
    ("bench-suite-dask", ["bench", "suite", "--dask", "tcp://127.0.0.1:1", "--out", "{dir}/b"], 2, "table1 only"),
    ("record-nothing", ["record", "--out", "{dir}/d.json"], 2, "record: give --log and --markers"),
    (
        "record-plant-udp",
        ["record", "--out", "{dir}/d.json", "--excite", "--plant", "cosserat", "--udp", "127.0.0.1:9"],
        2,
        "--plant: a simulated capture",
    ),
    ("record-excite-where", ["record", "--out", "{dir}/d.json", "--excite"], 2, "--excite: give exactly one"),
    ("calibrate-log-only", ["calibrate", "--log", "{dir}/l.jsonl", "--out", "{dir}/c.toml"], 2, "--log: needs"),
    ("ros-bridge-seed", ["ros-bridge", str(DYNAMIC), "--seed", "-1"], 2, "--seed: must be >= 0"),
]


@pytest.mark.parametrize(("argv", "code", "needle"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_every_refusal_is_one_line_with_the_documented_code(argv, code, needle, files, capsys, monkeypatch):
    monkeypatch.chdir(files["dir"])  # default outputs (out/...) land in the test's folder
    argv = [a.format(**{k: str(v) for k, v in files.items()}) for a in argv]
    refused(capsys, argv, code, needle)


def test_every_refusing_use_case_is_exercised():
    """Each module of crtraj/app that refuses (raises a user-facing error or prints a failure line) backs a
    command that the table above runs at least once: a new refusing command needs a case here."""
    covered = {c[1][0] if c[1][0] != "model" else "model-compare" for c in CASES}
    modules = {cli._USE_CASES[c].split(":")[0].rsplit(".", 1)[1] for c in covered if c in cli._USE_CASES}
    refusing = {
        p.stem
        for p in (ROOT / "crtraj" / "app").glob("*.py")
        if re.search(r"raise (InputError|AdmissionError|TransportError)|file=sys\.stderr", p.read_text())
    }
    # helpers of a command, refusing on its behalf (their command's cases reach them)
    helpers = {"approach": "stream", "plant_sim": "replan", "record_plant": "record", "suite": "bench"}
    # library calls with no command of their own: tests/test_public_api.py runs their refusals
    library = {"calibrate_file", "plan_motion"}
    api_tests = (ROOT / "tests" / "test_public_api.py").read_text()
    assert all(f"def test_{n}" in api_tests for n in ("admit_plan_refuses", "calibrate_robot_refuses_bad")), "moved?"
    missing = {m for m in refusing - modules - library if helpers.get(m) not in modules}
    assert not missing, f"no refusal case runs crtraj/app/{sorted(missing)}"


# ------------------------------------------------------- exits that said nothing on stderr


def test_a_failed_stream_says_why_on_stderr_not_only_stdout(files, capsys):
    """Reviewers: a stream that stops (device gone) printed its status on stdout only and exited 1. Now the
    status and message are also the one stderr line, with the run's log."""
    log = files["dir"] / "gone.jsonl"
    line = refused(capsys, ["stream", str(files["plan"]), "--udp", "127.0.0.1:9", "--log", str(log)], 1, "")
    assert line.startswith("crtraj: stream failed: error: ") and line.endswith(f"(log {log})"), line
    report = next(r for r in map(json.loads, log.read_text().splitlines()) if r["type"] == "report")
    assert report["status"] in line and report["message"] in line  # the log's own verdict, not another


@pytest.fixture(scope="module")
def dynamixel_sdk():
    """The Dynamixel SDK, asked for before `files` (a plan): without it the test fails (skips locally) at once."""
    return require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")


def test_stream_dynamixel_power_cycled_mid_stream_says_why(dynamixel_sdk, files, tmp_path, capsys, monkeypatch):
    """`crtraj stream --dynamixel` whose servos power-cycle mid-stream (torque off, positions relative):
    exit 1 with one stderr line naming what the stream met, the servos' status as the simulator had it."""
    from dxl_helpers import Clock, homed_state, in_process

    from crtraj.hardware.actuators import Actuators
    from crtraj.hardware.dynamixel import ServoChain, state_path

    robot_file = tmp_path / "robot.toml"
    robot_file.write_text(CDSR2.read_text())
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    plan = files["plan"]
    q0 = np.asarray(json.loads(plan.read_text())["waypoints"][0]["q"], dtype=float)
    clock = Clock()
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(acts.command(q0)))
    homed_state(chain, acts, clock.now()).save(state_path(robot_file))
    handle, cycled = chain.handle, []

    def handle_with_power_cut(packet, now):  # as `SimDynamixel(power_cycle_at=2.0)` does it, on the bus clock
        if not cycled and now >= 2.0:
            cycled.append(now)
            chain.power_cycle(now)
        return handle(packet, now)

    chain.handle = handle_with_power_cut
    dev = in_process(monkeypatch, chain, clock).path
    capsys.readouterr()
    log = tmp_path / "s.jsonl"
    line = refused(
        capsys,
        ["stream", str(plan), "--dynamixel", dev, "--robot", str(robot_file), "--log", str(log)],
        1,
        "crtraj: stream failed: ",
    )
    assert cycled, "the power cut never came: the stream ended first"
    report = next(r for r in map(json.loads, log.read_text().splitlines()) if r["type"] == "report")
    assert report["status"] != "done" and f"{report['status']}: {report['message']}"[:80] in line, (report, line)


def test_verify_contact_says_why_on_stderr(tmp_path, capsys):
    """`crtraj verify --model cosserat` reporting CONTACT exited 1 with the verdict on stdout only; now one
    stderr line says CONTACT, where, and the fix (the extra safety distance the result needs)."""
    from test_verify_cosserat import _document, _scene, _sideways

    from crtraj.model.cosserat import CosseratRod, RodLoad
    from crtraj.model.kinematics import Model

    robot = load_robot(CDSR2)
    side = _sideways(robot)
    x = robot.straight(robot.z_range[0])
    sagged = CosseratRod(side).solve(np.ones(6), RodLoad())  # the straight pose's 1 N pretension
    tip = sagged.tip + np.array([0.0, 0.0, x[-1]])
    assert np.linalg.norm(tip - Model(robot).tip_position(x)) > 30.0  # the rod sags where PCC does not
    doc = _document(side, _scene([{"center": (tip - [4.0, 0.0, 0.0]).tolist(), "radius": 3.0}]), [0.0, 1.0], [x, x])
    res = tmp_path / "side.json"
    res.write_text(json.dumps(doc))
    robot_file = tmp_path / "side.toml"
    text = CDSR2.read_text().replace("gravity = [0.0, 0.0, -9.80665]", "gravity = [-9.80665, 0, 0]")
    robot_file.write_text(text.replace("[robot.mechanics]", '[robot.mechanics]\nactuation = "tension"'))  # as _sideways
    line = refused(
        capsys,
        ["verify", str(res), "--model", "cosserat", "--robot", str(robot_file)],
        1,
        "crtraj: verify failed: CONTACT: under the Cosserat rod the body touches an obstacle",
    )
    extra = float(re.search(r"at least ([0-9.]+) mm larger", line).group(1))
    clearance = float(re.search(r"\(([-0-9.]+) mm at t", line).group(1))
    assert extra == pytest.approx(-clearance, abs=0.01) and extra > 0, line  # the fix is the rod's shortfall


def test_model_compare_without_a_converged_solve_says_why(tmp_path, capsys):
    """`crtraj model compare` with a Young's modulus too small for any rod solve to converge exited 1 saying
    nothing on stderr; now one line names the robot file, the modulus and the keys to check."""
    soft = tmp_path / "soft.toml"
    # tension control: the rod is solved under the tensions (under cable lengths, the next test refuses sooner)
    text = re.sub(r"(?m)^youngs_modulus = .*$", 'youngs_modulus = 1e-6\nactuation = "tension"', CDSR2.read_text())
    soft.write_text(re.sub(r"(?m)^steps = .*$", "steps = 4\nmax_iter = 5", text))  # fails as surely, sooner
    line = refused(capsys, ["model", "compare", str(soft), "--samples", "2"], 1, "crtraj: model compare failed:")
    assert f"[robot.mechanics] in {soft}: youngs_modulus 1e-06 MPa" in line and "2 configurations" in line, line


def test_model_compare_of_a_rod_too_soft_for_its_cable_lengths_names_the_modulus(tmp_path, capsys):
    """Under cable-length control the commanded lengths allow for the wire's shortening under tension: a
    modulus so small that a segment would shorten below zero length is the robot file's fault, said as such
    (it was "q: gives a tendon length <= 0 mm", naming a pose the user never gave)."""
    soft = tmp_path / "soft.toml"
    soft.write_text(re.sub(r"(?m)^youngs_modulus = .*$", "youngs_modulus = 1e-6", CDSR2.read_text()))
    line = refused(capsys, ["model", "compare", str(soft), "--samples", "2"], 2, "crtraj: error: ")
    assert "robot.mechanics.youngs_modulus: 1e-06 MPa is too soft" in line, line


# ------------------------------------------------------------------ rewritten messages


def test_another_robots_result_names_each_robots_own_value_and_the_fix(files):
    """Was: "the result was made for robot 'cdsr3' (3 segments, ...), but this Visualizer draws 'cdsr2' (3
    segments, not 2)": the count after cdsr2 was cdsr3's. Now each robot's name is followed by its own value."""
    res = read_result(json.loads(files["plan"].read_text()))
    three = load_robot(CDSR3)
    with pytest.raises(InputError) as e:
        res.check_robot(three, "--robot cdsr3.toml", "give --robot the robot file the result was planned with")
    assert str(e.value) == (
        "robot: the result was made for robot 'cdsr2' (segments 2), but --robot cdsr3.toml is robot 'cdsr3' "
        "(segments 3); give --robot the robot file the result was planned with"
    )
    other = read_result(files["other"])
    with pytest.raises(InputError) as e:
        other.check_robot(load_robot(CDSR2), "x", "y")
    length = load_robot(CDSR2).segments[1].length
    assert f"'cdsr2' (segment[1].length 150), but x is robot 'cdsr2' (segment[1].length {length:g}); y" in str(e.value)
    assert str(e.value).startswith(f"robot: {files['other']} was made for")  # the file to change


def test_true_robot_of_another_segment_count_speaks_of_segments(files, capsys):
    """Was: "--true-robot: 10 actuators, the loop's robot has 7". Now segments, and what to give instead."""
    line = refused(
        capsys, ["replan", str(DYNAMIC), "--out", str(files["dir"] / "t"), "--true-robot", str(CDSR3)], 2, ""
    )
    assert line == (
        "crtraj: error: --true-robot: robot 'cdsr3' has 3 segments, the problem's robot has 2: give a copy of the "
        "problem's robot file with only its parameters changed"
    )
    from crtraj.hardware.actuators import Actuators
    from crtraj.hardware.mocap import check_true_robot

    two = load_robot(CDSR2)  # the same segments with other parameters (here none): accepted
    check_true_robot(two, Actuators.from_robot(two), Actuators.from_robot(two))
    with pytest.raises(InputError, match="robot 'cdsr3' has 3 segments, the problem's robot has 2"):
        three = load_robot(CDSR3)  # the --plant path (crtraj.app.plant_sim) asks the same question
        check_true_robot(three, Actuators.from_robot(three), Actuators.from_robot(two))


def test_two_actuators_on_one_joint_are_both_named():
    """Was: "ros.joints: two actuators map to the same joint name"; now the actuators and the joint."""
    t = Table({"joints": {"s1c1": "joint_a", "s1c2": "joint_b", "z": "joint_a"}}, "ros")
    with pytest.raises(InputError) as e:
        RosOptions.from_table(t)
    assert str(e.value) == ("ros.joints: s1c1 and z both map to joint 'joint_a'; give each actuator its own joint name")
    RosOptions.from_table(Table({"joints": {"s1c1": "joint_a", "z": "joint_z"}}, "ros"))  # distinct: accepted


@pytest.mark.parametrize(
    ("argv", "level"),
    [(["plan", "-v"], 20), (["plan", "-vv"], 10), (["plan", "-q"], 40), (["-v", "plan"], 20), (["plan"], 30)],
)
def test_global_flags_work_after_the_command_too(argv, level, files, capsys):
    """Was: `crtraj plan -v` -> "unrecognized arguments: -v". -v/-q now stand on either side of the command."""
    import logging

    log = logging.getLogger("crtraj")
    before = log.level
    try:
        refused(capsys, [*argv, str(files["dir"] / "none.toml")], 2, "none.toml: no such file")
        assert log.level == level
        # a nested command's parser (model compare) takes them as well
        refused(capsys, ["model", "compare", "-q", str(files["dir"] / "none.toml")], 2, "none.toml: no such file")
        assert log.level == logging.ERROR
    finally:
        log.setLevel(before)  # later tests see the level they would have seen


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"\xff\xfe{\x00}\x00", "not UTF-8 text (it looks like UTF-16)"),
        (b"\x00\x9c garbage", "not UTF-8 text (byte 1 is 0x9c)"),
        (b'{"servos": [', "JSON"),
    ],
    ids=["utf16", "binary", "truncated"],
)
def test_a_damaged_homing_state_says_home_again_not_save_as_utf8(data, why, tmp_path):
    """Was: "save it as UTF-8" for crtraj's own robot.homing.json: the fix is to delete it and home again."""
    p = tmp_path / "robot.homing.json"
    p.write_bytes(data)
    with pytest.raises(InputError) as e:
        HomingState.load(p)
    text = str(e.value)
    assert text.startswith(f"{p}: damaged homing state file (") and why in text, text
    assert text.endswith("; delete it and run crtraj home again") and "save it" not in text, text


def test_the_time_based_drive_mode_refusal_is_short_and_says_remove_the_key(tmp_path):
    """Was 395 characters without saying what to do; now under 200, naming the key and saying to remove it."""
    text = CDSR2.read_text().replace("lead = 20.0", "drive_mode = { time_based_profile = true }\nlead = 20.0")
    p = tmp_path / "robot.toml"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        load_robot(p)
    msg = str(e.value)
    assert msg.startswith("robot.actuators.z.drive_mode.time_based_profile: crtraj does not support the time-based")
    assert msg.endswith(": remove this key from the robot file") and len(msg) < 200, (len(msg), msg)


# ------------------------------------------------------------------ the docs' exit codes


def test_documented_exit_codes_are_the_codes_main_returns(files, capsys):
    """docs/getting-started.md's table and the README give 0, 1 and 2 (130 for Ctrl-C); the Dynamixel
    tutorial gives exit 2 for `robot.actuators: ...` and `not homed ...` and 1 for the device's refusals."""
    table = (ROOT / "docs" / "getting-started.md").read_text().partition("## Exit codes")[2].partition("\n## ")[0]
    assert {int(c) for c in re.findall(r"(?m)^\| (\d+) \|", table)} == {0, 1, 2, 130, 143}
    readme = (ROOT / "README.md").read_text()
    assert "1: a well-formed task that could not be done" in readme and "2: bad input" in readme
    tutorial = (ROOT / "docs" / "tutorials" / "dynamixel.md").read_text()
    assert "exit 1, or 2 where the row says so" in tutorial
    for row in ("robot.actuators: no Dynamixel ids", "not homed since its last power-up"):
        assert re.search(re.escape(row) + r"[^\n]*\| exit 2:", tutorial), row
    refused(capsys, ["home", "--dynamixel", "/dev/null", "--robot", str(CDSR3)], 2, "robot.actuators: no Dynamixel")
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    dev = str(files["dir"] / "ttyUSB-none")
    argv = ["stream", str(files["plan"]), "--dynamixel", dev, "--robot", str(CDSR2), "--log", str(files["dir"] / "d")]
    refused(capsys, argv, 1, f"{dev}: no such port")


def test_a_bench_whose_worker_died_says_why_even_with_q(tmp_path, capsys, monkeypatch):
    """`crtraj bench table1` whose worker process dies exits 1; its reason was a logger warning, which -q
    silenced (exit 1, nothing on stderr). Now it is the failure line, -q or not; the finished runs are kept."""
    import concurrent.futures as cf

    from crtraj.bench.runner import Table1Bench

    def die(self, tasks, executor):  # what `_execute` raises when the pool loses a process
        raise cf.BrokenExecutor("A process in the process pool was terminated abruptly")
        yield  # a generator, as `_execute` is

    monkeypatch.setattr(Table1Bench, "_execute", die)
    argv = ["bench", "table1", "--workers", "0", "--scenarios", "1", "--counts", "1", "--planners", "rrt"]
    argv += ["--no-progress", "--out", str(tmp_path / "b")]
    for quiet in ([], ["-q"]):
        line = refused(capsys, [*quiet, *argv], 1, "crtraj: bench failed: a worker died (BrokenExecutor: ")
        assert line.endswith("the files hold the 0 runs that finished"), line
