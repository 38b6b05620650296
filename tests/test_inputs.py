"""Input rules every command shares: empty flags are errors, numbers are read by one bounded reader, the
environment's ROS domain is bounded, an output is never an input, and diagnostics go through the ``crtraj``
logger at the level ``-v``/``-q`` set."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from crtraj import cli
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_STAMP, read_int, read_number
from crtraj.core.fileio import MARKER, is_marked
from crtraj.core.logs import configure_logging
from crtraj.hardware.dynamixel import parse_url
from crtraj.hardware.ros import RosOptions, domain_id

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "problems" / "robots" / "cdsr2.toml"


@pytest.fixture(autouse=True)
def _restore_logger():
    log = logging.getLogger("crtraj")
    level, handlers, propagate = log.level, list(log.handlers), log.propagate
    yield
    log.setLevel(level)
    log.handlers[:] = handlers
    log.propagate = propagate


def _exit_and_err(argv: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()
    try:
        rc = cli.main(argv)
    except SystemExit as exc:
        rc = int(exc.code)
    return rc, capsys.readouterr().err


# ------------------------------------------------------------------ empty flags
@pytest.mark.parametrize(
    "argv",
    [
        ["stream", "r.json", "--dynamixel", ""],
        ["stream", "r.json", "--serial", ""],
        ["stream", "r.json", "--dry-run", ""],
        ["stream", "r.json", "--udp", ""],
        ["stream", "r.json", "--dry-run", "f.bin", "--log", ""],
        ["export", "--out", ""],
        ["plan", "p.toml", "--out", ""],
        ["replan", "p.toml", "--stream", ""],
        ["ros-bridge", "p.toml", "--out", ""],
        ["record", "--out", "", "--log", "l.jsonl"],
        ["bench", "table1", "--dask", ""],
        ["view", ""],
    ],
)
def test_an_empty_path_or_url_flag_is_one_line_naming_it(argv, capsys):
    """ "" is never "not given": exit 2, one line naming the flag, before anything is read."""
    rc, err = _exit_and_err(argv, capsys)
    flag = argv[argv.index("") - 1] if argv.index("") > 0 and argv[argv.index("") - 1].startswith("--") else None
    assert rc == 2 and err.count("\n") == 1 and err.startswith("crtraj: error: "), err
    assert "must not be empty" in err and (flag is None or f"argument {flag}: " in err), err


def test_an_empty_note_stays_allowed():
    """--note is free text: an empty line is a valid value, not a missing path."""
    args = cli.build_parser().parse_args(["bench", "modes", "--note", ""])
    assert args.note == ""


@pytest.mark.parametrize("text", ["\u0661\u0660", "1_0", "\uff11"])
def test_int_and_float_flags_take_ascii_digits_only(text, capsys):
    """int() takes Arabic-Indic and full-width digits and "_"; a flag does not."""
    for flag in ("--seed", "--time-limit"):
        rc, err = _exit_and_err(["plan", "p.toml", flag, text], capsys)
        kind = "int" if flag == "--seed" else "float"
        assert rc == 2 and f"argument {flag}: invalid {kind} value" in err and err.count("\n") == 1, err


# --------------------------------------------------------------- number reader
@pytest.mark.parametrize(
    ("value", "message"),
    [
        (10**400, "an integer of 401 digits"),
        (1e300, "must be within"),
        (float("nan"), "must be finite"),
        (float("-inf"), "must be finite"),
        ("\u0661\u0662", "expected a number"),
        ("9" * 400, "expected a number"),
        ("1_000", "expected a number"),
        (True, "expected a number"),
        ("", "expected a number"),
    ],
)
def test_read_number_refuses_with_the_field_name(value, message):
    """Every number from JSON, JSON lines or CSV: bounded and finite, ASCII text, named in the error."""
    with pytest.raises(InputError, match=rf"^log line 3: wall: .*{message}"):
        read_number(value, "log line 3: wall", limit=MAX_STAMP)


def test_read_number_takes_plain_numbers_and_csv_text():
    assert read_number(" -2.5e3 ", "x") == -2500.0 and read_number(7, "x") == 7.0
    assert read_number(1.7e9, "wall", limit=MAX_STAMP) == 1.7e9  # an epoch time stamp is in range


@pytest.mark.parametrize("text", ["\u00b3", "\u0663", "\uff13", "3\u0663", "1_0", "", "+", "0x3"])
def test_read_int_takes_ascii_decimal_only(text):
    """str.isdigit is true for superscripts (int() fails on them); int() takes other scripts' digits."""
    with pytest.raises(InputError, match=r"^id: expected an integer"):
        read_int(text, "id", le=252)


def test_read_int_bounds():
    assert read_int("17", "id", le=252) == 17 and read_int(" +4", "id", le=252) == 4
    with pytest.raises(InputError, match=r"^id: must be in 0\.\.252, got 253$"):
        read_int("253", "id", le=252)
    with pytest.raises(InputError, match=r"^id: must be in 0\.\.252, got an integer of 400 digits$"):
        read_int(10**399, "id", le=252)


# -------------------------------------------------------------- ROS_DOMAIN_ID
@pytest.mark.parametrize("env", ["233", "-1", "99999999999", "\u0663", "1.5", "abc"])
def test_ros_domain_id_from_the_environment_is_bounded(env):
    """An out-of-range ROS_DOMAIN_ID would end the process in Fast DDS's C code: one line naming it."""
    with pytest.raises(InputError, match=r"^ROS_DOMAIN_ID: must be an integer in 0\.\.232"):
        domain_id(RosOptions(), {"ROS_DOMAIN_ID": env})


def test_ros_domain_id_sources():
    """[ros] domain_id wins; else the environment's (0..232); else rclpy's default (None)."""
    assert domain_id(RosOptions(), {"ROS_DOMAIN_ID": " 232 "}) == 232
    assert domain_id(RosOptions(), {"ROS_DOMAIN_ID": ""}) is None
    assert domain_id(RosOptions(), {}) is None
    assert domain_id(RosOptions(domain_id=7), {"ROS_DOMAIN_ID": "999"}) == 7


# -------------------------------------------------------- outputs never inputs
@pytest.fixture()
def result_file(model, tmp_path) -> Path:
    """A small successful plan result of the default robot (streams in a dry run)."""
    robot = model.robot
    wps = [{"t": 2.0 * i, "x": [0.01 * i, 0.0, 0.0, 0.01 * i, float(i)]} for i in range(3)]
    for w in wps:
        w["q"] = robot.cables(w["x"]).tolist()
        w["tip"] = model.tip_position(w["x"]).tolist()
    res = {"kind": "plan", "robot": robot.to_dict(), "status": "success", "success": True, "waypoints": wps}
    p = tmp_path / "r.json"
    p.write_text(json.dumps(res, default=lambda o: o.tolist()))
    return p


def _refused_keeping(argv: list[str], files: list[Path], needle: str, capsys) -> None:
    before = {p: p.read_bytes() for p in files}
    rc, err = _exit_and_err([str(a) for a in argv], capsys)
    assert rc == 2 and err.count("\n") == 1 and needle in err, err
    assert {p: p.read_bytes() for p in files} == before


def test_stream_outputs_are_never_its_inputs(result_file, tmp_path, capsys):
    robot = tmp_path / "robot.toml"
    robot.write_bytes(ROBOT.read_bytes())
    frames = tmp_path / "f.bin"
    base = ["stream", result_file, "--robot", robot]
    _refused_keeping([*base, "--dry-run", frames, "--log", result_file], [result_file], "--log: ", capsys)
    _refused_keeping([*base, "--dry-run", robot], [robot], "--dry-run: ", capsys)
    _refused_keeping([*base, "--dry-run", frames, "--log", frames], [result_file], "is also --log", capsys)
    assert not frames.exists()


def test_view_html_is_never_the_result(result_file, capsys):
    _refused_keeping(["view", result_file, "--html", result_file], [result_file], "--html: ", capsys)


def test_bench_outputs_are_never_its_inputs(tmp_path, capsys):
    out = tmp_path / "b"
    out.mkdir()
    cfg = out / "runs.csv"  # a planner config that table1 would overwrite with its runs
    cfg.write_text("[planner]\n")
    argv = ["bench", "table1", "--out", out, "--planner-config", cfg, "--workers", "0", "--scenarios", "1"]
    _refused_keeping(argv, [cfg], "is also --planner-config", capsys)
    runs = out / "table1-modes.md"
    runs.write_text("planner,count\n")
    _refused_keeping(["bench", "modes", "--runs", runs, "--out", out], [runs], "is also --runs", capsys)


def test_export_replaces_only_its_own_folder_and_never_its_robot(tmp_path, capsys):
    """--out is staged and swapped in whole: a folder of the user's, or one holding the robot file, is refused;
    an earlier export (it carries crtraj's marker) is replaced."""
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep")
    _refused_keeping(["export", "--out", user, "--no-compile"], [user / "notes.txt"], "did not write", capsys)
    robot = user / "robot.toml"
    robot.write_bytes(ROBOT.read_bytes())
    _refused_keeping(["export", "--robot", robot, "--out", user, "--no-compile"], [robot], "holds --robot", capsys)
    out = tmp_path / "export"
    assert cli.main(["export", "--out", str(out), "--no-compile"]) == 0
    assert is_marked(out, "export") and (out / "manifest.json").is_file() and (out / MARKER).is_file()
    (out / "stale.casadi").write_text("from an older export")
    assert cli.main(["export", "--out", str(out), "--no-compile"]) == 0
    assert not (out / "stale.casadi").exists() and (out / "manifest.json").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no staged folder left"


# --------------------------------------------------------------------- logging
@pytest.mark.parametrize(
    ("flags", "shown"),
    [
        ([], {"warning", "error"}),
        (["-v"], {"info", "warning", "error"}),
        (["-vv"], {"debug", "info", "warning", "error"}),
        (["-q"], {"error"}),
    ],
)
def test_v_and_q_set_the_crtraj_logger(flags, shown, capsys):
    """Global -v/-q set the level; each record is one plain `crtraj: ` line on stderr."""
    parser = cli.build_parser()
    args = parser.parse_args([*flags, "build", "--list"])
    configure_logging(args.verbose, args.quiet_log)
    capsys.readouterr()
    log = logging.getLogger("crtraj.core.build_cache")
    for level in ("debug", "info", "warning", "error"):
        getattr(log, level)("%s line", level)
    err = capsys.readouterr().err
    assert err == "".join(f"crtraj: {lv} line\n" for lv in ("debug", "info", "warning", "error") if lv in shown)


def test_build_without_a_compiler_says_so_even_with_q(tmp_path, capsys, monkeypatch):
    """For `crtraj build` no compiler is the failure itself (exit 1), not the cache's diagnostic that -q
    silences: one error line either way (issue 36: no exit 1 with nothing on stderr)."""
    monkeypatch.setenv("CRTRAJ_CC", "none")
    monkeypatch.setenv("CRTRAJ_CACHE_DIR", str(tmp_path / "cache"))
    for argv in (["build", "--robot", str(ROBOT)], ["-q", "build", "--robot", str(ROBOT)]):
        rc, err = _exit_and_err(argv, capsys)
        assert rc == 1 and err.startswith("crtraj: build failed: no C compiler found") and err.count("\n") == 1, err


@pytest.mark.parametrize("baud", ["\u0661\u0660\u0660\u0660\u0660\u0660\u0660", "1_000_000", "9" * 400, "-1"])
def test_dynamixel_url_baud_is_ascii_digits(baud):
    """The baud of ``dynamixel:///dev/X?baud=N`` is read like any other integer: ASCII digits, bounded."""
    assert parse_url("dynamixel:///dev/ttyUSB0?baud=57600") == ("/dev/ttyUSB0", 57600)
    with pytest.raises(InputError, match=r"^stream target: baud must be an integer"):
        parse_url(f"dynamixel:///dev/ttyUSB0?baud={baud}")
