"""Issue 11, bad input: each case measured on main as a traceback or a hang is now one line, exit 2,
checked before any work, with nothing already written touched."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from crtraj import cli
from crtraj.control.horizon import MOVED_TO_LOOP, ReplanOptions
from crtraj.control.loop import LoopOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import Table, check_array
from crtraj.core.fileio import MAX_DEPTH, read_json, read_toml
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import MAX_SETPOINTS, SetpointPath
from crtraj.io.problem import Problem

ROOT = Path(__file__).resolve().parent.parent
STATIC = (ROOT / "problems" / "paper_static.toml").read_text()
ROBOT = (ROOT / "problems" / "robots" / "cdsr2.toml").read_text()


def _problem(tmp_path: Path, text: str, name: str = "p.toml") -> Path:
    """A problem file beside a copy of the robot file it names."""
    (tmp_path / "robots").mkdir(exist_ok=True)
    (tmp_path / "robots" / "cdsr2.toml").write_text(ROBOT)
    p = tmp_path / name
    p.write_text(text)
    return p


def _kept(tmp_path: Path) -> dict[Path, bytes]:
    """Result files that exist before a run, with known bytes."""
    files = {tmp_path / "keep" / "plan.json": b'{"kept": 1}\n', tmp_path / "keep" / "plan.html": b"<p>kept</p>\n"}
    for p, data in files.items():
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(data)
    return files


def _one_line(capsys, argv: list[str], needle: str) -> str:
    """Run the CLI in-process: exit 2, one stderr line `crtraj: error: ...` containing `needle`."""
    capsys.readouterr()
    rc = cli.main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith("crtraj: error: "), err
    assert needle in err, err
    return err


# ------------------------------------------------------------ file encodings

UTF16 = STATIC.encode("utf-16")
GARBAGE = bytes(range(256)) * 4


@pytest.mark.parametrize("data", [UTF16, GARBAGE, b"\xef\xbb\xbf" + b"\xff" * 10], ids=["utf16", "garbage", "bom"])
@pytest.mark.parametrize("command", ["plan", "replan", "export", "bench", "stream"])
def test_undecodable_toml_is_one_line_for_every_reader(command, data, tmp_path, capsys):
    f = tmp_path / "bad.toml"
    f.write_bytes(data)
    kept = _kept(tmp_path)
    argv = {
        "plan": ["plan", str(f), "--out", str(tmp_path / "keep" / "plan.json")],
        "replan": ["replan", str(f), "--out", str(tmp_path / "keep" / "run"), "--quiet"],
        "export": ["export", "--robot", str(f), "--out", str(tmp_path / "keep"), "--no-compile"],
        "bench": ["bench", "table1", "--robot", str(f), "--out", str(tmp_path / "keep"), "--workers", "0"],
        "stream": ["stream", "r.json", "--robot", str(f), "--dry-run", str(tmp_path / "keep" / "plan.json")],
    }[command]
    if command == "stream":  # a valid result, so that the robot file is what fails
        res = tmp_path / "r.json"
        res.write_text(json.dumps({"robot": read_toml(ROOT / "problems" / "robots" / "cdsr2.toml")["robot"]}))
        argv[1] = str(res)
    _one_line(capsys, argv, "bad.toml: not UTF-8 text")
    assert {p: p.read_bytes() for p in kept} == kept


def test_utf8_bom_is_accepted(tmp_path):
    p = _problem(tmp_path, "\ufeff" + STATIC)
    assert read_toml(p)["name"] == "paper_static"


# ------------------------------------------------------------------- nesting


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 900, 5000, 200_000])
def test_deep_nesting_is_one_line_at_any_depth(depth, tmp_path):
    t = tmp_path / "deep.toml"
    t.write_text("a = " + "[" * depth + "]" * depth + "\n")
    j = tmp_path / "deep.json"
    j.write_text("[" * depth + "]" * depth)
    with pytest.raises(InputError, match=r"deep\.toml: .*nested deeper than 32 levels"):
        read_toml(t)
    with pytest.raises(InputError, match=r"deep\.json: .*nested deeper than 32 levels"):
        read_json(j)


def test_nesting_up_to_the_bound_is_read(tmp_path):
    j = tmp_path / "ok.json"
    j.write_text("[" * MAX_DEPTH + "]" * MAX_DEPTH)
    v = read_json(j)
    for _ in range(MAX_DEPTH - 1):
        v = v[0]
    assert v == []


def test_oversized_and_special_files_are_refused_before_reading(tmp_path):
    big = tmp_path / "big.toml"
    with big.open("wb") as fh:  # sparse: 5 MiB without writing them
        fh.truncate(5 * 1024 * 1024)
    with pytest.raises(InputError, match=r"big\.toml: 5242880 bytes, larger than the 4194304 bytes"):
        read_toml(big)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # opening it would block until a writer comes
    with pytest.raises(InputError, match=r"fifo\.toml: not a regular file"):
        read_toml(fifo)
    with pytest.raises(InputError, match=r"is a folder"):
        read_toml(tmp_path)


def test_huge_integer_literal_is_one_line(tmp_path):
    t = tmp_path / "p.toml"
    t.write_text("seed = " + "9" * 5000 + "\n")
    with pytest.raises(InputError, match=r"p\.toml: not valid TOML \(Exceeds the limit"):
        read_toml(t)


# --------------------------------------------------------- numbers and sizes


def test_obstacle_centre_1e308_with_html_is_refused_before_planning(tmp_path, capsys):
    text = STATIC.replace("center = [0.0, 90.0, 330.0]", "center = [1e308, 90.0, 330.0]")
    assert text != STATIC
    p = _problem(tmp_path, text)
    kept = _kept(tmp_path)
    out, html = kept
    _one_line(capsys, ["plan", str(p), "--out", str(out), "--html", str(html)], "scene.obstacle[0].center[0]: must be")
    assert {p: p.read_bytes() for p in kept} == kept


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("points = 15", "points = 100000000", "planner.check.points: must be <= 1000, got 100000000"),
        ("max_iterations = 20000", "max_iterations = 99999999999", "planner.max_iterations: must be <= 10000000"),
        ("resolution = 3.0", "resolution = 1e-300", "planner.check.resolution: must be >= 0.1"),
        ("waypoint_step = 20.0", "waypoint_step = 5e-324", "planner.waypoint_step: must be >= 0.1"),
        ("time_limit = 5.0", "time_limit = 1e300", "planner.time_limit: must be"),
        ("goal = [10.0, -120.0, 170.0]", "goal = [10.0, -120.0, 1e300]", "task.goal[2]: must be within +-1e+06"),
        ("safety_distance = 5.0", "safety_distance = 5.0\ntime_step = 1.0", "scene.time_step: no longer supported"),
        ('name = "paper_static"', 'name = "../../etc/x"', "name: '../../etc/x' cannot be part of a file name"),
        ("seed = 1", "seed = 18446744073709551616", "seed: must be <= 4294967295"),
    ],
)
def test_bad_problem_values_are_one_line(old, new, needle, tmp_path, capsys):
    text = STATIC.replace(old, new)
    assert text != STATIC
    p = _problem(tmp_path, text)
    kept = _kept(tmp_path)
    _one_line(capsys, ["plan", str(p), "--out", str(next(iter(kept)))], needle)
    assert {p: p.read_bytes() for p in kept} == kept


@pytest.mark.parametrize("key", MOVED_TO_LOOP)
def test_loop_key_in_replan_section_says_it_moved(key, tmp_path, capsys):
    # an old problem file with a closed-loop key under [replan]: one line naming it and its new section,
    # before any planning, and the run folder is not created
    text = STATIC.replace("[planner]", f"[replan]\n{key} = 2\n\n[planner]", 1)
    p = _problem(tmp_path, text)
    out = tmp_path / "run"
    err = _one_line(capsys, ["replan", str(p), "--out", str(out), "--no-html"], "")
    assert err == f"crtraj: error: replan.{key}: moved to the [loop] section; write it under [loop]\n"
    assert not out.exists()
    # the same key under [loop] is read there
    value = 1 if key == "reference_speed" else 2
    moved = _problem(tmp_path, STATIC.replace("[planner]", f"[loop]\n{key} = {value}\n\n[planner]", 1), "q.toml")
    assert Problem.load(moved).options(LoopOptions, "loop").to_dict()[key] == value


def test_scene_time_step_message_is_exact(tmp_path, capsys):
    p = _problem(tmp_path, STATIC.replace("safety_distance = 5.0", "time_step = 1.0\nsafety_distance = 5.0"))
    err = _one_line(capsys, ["plan", str(p)], "")
    assert err == "crtraj: error: scene.time_step: no longer supported (it had no effect); remove it\n"


def test_shipped_problems_have_no_time_step():
    for p in (ROOT / "problems").glob("*.toml"):
        assert "time_step" not in read_toml(p).get("scene", {}), p


def test_collision_points_1e5_is_refused(tmp_path, capsys):
    (tmp_path / "r.toml").write_text(ROBOT.replace("collision_points = 10", "collision_points = 100000"))
    _one_line(
        capsys,
        ["export", "--robot", str(tmp_path / "r.toml"), "--out", str(tmp_path / "x"), "--no-compile"],
        "robot.collision_points: must be <= 200, got 100000",
    )
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--points", "100000"], "--points: must be in [2, 1000], got 100000"),
        (["--points", "1"], "--points: must be in [2, 1000], got 1"),
        (["--batch", "1000000000"], "--batch: must be in [1, 1000000], got 1000000000"),
        (["--batch", "0"], "--batch: must be in [1, 1000000], got 0"),
        (["--batch", "1e9"], "argument --batch: invalid int value: '1e9'"),
    ],
)
def test_export_sizes_are_bounded_before_building(flags, needle, tmp_path, capsys):
    out = tmp_path / "x"
    capsys.readouterr()
    try:
        rc = cli.main(["export", "--out", str(out), "--no-compile", *flags])
    except SystemExit as exc:  # argparse's own errors: one line too
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and err.startswith("crtraj: error: ") and needle in err, err
    assert not out.exists()


@pytest.fixture()
def plan_result(model, tmp_path) -> Path:
    """A small valid plan result over 4 s, with the robot's actuators (streams in a dry run)."""
    robot = model.robot
    X = np.linspace(0.0, 1.0, 5)[:, None] * np.array([0.05, 0.0, 0.0, 0.05, 10.0])
    wps = [{"t": float(4.0 * i / 4), "x": X[i].tolist(), "q": robot.cables(X[i]).tolist()} for i in range(5)]
    res = {"kind": "plan", "robot": json.loads(json.dumps(robot.to_dict(), default=float)), "waypoints": wps}
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(res, default=lambda o: o.tolist()))
    return p


def test_waypoint_time_1e300_to_stream_is_one_line(plan_result, tmp_path, capsys):
    res = json.loads(plan_result.read_text())
    res["waypoints"][-1]["t"] = 1e300
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(res))
    frames = tmp_path / "frames.bin"
    frames.write_bytes(b"old frames")
    log = tmp_path / "log.jsonl"
    _one_line(
        capsys,
        ["stream", str(bad), "--dry-run", str(frames), "--log", str(log)],
        "waypoints[4].t: must be within +-1e+06, got 1e+300",
    )
    assert frames.read_bytes() == b"old frames" and not log.exists()


@pytest.mark.parametrize(
    ("value", "needle"),
    [
        ("1e9", "--time-scale: must be <= 1000, got 1e+09"),
        ("inf", "--time-scale: must be finite, got inf"),
        ("nan", "--time-scale: must be finite, got nan"),
        ("0", "--time-scale: must be >= 0.001, got 0"),
        ("-2", "--time-scale: must be >= 0.001, got -2"),
    ],
)
def test_time_scale_is_bounded_with_the_right_message(value, needle, plan_result, tmp_path, capsys):
    frames = tmp_path / "frames.bin"
    frames.write_bytes(b"old frames")
    argv = ["stream", str(plan_result), "--dry-run", str(frames), "--log", str(tmp_path / "l.jsonl")]
    _one_line(capsys, [*argv, "--time-scale", value], needle)
    assert frames.read_bytes() == b"old frames"
    _one_line(capsys, ["replan", str(tmp_path / "missing.toml"), "--time-scale", value], needle)


def test_setpoint_count_is_bounded_before_allocating(model):
    acts = Actuators.from_robot(model.robot)
    q = model.robot.cables(np.zeros((2, model.robot.nx)))
    path = SetpointPath.from_actuation([0.0, 1e6], q, acts)
    with pytest.raises(InputError, match=rf"1e\+06 s at 100 Hz is more than {MAX_SETPOINTS} set-points"):
        path.sample(100.0)
    # the bound is a count, not a guess: just under it samples
    short = SetpointPath.from_actuation([0.0, MAX_SETPOINTS / 1000.0 / 10], q, acts)
    stamps, _ = short.sample(1000.0)
    assert len(stamps) == MAX_SETPOINTS // 10 + 1


def test_replan_step_count_is_bounded():
    with pytest.raises(InputError, match=r"loop\.duration: 1e\+06 s is 1000000000 steps of replan\.dt 0\.001 s"):
        LoopOptions(duration=1e6).steps(1e-3)
    assert LoopOptions(duration=1e4).steps(0.1) == 100_000  # the bound itself is allowed
    with pytest.raises(InputError, match=r"replan\.dt: must be >= 0\.001"):
        ReplanOptions.from_table(Table({"dt": 1e-300}, "replan"))
    with pytest.raises(InputError, match=r"replan\.max_iter: must be <= 100000"):
        ReplanOptions.from_table(Table({"max_iter": 10**12}, "replan"))


# ----------------------------------------------------------- the primitives


def test_every_integer_field_must_state_its_upper_bound():
    t = Table({"n": 3}, "x")
    with pytest.raises(TypeError):
        t.int("n", ge=0)  # no `le`: refused when the code is written, not when a user finds it
    assert t.int("n", ge=0, le=3) == 3
    with pytest.raises(InputError, match=r"^x\.n: must be <= 2, got 3$"):
        Table({"n": 3}, "x").int("n", ge=0, le=2)


def test_numbers_are_magnitude_bounded_and_strings_are_not_numbers():
    with pytest.raises(InputError, match=r"^v: must be within \+-1e\+09, got 1e\+300$"):
        Table({"v": 1e300}, "").float("v")
    with pytest.raises(InputError, match=r"^v: must be within \+-1e\+09, got an integer of 401 digits$"):
        Table({"v": 10**400}, "").float("v")
    assert Table({"v": -1e9}, "").float("v") == -1e9
    for bad in (["1", 2], [True, 2], [None, 2], [[1], 2]):
        with pytest.raises(InputError, match=r"^a: expected numbers"):
            check_array(bad, "a", (2,))
    with pytest.raises(InputError, match=r"^a: values must be within \+-1e\+06"):
        check_array([0.0, -2e6], "a", (2,), limit=1e6)


def test_odd_keys_and_values_stay_on_one_line(tmp_path, capsys):
    p = _problem(tmp_path, STATIC.replace("[task]", '[task]\n"a\\nb\\u0001" = "x\\ny"'))
    err = _one_line(capsys, ["plan", str(p)], "task.'a\\nb\\x01': unknown key")
    # the key's newline and control character are shown escaped, never written raw to the terminal
    body = err[: -len("\n")]
    assert body.isprintable() and "\x01" not in err and "\r" not in err, repr(err)


# ----------------------------------------------------- end to end (subprocess)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["plan", "{dir}/utf16.toml"], "utf16.toml: not UTF-8 text (it looks like UTF-16)"),
        (["view", "{dir}/deep.json", "--html", "{dir}/v.html"], "deep.json: not valid JSON (nested deeper than 32"),
        (["export", "--points", "100000", "--out", "{dir}/x", "--no-compile"], "--points: must be in [2, 1000]"),
    ],
    ids=["utf16-plan", "deep-view", "export-points"],
)
def test_end_to_end_no_traceback(args, needle, tmp_path):
    (tmp_path / "utf16.toml").write_bytes(UTF16)
    (tmp_path / "deep.json").write_text("[" * 100_000 + "]" * 100_000)
    argv = [a.replace("{dir}", str(tmp_path)) for a in args]
    # the timeout bounds a hang (the measured ones ran > 150 s); a normal run takes about a second
    proc = subprocess.run([sys.executable, "-m", "crtraj.cli", *argv], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and proc.stderr.startswith("crtraj: error: "), proc.stderr
    assert needle in proc.stderr
    assert not (tmp_path / "v.html").exists() and not (tmp_path / "x").exists()


# ------------------------------------------------------------ non-finite times in the validity checks


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "compiled"])
@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
def test_non_finite_edge_times_are_refused_before_numpy_sees_them(bad, compiled, model, tmp_path):
    """Issue 36: an infinite or NaN motion time is one InputError naming the time (t0, t1, t), never numpy's
    "invalid value" RuntimeWarning first (pyproject's filterwarnings makes such a warning from the validity
    module an error; here it is an error whatever the configuration)."""
    import warnings

    from crtraj.planning.validity import Kernels, MotionValidator
    from crtraj.world.scene import Scene

    scene = Problem.load(ROOT / "problems" / "paper_dynamic.toml").options(Scene, "scene")
    v = MotionValidator(model, scene, kernels=Kernels(), compiled=compiled)
    assert (v.state.kernel is not None) == compiled
    rng = np.random.default_rng(0)
    XA, XB = v.sample(rng, 2), v.sample(rng, 2)
    good = np.array([0.0, 1.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for name, TA, TB in (("t0", np.array([0.0, bad]), good + 1), ("t1", good, np.array([1.0, bad]))):
            for check in (v.check_edges, v.edge_clearance, v.edges_valid):
                with pytest.raises(InputError, match=f"^{name}: contains NaN or infinity$"):
                    check(XA, XB, TA, TB)
        with pytest.raises(InputError, match=r"^t: contains NaN or infinity$"):
            v.path_clearance(np.vstack([XA, XB]), np.array([0.0, 1.0, bad, 3.0]))
        # finite times still pass through (the refusal is not a blanket one)
        assert v.edge_clearance(XA, XB, good, good + 1)[0].shape == (2,)
