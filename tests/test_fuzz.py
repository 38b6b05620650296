"""Fuzz test of every file crtraj reads: problem TOML, robot TOML and result JSON.

A seeded generator turns a valid file into an INVALID one - random bytes, a
truncation, a wrong type, NaN or infinity, a huge or (where a floor applies)
a tiny number, deep nesting, an unknown key - and feeds it to the command that
reads it (`plan`, `replan`, `export --robot`, `stream --dry-run`, `view
--html`). Every mutation is invalid by construction (it hits a field the
command reads, in a way its schema rejects), so every case must end with:

- exit code 2 (bad input) - never a traceback, never 0;
- exactly one line on stderr, ``crtraj: error: ...``;
- every file that existed before (the --out file or folder, the --html file,
  the dry-run frame file, the stream log) byte-identical, and no new file.

The cases run in-process (`crtraj.cli.main`), which is fast; a few run as
subprocesses with a generous timeout as the end-to-end proof of "no
traceback, no hang" (the timeout bounds a hang; it is not a race).
"""

from __future__ import annotations

import json
import math
import random
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from crtraj import cli
from crtraj.core.fields import Table
from crtraj.core.fileio import read_toml, to_jsonable
from crtraj.io.problem import Problem
from crtraj.model.robot import Robot
from crtraj.planning.options import PlannerOptions
from crtraj.planning.steer import SteerOptions
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
CASES = 30  # per target; the whole file runs in a few seconds in-process

# ------------------------------------------------------------- base inputs


def _robot_dict() -> dict[str, Any]:
    return read_toml(ROOT / "problems" / "robots" / "cdsr2.toml")["robot"]


def _problem_dict() -> dict[str, Any]:
    """paper_static with its robot inline; [task] last, so that every truncation cuts into it."""
    data = read_toml(ROOT / "problems" / "paper_static.toml")
    data["robot"] = _robot_dict()
    task = data.pop("task")
    data["task"] = task
    return data


def _result_dict(model) -> dict[str, Any]:
    """A small valid plan result: 5 waypoints over 20 s from the straight pose to a slight bend."""
    robot = model.robot
    x1 = np.array([0.05, 0.0, 0.0, 0.05, 10.0])
    s = np.linspace(0.0, 1.0, 5)
    X = s[:, None] * x1
    waypoints = [
        {"t": 20.0 * s[i], "x": X[i], "tip": model.tip_position(X[i]), "q": robot.cables(X[i])} for i in range(5)
    ]
    res = {
        "kind": "plan",
        "robot": robot.to_dict(),
        "scene": {"safety_distance": 5.0, "workspace": {"lo": [-150, -150, 0], "hi": [150, 150, 500]}},
        "task": {"start": waypoints[0]["tip"], "goal": waypoints[-1]["tip"], "goal_tolerance": 0.5},
        "status": "success",
        "success": True,
        "waypoints": waypoints,
    }
    return json.loads(json.dumps(to_jsonable(res)))


# ----------------------------------------------------------- TOML writing


def _toml_key(k: str) -> str:
    return json.dumps(k)  # a TOML basic string accepts JSON's escapes


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(data: dict[str, Any]) -> str:
    """TOML text of `data`, one top-level key per line, tables inline (order kept)."""
    return _expand("".join(f"{_toml_key(k)} = {_toml_value(v)}\n" for k, v in data.items()))


# --------------------------------------------------------------- mutations


def _leaves(d: Any, path: tuple = ()) -> list[tuple]:
    """Paths of every scalar in `d` (dict keys and list indices)."""
    if isinstance(d, dict):
        return [p for k, v in d.items() for p in _leaves(v, (*path, k))]
    if isinstance(d, list):
        return [p for i, v in enumerate(d) for p in _leaves(v, (*path, i))]
    return [path]


def _tables(d: Any, path: tuple = ()) -> list[tuple]:
    """Paths of every dict in `d` (itself included)."""
    out = [path] if isinstance(d, dict) else []
    items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) else ()
    for k, v in items:
        out += _tables(v, (*path, k))
    return out


def _get(d: Any, path: tuple) -> Any:
    for p in path:
        d = d[p]
    return d


def _set(d: Any, path: tuple, value: Any) -> None:
    _get(d, path[:-1])[path[-1]] = value


def _category(v: Any) -> str:
    if isinstance(v, bool):
        return "bool"
    if isinstance(v, (int, float)):
        return "number"
    return type(v).__name__


_WRONG = {
    "bool": ["yes", 1, [True], {"v": True}],
    "number": ["12", True, [1.0], {"v": 1.0}, ""],
    "str": [7, 1.5, False, ["a"], {"s": "a"}],
}
_HUGE = [1e300, -1e300, 1e21, -1e21, 10**40, -(10**40), 1.7976931348623157e308, 10**400]
_NONFINITE = [math.nan, math.inf, -math.inf]
_ODD_KEYS = ["typo", "Name", "a b", "time_step_", "\u00e9t\u00e9", "x\ny", "k\x01", "\ud7ff" * 3, "9" * 300]


def _deep(depth: int) -> str:
    """A marker that `_expand` turns into `depth` nested arrays in the file's text (TOML and JSON
    agree on ``[[[1]]]``); the writers here would recurse as deep as the nesting."""
    return f"@@deep:{depth}@@"


def _expand(text: str) -> str:
    """Replace every quoted `_deep` marker by its nested arrays."""
    while '"@@deep:' in text:
        i = text.index('"@@deep:')
        j = text.index('@@"', i + 8)
        n = int(text[i + 8 : j])
        text = text[:i] + "[" * n + "1" + "]" * n + text[j + 3 :]
    return text


def mutate(rng: random.Random, data: dict, leaves: list[tuple], tables: list[tuple], tiny: list[tuple]) -> dict:
    """A copy of `data` with one invalid change at a path the command reads."""
    d = json.loads(json.dumps(data))
    kind = rng.choice(["wrong_type", "nonfinite", "huge", "tiny", "deep", "unknown_key"])
    numeric = [p for p in leaves if _category(_get(d, p)) == "number"]
    if kind == "wrong_type":
        p = rng.choice(leaves)
        _set(d, p, rng.choice(_WRONG[_category(_get(d, p))]))
    elif kind == "nonfinite":
        _set(d, rng.choice(numeric), rng.choice(_NONFINITE))
    elif kind == "huge":
        _set(d, rng.choice(numeric), rng.choice(_HUGE))
    elif kind == "tiny":  # only where a positive floor applies: there a tiny value would explode the work
        _set(d, rng.choice(tiny), rng.choice([1e-300, 5e-324, 1e-12]))
    elif kind == "deep":
        _set(d, rng.choice(leaves), _deep(rng.choice([33, 40, 500, 5000, 100_000])))
    else:
        key = rng.choice(_ODD_KEYS)
        _get(d, rng.choice(tables))[key] = rng.choice([1, "x", 2.5, [1]])
    return d


def _json_nan(d: Any) -> str:
    """JSON text that keeps NaN/inf (as Python's json does) and integers beyond float range."""
    return _expand(json.dumps(d, allow_nan=True))


def corrupt_bytes(rng: random.Random, text: str) -> bytes:
    """Random bytes, a text truncated inside its last line, UTF-16, or bytes flipped to invalid UTF-8."""
    raw = text.encode()
    how = rng.choice(["random", "truncate", "utf16", "flip"])
    if how == "random":
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 400)))
    if how == "truncate":
        last = raw.rstrip(b"\n").rfind(b"\n")
        return raw[: rng.randint(0, max(last, 0))]
    if how == "utf16":
        return text.encode("utf-16")
    i = rng.randrange(len(raw))
    return raw[:i] + bytes([rng.choice([0x80, 0xC0, 0xFF, 0xFE])]) + raw[i + 1 :]


# ---------------------------------------------------------------- harness


class Outputs:
    """Files that exist before a run, with known bytes, to be found unchanged afterwards."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.files = {
            "out.json": b'{"keep": "plan"}\n',
            "out.html": b"<html>keep</html>\n",
            "frames.bin": b"\x00keep-frames\x00",
            "stream.jsonl": b'{"keep": "log"}\n',
            "run/run.json": b'{"keep": "run"}\n',
            "run/run.html": b"<html>run</html>\n",
            "export/manifest.json": b'{"keep": "export"}\n',
        }
        for name, data in self.files.items():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(data)

    def __getitem__(self, name: str) -> str:
        return str(self.folder / name)

    def check(self) -> None:
        found = sorted(str(p.relative_to(self.folder)) for p in self.folder.rglob("*") if p.is_file())
        assert found == sorted(self.files), f"files appeared or vanished: {found}"
        for name, data in self.files.items():
            assert (self.folder / name).read_bytes() == data, f"{name} was changed"


def run_main(argv: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()
    rc = cli.main(argv)
    cap = capsys.readouterr()
    return rc, cap.err


def assert_one_line_error(rc: int, err: str, what: str) -> None:
    assert rc == 2, f"{what}: exit {rc}, stderr {err!r}"
    assert err.count("\n") == 1 and err.endswith("\n"), f"{what}: not exactly one line: {err!r}"
    assert err.startswith("crtraj: error: "), f"{what}: {err!r}"
    assert "Traceback" not in err


# ------------------------------------------------------------- the fuzzers


@pytest.fixture(scope="module")
def problem_data():
    data = _problem_dict()
    # the base is valid for every section plan reads, so each mutation alone makes it invalid
    prob = Problem.from_dict(json.loads(json.dumps(data)), None)
    prob.options(Scene, "scene")
    prob.options(PlannerOptions, "planner")
    prob.options(SteerOptions, "steer")
    return data


def _plan_reads(data: dict) -> tuple[list[tuple], list[tuple], list[tuple]]:
    """(leaves, tables, tiny-floor leaves) of the sections `plan` reads."""
    sections = ("robot", "task", "scene", "planner", "steer", "seed", "name")
    leaves = [p for p in _leaves(data) if p[0] in sections]
    leaves = [p for p in leaves if p[:2] != ("robot", "actuators") and p[:2] != ("robot", "description")]
    leaves = [p for p in leaves if p != ("description",)]
    tables = [p for p in _tables(data) if not p or (p[0] in sections and p[:2] != ("robot", "actuators"))]
    tiny = [("robot", "cable_radius"), ("robot", "segment", 0, "length"), ("robot", "segment", 1, "length")]
    tiny += [("planner", "check", "resolution"), ("planner", "waypoint_step")]
    return leaves, tables, tiny


def test_base_files_are_valid(model, tmp_path, capsys):
    """The control: unmutated, the result streams and views (exit 0), so every failure below is the mutation's."""
    res = tmp_path / "r.json"
    res.write_text(json.dumps(_result_dict(model)))
    rc, err = run_main(["view", str(res), "--html", str(tmp_path / "v.html")], capsys)
    assert rc == 0, err
    rc, err = run_main(
        ["stream", str(res), "--dry-run", str(tmp_path / "f.bin"), "--log", str(tmp_path / "l.jsonl")], capsys
    )
    assert rc == 0, err


def test_fuzz_problem_files_plan_and_replan(problem_data, tmp_path, capsys):
    rng = random.Random(11)
    leaves, tables, tiny = _plan_reads(problem_data)
    outs = Outputs(tmp_path / "outs")
    for i in range(CASES):
        src = tmp_path / f"p{i}.toml"
        if i % 4 == 0:
            src.write_bytes(corrupt_bytes(rng, to_toml(problem_data)))
        else:
            src.write_text(to_toml(mutate(rng, problem_data, leaves, tables, tiny)))
        rc, err = run_main(["plan", str(src), "--out", outs["out.json"], "--html", outs["out.html"]], capsys)
        assert_one_line_error(rc, err, f"plan case {i}")
        outs.check()
        if i % 3 == 0:  # replan reads the same file first (and more sections)
            rc, err = run_main(["replan", str(src), "--out", outs["run"], "--quiet"], capsys)
            assert_one_line_error(rc, err, f"replan case {i}")
            outs.check()


def test_fuzz_robot_files_export(tmp_path, capsys):
    rng = random.Random(12)
    base = {"robot": _robot_dict()}
    Robot.from_table(Table(base["robot"], "robot"))  # the base is valid
    leaves = [p for p in _leaves(base) if p[:2] != ("robot", "description")]
    tables = _tables(base)
    tiny = [("robot", "cable_radius"), ("robot", "segment", 0, "length"), ("robot", "actuators", "spool_radius")]
    outs = Outputs(tmp_path / "outs")
    for i in range(CASES):
        src = tmp_path / f"r{i}.toml"
        if i % 4 == 0:
            src.write_bytes(corrupt_bytes(rng, to_toml(base)))
        else:
            src.write_text(to_toml(mutate(rng, base, leaves, tables, tiny)))
        rc, err = run_main(["export", "--robot", str(src), "--out", outs["export"], "--no-compile"], capsys)
        assert_one_line_error(rc, err, f"export case {i}")
        outs.check()


def _result_reads(res: dict, command: str) -> tuple[list[tuple], list[tuple], list[tuple]]:
    """(leaves, tables, tiny) of a result that `command` (stream or view) reads and validates strictly."""
    leaves = [p for p in _leaves(res) if p[0] == "robot" and p[:2] != ("robot", "description")]
    leaves += [p for p in _leaves(res) if p[0] == "waypoints" and p[2] == "t"]
    if command == "stream":
        leaves += [p for p in _leaves(res) if p[0] == "waypoints" and p[2] == "q"]
    else:
        leaves = [p for p in leaves if p[:2] != ("robot", "actuators")]  # view draws the body only
        leaves += [p for p in _leaves(res) if p[0] == "waypoints" and p[2] in ("x", "tip")]
        leaves += [p for p in _leaves(res) if p[0] in ("task",) and p[1] in ("start", "goal")]
        leaves += [p for p in _leaves(res) if p[:2] == ("scene", "workspace")]
    tables = [p for p in _tables(res) if p[:1] == ("robot",)]
    if command == "view":
        tables = [p for p in tables if p[:2] != ("robot", "actuators")]
    tiny = [("robot", "cable_radius"), ("robot", "segment", 0, "length")]
    return leaves, tables, tiny


@pytest.mark.parametrize("command", ["stream", "view"])
def test_fuzz_result_json(model, command, tmp_path, capsys):
    rng = random.Random(13 if command == "stream" else 14)
    base = _result_dict(model)
    leaves, tables, tiny = _result_reads(base, command)
    outs = Outputs(tmp_path / "outs")
    for i in range(CASES):
        src = tmp_path / f"res{i}.json"
        if i % 4 == 0:
            src.write_bytes(corrupt_bytes(rng, json.dumps(base)))
        else:
            src.write_text(_json_nan(mutate(rng, base, leaves, tables, tiny)))
        if command == "stream":
            argv = ["stream", str(src), "--dry-run", outs["frames.bin"], "--log", outs["stream.jsonl"]]
        else:
            argv = ["view", str(src), "--html", outs["out.html"]]
        rc, err = run_main(argv, capsys)
        assert_one_line_error(rc, err, f"{command} case {i}")
        outs.check()


# ------------------------------------------- end to end, in a subprocess


def _deep_json(depth: int) -> str:
    return "[" * depth + "]" * depth


E2E = [
    ("plan", "p.toml", "a = " + "[" * 5000 + "]" * 5000 + "\n", ["plan", "{src}", "--out", "{out.json}"]),
    ("export", "r.toml", None, ["export", "--robot", "{src}", "--out", "{export}", "--no-compile"]),
    ("view", "r.json", _deep_json(100_000), ["view", "{src}", "--html", "{out.html}"]),
    ("stream", "r.json", None, ["stream", "{src}", "--dry-run", "{frames.bin}", "--log", "{stream.jsonl}"]),
]


@pytest.mark.parametrize(("name", "file", "text", "argv"), E2E, ids=[c[0] for c in E2E])
def test_end_to_end_one_line_no_traceback(name, file, text, argv, tmp_path):
    outs = Outputs(tmp_path / "outs")
    src = tmp_path / file
    if text is None:  # UTF-16: what a Windows editor may save
        src.write_bytes('[robot]\nname = "x"\n'.encode("utf-16"))
    else:
        src.write_text(text)
    names = {"src": str(src), "export": outs["export"], **{k: outs[k] for k in outs.files}}
    args = []
    for a in argv:
        for k, v in names.items():
            a = a.replace("{" + k + "}", v)
        args.append(a)
    proc = subprocess.run(
        [sys.executable, "-m", "crtraj.cli", *args], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert_one_line_error(proc.returncode, proc.stderr, name)
    assert proc.stdout == ""
    outs.check()
