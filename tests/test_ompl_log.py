"""OMPL benchmark logs and the runs.csv log: round trips through parsers written apart from the writers.

`_parse` follows the published grammar of OMPL's benchmark log (the one
``ompl_benchmark_statistics.py`` reads) line by line; OMPL's own reader
then loads the same text into its SQLite database.
"""

from __future__ import annotations

import itertools
import math
import sqlite3

import pytest
from conftest import require_module

from crtraj.bench.ompl_log import log_text, write_logs
from crtraj.bench.records import RunRecord
from crtraj.bench.runlog import RunLog, read_runs
from crtraj.planning.planners._ompl import OMPLPlanner


def _rec(planner: str, index: int, *, ok: bool, paper_ok: bool, progress: str = "", status: str = "exact") -> RunRecord:
    nan = math.nan
    return RunRecord(
        planner, 3, index, 11 + index, status, status == "exact", ok, ok, 0.5 + index, 300.0 + index if ok else nan,
        7.25, 0.01, 12.0, 9, "host:1", "msg, with comma", "ok" if ok else "rejected",
        check_mode="paper" if planner.endswith("-paper") else "strict", dsf_clearance_mm=2.25,
        paper_success=paper_ok, paper_clearance_mm=4.5, first_solution_s=0.25 + index, graph_states=40 + index,
        best_cost=250.5 + index, cost_progress=progress, cpu_s=0.4 + index,
    )  # fmt: skip


RECORDS = [
    _rec("rrt-paper", 0, ok=False, paper_ok=True),
    _rec("rrt-paper", 1, ok=True, paper_ok=True),
    _rec("ompl-rrtstar", 0, ok=True, paper_ok=True, progress="0.5:400;1.25:320.5;3:300"),
    _rec("ompl-rrtstar", 1, ok=False, paper_ok=False, status="approximate"),
]


def _value(kind: str, cell: str) -> object:
    """One cell of a run line by its declared type (empty: missing)."""
    if cell == "":
        return None
    return cell == "1" if kind == "BOOLEAN" else int(cell) if kind == "INTEGER" else float(cell)


def _parse(text: str) -> dict:
    """A reader of the OMPL benchmark log grammar, written from its description, not from the writer."""
    lines = text.split("\n")
    pos = 0

    def take() -> str:
        nonlocal pos
        pos += 1
        return lines[pos - 1]

    def block() -> list[str]:
        assert take() == "<<<|"
        out = []
        while (line := take()) != "|>>>":
            out.append(line)
        return out

    head = {"library": take().split()}
    assert head["library"][1] == "version"
    assert take().startswith("Experiment ")
    nprops = int(take().split()[0])
    head["experiment properties"] = dict(take().split(" = ") for _ in range(nprops))
    assert take().startswith("Running on ") and take().startswith("Starting at ")
    head["setup"], head["cpuinfo"] = block(), block()
    assert take().endswith("is the random seed")
    head["time limit"] = float(take().split()[0])
    assert take().endswith("MB per run")
    head["runs per planner"] = int(take().split()[0])
    assert take().endswith("seconds spent to collect the data")
    assert take() == "0 enum types"
    planners = {}
    for _ in range(int(take().split(" planners")[0])):
        name = take()
        assert take() == "0 common properties"
        props = [take().rsplit(" ", 1) for _ in range(int(take().split(" properties for each run")[0]))]
        runs = []
        for _ in range(int(take().split(" runs")[0])):
            line = take()
            assert line.endswith("; ") or line == ""
            cells = line.split("; ")[:-1]
            assert len(cells) == len(props)
            runs.append({name_: _value(kind, c) for (name_, kind), c in zip(props, cells, strict=True)})
        progress_props = [take().rsplit(" ", 1) for _ in range(int(take().split()[0]))]
        assert [p[0] for p in progress_props] == ["time", "best cost"]
        series = []
        for _ in range(int(take().split(" runs")[0])):
            samples = take().split(";")[:-1]
            series.append([tuple(float(v) for v in s.split(",")[:-1]) for s in samples])
        assert take() == "."
        planners[name] = {"runs": runs, "progress": series}
    assert pos == len(lines) - 1 and lines[-1] == ""  # nothing after the last planner
    return {"head": head, "planners": planners}


def test_log_round_trip_through_an_independent_parser():
    text = log_text(
        RECORDS, ["rrt-paper", "ompl-rrtstar"], experiment="t 3obs", mode="paper", time_limit=5.0, setup="a\nb"
    )
    log = _parse(text)
    assert log["head"]["experiment properties"] == {"check_mode VARCHAR(16)": "paper"}
    assert log["head"]["time limit"] == 5.0 and log["head"]["runs per planner"] == 2
    assert log["head"]["setup"] == ["a", "b"]
    for name in ("rrt-paper", "ompl-rrtstar"):
        mine = sorted((r for r in RECORDS if r.planner == name), key=lambda r: r.index)
        got = log["planners"][name]
        for r, run in zip(mine, got["runs"], strict=True):
            assert run["time"] == pytest.approx(r.time_s) and run["cpu time"] == pytest.approx(r.cpu_s)
            assert run["solved"] is True  # exact or approximate: a path came back
            assert run["approximate solution"] is (r.status == "approximate")
            assert run["correct solution"] is r.paper_success  # the paper mode's verdict
            assert run["solution length"] == (None if math.isnan(r.length_mm) else pytest.approx(r.length_mm))
            assert run["solution clearance"] == pytest.approx(r.dsf_clearance_mm)
            assert run["surface clearance"] == pytest.approx(r.min_clearance_mm)
            assert run["graph states"] == r.graph_states
            assert run["time first solution"] == pytest.approx(r.first_solution_s)
            assert run["best cost"] == pytest.approx(r.best_cost)
    assert log["planners"]["ompl-rrtstar"]["progress"] == [[(0.5, 400.0), (1.25, 320.5), (3.0, 300.0)], []]
    strict = _parse(log_text(RECORDS, ["rrt-paper"], experiment="s", mode="strict", time_limit=5.0, setup=""))
    assert [run["correct solution"] for run in strict["planners"]["rrt-paper"]["runs"]] == [False, True]


def test_ompls_own_statistics_script_reads_the_logs(tmp_path):
    require_module("ompl", hint="pip install 'crtraj[bench]'")
    from ompl.tools import readBenchmarkLog

    files = write_logs(RECORDS, tmp_path, {"paper": ("rrt-paper", "ompl-rrtstar")}, (3,), time_limit=5.0, setup="x")
    db = tmp_path / "bench.db"
    readBenchmarkLog(str(db), [str(f) for f in files], False)
    con = sqlite3.connect(db)
    assert con.execute("select name, timelimit, runcount, check_mode from experiments").fetchall() == [
        ("table1-paper-3obs", 5.0, 2, "paper")
    ]
    rows = con.execute(
        "select p.name, r.time, r.correct_solution, r.solution_length, r.graph_states, r.best_cost "
        "from runs r join plannerConfigs p on r.plannerid = p.id order by p.name, r.time"
    ).fetchall()
    assert rows == [
        ("ompl-rrtstar", 0.5, 1, 300.0, 40, 250.5),
        ("ompl-rrtstar", 1.5, 0, None, 41, 251.5),
        ("rrt-paper", 0.5, 1, None, 40, 250.5),
        ("rrt-paper", 1.5, 1, 301.0, 41, 251.5),
    ]
    progress = con.execute("select time, best_cost from progress order by time").fetchall()
    assert progress == [(0.5, 400.0), (1.25, 320.5), (3.0, 300.0)]


def test_runs_csv_appends_and_reads_back(tmp_path):
    path = tmp_path / "runs.csv"
    log = RunLog(path)
    for r in RECORDS[:2]:
        log.append(r)
    log.close()
    log = RunLog(path)  # reopened: no second header
    for r in RECORDS[2:]:
        log.append(r)
    log.close()
    back = sorted(read_runs(path), key=lambda r: (r.planner, r.index))
    want = sorted(RECORDS, key=lambda r: (r.planner, r.index))
    for a, b in zip(back, want, strict=True):
        for k in RunRecord.fields():
            va, vb = getattr(a, k), getattr(b, k)
            if isinstance(vb, float) and math.isnan(vb):
                assert math.isnan(va), k
            elif isinstance(vb, float):
                assert va == pytest.approx(vb, rel=1e-5), k
            else:
                assert va == vb, k


class _FakeRRTstar:
    """OMPL's RRTstar as the watch sees it: its best cost, infinite until a first solution."""

    def __init__(self, costs):
        self.costs = iter(costs)

    def bestCost(self):  # noqa: N802 (OMPL's name)
        value = next(self.costs)
        return type("Cost", (), {"value": lambda self: value})()


def test_rrtstar_watch_records_first_solution_and_improvements_only():
    planner, progress = _FakeRRTstar([math.inf, math.inf, 500.0, 500.0, 420.0, 430.0, 400.0]), []
    for _ in range(7):
        assert OMPLPlanner._watch(planner, 0.0, progress) is False  # never stops the search
    assert [c for _, c in progress] == [500.0, 420.0, 400.0]
    assert all(a[0] <= b[0] for a, b in itertools.pairwise(progress))
