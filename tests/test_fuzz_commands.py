"""Fuzz test of the newer commands: `record`, `calibrate`, `feed-replay`, `build` and `stream --dynamixel`.

Seeded hostile input - random bytes, integers of 400 digits, 1e300, NaN, numbers written in other scripts'
digits, empty strings for path and device flags, FIFOs where files belong, an output that is an input -
must end every case with exit 1 or 2, exactly one stderr line ``crtraj: ...``, no traceback, and every
file that existed before byte-identical (the harness of `test_fuzz`).
"""

from __future__ import annotations

import functools
import json
import math
import os
import random

import numpy as np
import pytest
from test_fuzz import (
    CASES,
    ROOT,
    Outputs,
    _leaves,
    _problem_dict,
    _result_dict,
    _robot_dict,
    _tables,
    corrupt_bytes,
    mutate,
    run_main,
    to_toml,
)

from crtraj import cli
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.io.problem import Problem, load_robot
from crtraj.model.calibration import Hardware, paper_markers, simulate_markers
from crtraj.world.scene import Scene

_UNICODE_DIGITS = ["\u0661\u0662", "\u00b2", "\uff11\uff12", "\u07c1", "1\u0662"]
_HOSTILE = [10**400, -(10**400), 1e300, -1e300, math.nan, math.inf]


def _scene_is_valid(data: dict) -> bool:
    """Whether the library's problem reader accepts `data`'s scene (the oracle for a mutation that is valid)."""
    try:
        Problem.from_dict(json.loads(json.dumps(data)), None).options(Scene, "scene")
    except InputError:
        return False
    return True


def assert_one_line_failure(rc: int, err: str, what: str) -> None:
    assert rc in (1, 2), f"{what}: exit {rc}, stderr {err!r}"
    assert err.count("\n") == 1 and err.endswith("\n"), f"{what}: not exactly one line: {err!r}"
    assert err.startswith("crtraj: ") and "Traceback" not in err, f"{what}: {err!r}"


def _keep(outs: Outputs, name: str, data: bytes) -> str:
    """Add a pre-existing file (an input, say) that must be byte-identical after every case."""
    outs.files[name] = data
    (outs.folder / name).write_bytes(data)
    return outs[name]


def _garble(rng: random.Random, text: str) -> bytes:
    """`corrupt_bytes`, but never a clean truncation (a log or capture cut between lines is still valid)."""
    data = corrupt_bytes(rng, text)
    while text.encode().startswith(data):
        data = corrupt_bytes(rng, text)
    return data


def _log_lines(names: list[str]) -> list[dict]:
    """A stream log (JSON lines) over 2 s: a header and set-points at 10 Hz."""
    tx = [{"type": "tx", "wall": 0.1 * k, "kind": "move", "values": [0.01 * k] * len(names)} for k in range(21)]
    return [{"type": "header", "names": names}, *tx]


@functools.cache
def _marker_rows() -> list[tuple]:
    """The paper's three markers where the nominal robot puts them (capture frame = robot frame, no noise) at the
    log's values interpolated to the marker times, so the unmutated join passes `record`'s unit check."""
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    act = Actuators.from_robot(robot)
    t = np.array([0.05 + 0.1 * k for k in range(19)])
    values = np.repeat(0.1 * t[:, None], act.n, axis=1)  # the log: 0.01 k at 0.1 k s, every actuator
    sites = paper_markers(robot.n_segments)
    m, _ = simulate_markers(robot, Hardware(act.spool_radius, act.sign), act.zero_offset, np.zeros(6), values, sites)
    return [(float(t[k]), s.name, tuple(float(c) for c in m[k, j])) for k in range(len(t)) for j, s in enumerate(sites)]


def _markers_text(rows: list[tuple]) -> str:
    return "timestamp,marker,x,y,z\n" + "".join(f"{t},{m},{x},{y},{z}\n" for t, m, (x, y, z) in rows)


def _hostile_log(rng: random.Random, names: list[str]) -> bytes:
    """A stream log with one hostile number (a huge integer, 1e300, NaN, a Unicode-digit string) or random bytes."""
    lines = _log_lines(names)
    how = rng.choice(["bytes", "number", "number", "digits"])
    if how == "bytes":
        return _garble(rng, "".join(json.dumps(x) + "\n" for x in lines))
    k = rng.randrange(1, len(lines))
    bad = rng.choice(_HOSTILE) if how == "number" else rng.choice(_UNICODE_DIGITS)
    if rng.random() < 0.5:
        lines[k]["wall"] = bad
    else:
        lines[k]["values"][rng.randrange(len(names))] = bad
    return "".join(json.dumps(x, allow_nan=True) + "\n" for x in lines).encode()


def _hostile_markers(rng: random.Random) -> bytes:
    """The marker CSV with one cell a Unicode-digit number, a 400-digit integer, 1e300 or inf; or random bytes."""
    text = _markers_text(_marker_rows())
    if rng.random() < 0.25:
        return _garble(rng, text)
    rows = [list(r) for r in _marker_rows()]
    k = rng.randrange(len(rows))
    bad = rng.choice([*_UNICODE_DIGITS, "9" * 400, "1e300", "-inf"])
    if rng.random() < 0.5:
        rows[k][0] = bad
    else:
        xyz = list(rows[k][2])
        xyz[rng.randrange(3)] = bad
        rows[k][2] = tuple(xyz)
    return _markers_text(rows).encode()


@pytest.fixture()
def record_inputs(robot, tmp_path):
    """(outputs, robot file, actuator names) of the record and calibrate cases."""
    outs = Outputs(tmp_path / "outs")
    names = list(Actuators.from_robot(robot).names)
    src = _keep(outs, "robot.toml", (ROOT / "problems" / "robots" / "cdsr2.toml").read_bytes())
    return outs, src, names


def test_fuzz_record_and_calibrate_logs_and_marker_files(record_inputs, tmp_path, capsys):
    outs, robot_file, names = record_inputs
    log, mk = tmp_path / "log.jsonl", tmp_path / "m.csv"
    log.write_text("".join(json.dumps(x) + "\n" for x in _log_lines(names)))
    mk.write_text(_markers_text(_marker_rows()))
    control = ["record", "--robot", robot_file, "--log", str(log), "--markers", str(mk)]
    rc, err = run_main([*control, "--out", str(tmp_path / "d.json")], capsys)
    assert rc == 0, err  # the control: unmutated, the join works
    rng = random.Random(21)
    for i in range(CASES):
        if i % 2:
            log.write_bytes(_hostile_log(rng, names))
            mk.write_text(_markers_text(_marker_rows()))
        else:
            log.write_text("".join(json.dumps(x) + "\n" for x in _log_lines(names)))
            mk.write_bytes(_hostile_markers(rng))
        argv = ["--robot", robot_file, "--log", str(log), "--markers", str(mk), "--out", outs["out.json"]]
        rc, err = run_main(["record", *argv], capsys)
        assert_one_line_failure(rc, err, f"record case {i}")
        outs.check()
        if i % 5 == 0:
            argv[-1] = str(outs.folder / "cal.toml")
            rc, err = run_main(["calibrate", *argv], capsys)
            assert_one_line_failure(rc, err, f"calibrate case {i}")
            outs.check()


def test_fuzz_calibrate_datasets_fifos_empty_flags_and_its_own_input(record_inputs, tmp_path, capsys):
    outs, robot_file, _ = record_inputs
    rng = random.Random(22)
    data = tmp_path / "data.json"
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    docs = [{"t": [10**400]}, {"t": [1e300], "values": [[math.nan]]}, [[[]]], {"\u0661": "\u0661"}]
    for i in range(CASES // 3):
        data.write_bytes(corrupt_bytes(rng, "{}") if i % 2 else json.dumps(rng.choice(docs)).encode())
        rc, err = run_main(["calibrate", str(data), "--robot", robot_file, "--out", outs["out.json"]], capsys)
        assert_one_line_failure(rc, err, f"calibrate dataset case {i}")
        outs.check()
    cases = [
        ["calibrate", str(fifo), "--robot", robot_file, "--out", str(tmp_path / "c.toml")],
        ["calibrate", str(data), "--robot", robot_file, "--out", robot_file],  # the output is the input
        ["calibrate", str(data), "--robot", robot_file, "--out", ""],
        ["record", "--robot", robot_file, "--log", str(fifo), "--markers", str(fifo), "--out", str(tmp_path / "d")],
        ["record", "--robot", robot_file, "--log", "", "--markers", str(data), "--out", str(tmp_path / "d.json")],
        ["record", "--robot", "", "--log", str(data), "--markers", str(data), "--out", str(tmp_path / "d.json")],
    ]
    for argv in cases:
        try:
            rc, err = run_main(argv, capsys)
        except SystemExit as exc:  # argparse's own errors
            rc, err = exc.code, capsys.readouterr().err
        assert_one_line_failure(rc, err, " ".join(argv))
        outs.check()
    assert not (tmp_path / "c.toml").exists() and not (tmp_path / "d.json").exists()


def _cli(argv: list[str], capsys) -> tuple[int, str]:
    """`run_main`, with argparse's exit (a bad flag) as its exit code."""
    try:
        return run_main(argv, capsys)
    except SystemExit as exc:
        return int(exc.code), capsys.readouterr().err


def test_fuzz_feed_replay_scene_and_flags(tmp_path, capsys):
    rng = random.Random(23)
    problem_data = _problem_dict()
    scene = {"scene": problem_data["scene"]}
    leaves, tables = _leaves(scene), _tables(scene)
    tiny = [p for p in leaves if p[-1] in ("radius",)]
    outs = Outputs(tmp_path / "outs")
    base = tmp_path / "base.toml"
    base.write_text(to_toml(problem_data))
    flags = [["--udp", ""], ["--udp", "127.0.0.1:\u0669\u0668\u0667"], ["--rate", "\u0661\u0660"], ["--udp", "x:1"]]
    flags += [["--seed", "\u00b2"], ["--duration", "1_0"]]
    for i in range(CASES // 2):
        src = tmp_path / f"f{i}.toml"
        data = dict(problem_data, **mutate(rng, scene, leaves, tables, tiny or leaves[:1]))
        src.write_bytes(corrupt_bytes(rng, to_toml(problem_data)) if i % 4 == 0 else to_toml(data).encode())
        rc, err = _cli(["feed-replay", str(src), "--udp", "127.0.0.1:9", "--duration", "0.01"], capsys)
        if i % 4 and _scene_is_valid(data):  # a mutation the library's own reader accepts (a radius of 5e-324
            assert rc == 0 and err == "", f"feed-replay case {i}: a valid scene refused: {err!r}"  # mm is one)
        else:
            assert_one_line_failure(rc, err, f"feed-replay case {i}")
        outs.check()
    for f in flags:
        argv = ["feed-replay", str(base), "--udp", "127.0.0.1:9", "--duration", "0.01", *f]
        rc, err = _cli(argv, capsys)
        assert_one_line_failure(rc, err, " ".join(f))


def test_fuzz_build_robot_files_flags_and_cache_folders(tmp_path, capsys, monkeypatch):
    rng = random.Random(24)
    base = {"robot": _robot_dict()}
    leaves = [p for p in _leaves(base) if p[:2] not in (("robot", "description"), ("robot", "actuators"))]
    tables = [p for p in _tables(base) if p[:2] != ("robot", "actuators")]
    cache = tmp_path / "cache"
    cache.mkdir()
    monkeypatch.setenv("CRTRAJ_CACHE_DIR", str(cache))
    outs = Outputs(cache)  # a user's files in the cache folder: a folder with a manifest.json among them
    for i in range(CASES // 2):
        src = tmp_path / f"b{i}.toml"
        if i % 4 == 0:
            src.write_bytes(corrupt_bytes(rng, to_toml(base)))
        else:
            src.write_text(to_toml(mutate(rng, base, leaves, tables, [("robot", "cable_radius")])))
        rc, err = _cli(["build", "--robot", str(src)], capsys)
        assert_one_line_failure(rc, err, f"build case {i}")
        outs.check()
    for flags in (["--check-points", "\u0661\u0660"], ["--check-points", "9" * 400], ["--robot", ""]):
        rc, err = _cli(["build", *flags], capsys)
        assert_one_line_failure(rc, err, " ".join(flags)[:40])
    os.mkfifo(cache / "entry-fifo")
    (cache / "entry-fifo-dir").mkdir()
    os.mkfifo(cache / "entry-fifo-dir" / "manifest.json")
    outs.files["entry-fifo-dir/manifest.json"] = b""  # stands for itself: a FIFO, kept
    capsys.readouterr()
    assert cli.main(["build", "--list"]) == 0
    assert "entry-fifo-dir" in capsys.readouterr().out
    assert cli.main(["build", "--clear"]) == 0
    assert (cache / "entry-fifo").exists() and (
        cache / "export" / "manifest.json"
    ).read_bytes() == b'{"keep": "export"}\n'


def test_fuzz_stream_dynamixel_targets(model, tmp_path, capsys):
    res = tmp_path / "r.json"
    res.write_text(json.dumps(_result_dict(model)))
    outs = Outputs(tmp_path / "outs")
    result = _keep(outs, "r.json", res.read_bytes())
    fifo, plain = tmp_path / "fifo", tmp_path / "plain"
    os.mkfifo(fifo)
    plain.write_bytes(b"not a serial port")
    log = ["--log", outs["stream.jsonl"]]
    cases = [
        ["--dynamixel", ""],
        ["--serial", ""],
        ["--dry-run", ""],
        ["--udp", ""],
        ["--dynamixel", str(tmp_path / "no-such-port")],
        ["--dynamixel", str(fifo)],
        ["--dynamixel", str(plain), "--baud", "\u0661\u0660\u0660"],
        ["--dynamixel", str(plain), "--baud", "9" * 400],
        ["--dry-run", outs["frames.bin"], "--log", result],  # the log would overwrite the result
        ["--dry-run", result],  # the frames would overwrite the result
    ]
    for flags in cases:
        argv = ["stream", result, *flags] + (log if "--log" not in flags else [])
        rc, err = _cli(argv, capsys)
        assert_one_line_failure(rc, err, " ".join(flags)[:60])
        outs.check()
