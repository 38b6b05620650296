"""Issue 27 in `crtraj bench`: outputs are never inputs, written together at the end or not at all, a
folder replaced only when it is crtraj's; runs.csv numbers through the bounded reader; a torn log row is
cut on resume. Every refusal is one stderr line, no traceback, with every file already there unchanged."""

from __future__ import annotations

import csv
import hashlib
import io
import math
from pathlib import Path

import pytest

from crtraj.app.bench import OMPL_MARKER
from crtraj.bench.outputs import OutputSet
from crtraj.bench.records import RunRecord
from crtraj.bench.runlog import RunLog, read_runs
from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.core.fileio import MARKER, is_marked, mark_folder


def _snapshot(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under `folder` (hidden ones too), and every folder as "dir"."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _one_line(rc: int, capsys, *needles: str) -> str:
    err = capsys.readouterr().err
    assert rc in (1, 2), err
    assert err.count("\n") == 1 and err.startswith("crtraj: error: ") and "Traceback" not in err, err
    for n in needles:
        assert n in err, err
    return err


def _rec(index: int, ok: bool = True) -> RunRecord:
    return RunRecord(
        "rrt-paper", 3, index, 11 + index, "exact", True, ok, ok, 0.5 + index, 300.0 + index, 7.25, 0.01, 12.0,
        9, "host:1", "msg, with comma", "ok", check_mode="paper", dsf_clearance_mm=2.25, paper_success=True,
        paper_clearance_mm=4.5, first_solution_s=0.25, graph_states=40 + index, best_cost=250.5, cpu_s=0.4,
    )  # fmt: skip


def _runs_csv(path: Path, records: list[RunRecord]) -> Path:
    log = RunLog(path)
    for r in records:
        log.append(r)
    log.close()
    return path


def _with_cell(path: Path, column: str, text: str) -> None:
    """Set `column` of the first data row (CSV line 2) of a runs.csv to `text`."""
    rows = list(csv.DictReader(io.StringIO(path.read_text(encoding="utf-8"))))
    rows[0][column] = text
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=RunRecord.fields(), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    path.write_text(buf.getvalue(), encoding="utf-8")


@pytest.fixture
def old_report(tmp_path: Path) -> Path:
    """A folder holding an earlier `bench modes` report and a user's file: all must survive a refusal."""
    out = tmp_path / "report"
    (out / "ompl").mkdir(parents=True)
    (out / "table1-modes.md").write_text("# old table\n")
    (out / "success.png").write_bytes(b"\x89PNG old")
    (out / "ompl" / "table1-paper-3obs.log").write_text("old log\n")
    (out / "notes.txt").write_text("mine\n")
    return out


# ------------------------------------------------------------------ runs.csv numbers
@pytest.mark.parametrize(
    ("column", "text"),
    [
        ("index", "1" + "0" * 400),  # a 400-digit integer
        ("time_s", "1e300"),
        ("length_mm", "nan"),
        ("best_cost", "inf"),
        ("n_obstacles", "\u0663"),  # ARABIC-INDIC DIGIT THREE: int() takes it
        ("seed", "1_0"),  # int() takes it
        ("graph_states", "\u00b2"),  # SUPERSCRIPT TWO: isdigit() is true
        ("cpu_s", "\u0661.5"),  # float() takes other scripts' digits
        ("waypoints", "-3"),
    ],
)
def test_modes_refuses_an_unbounded_runs_cell_naming_row_and_column(tmp_path, old_report, capsys, column, text):
    runs = _runs_csv(tmp_path / "runs.csv", [_rec(0), _rec(1)])
    _with_cell(runs, column, text)
    before = _snapshot(tmp_path)
    rc = main(["bench", "modes", "--runs", str(runs), "--scenes", "paper", "--out", str(old_report)])
    _one_line(rc, capsys, f"runs.csv:2: {column}")
    assert _snapshot(tmp_path) == before


def test_runs_cells_read_back_exactly_and_empty_floats_are_nan(tmp_path):
    """The bounded reader keeps every value the writer wrote (6 significant digits); NaN is an empty cell."""
    r = _rec(4)
    nan_rec = RunRecord(**{**r.__dict__, "index": 5, "length_mm": math.nan, "best_cost": math.nan})
    back = sorted(read_runs(_runs_csv(tmp_path / "runs.csv", [r, nan_rec])), key=lambda x: x.index)
    assert back[0] == r
    assert math.isnan(back[1].length_mm) and math.isnan(back[1].best_cost) and back[1].graph_states == 44


def test_a_torn_last_row_is_cut_when_the_log_is_resumed(tmp_path):
    """A run killed mid-row leaves a partial line; the resumed log drops it and reads back every whole row."""
    path = _runs_csv(tmp_path / "runs.csv", [_rec(0), _rec(1)])
    whole = path.read_bytes()
    path.write_bytes(whole + b"rrt-paper,3,2,13,exa")
    with pytest.raises(InputError, match=r"runs.csv:4"):
        read_runs(path)
    _runs_csv(path, [_rec(2)])
    assert path.read_bytes().startswith(whole)
    assert sorted(r.index for r in read_runs(path)) == [0, 1, 2]
    assert path.read_text().count("planner,") == 1  # one header


# ------------------------------------------------------------------ output folders
def test_modes_refuses_an_ompl_folder_crtraj_did_not_write(tmp_path, old_report, capsys):
    """DIR/ompl is replaced as a whole: with a file of the user's in it (and no marker) nothing is written."""
    (old_report / "ompl" / "plot-data.txt").write_text("the user's\n")
    runs = _runs_csv(tmp_path / "runs.csv", [_rec(0)])
    before = _snapshot(tmp_path)
    rc = main(["bench", "modes", "--runs", str(runs), "--scenes", "paper", "--out", str(old_report)])
    _one_line(rc, capsys, "--out (ompl)", "plot-data.txt")
    assert _snapshot(tmp_path) == before


def test_modes_refuses_an_input_inside_its_ompl_folder(tmp_path, old_report, capsys):
    runs = _runs_csv(old_report / "ompl" / "runs.csv", [_rec(0)])
    mark_folder(old_report / "ompl", OMPL_MARKER)
    before = _snapshot(tmp_path)
    rc = main(["bench", "modes", "--runs", str(runs), "--scenes", "paper", "--out", str(old_report)])
    _one_line(rc, capsys, "--out (ompl)", "holds --runs")
    assert _snapshot(tmp_path) == before


def test_modes_replaces_its_own_files_and_keeps_the_users(tmp_path, old_report, capsys):
    """A report next to its inputs (docs/table1 holds the runs files): the tables, plots and the ompl folder
    are replaced; the user's notes and the runs file stay byte-identical; the old unmarked log of crtraj's
    naming is replaced with the new set, which carries the marker."""
    runs = _runs_csv(old_report / "runs-7.csv", [_rec(0), _rec(1, ok=False)])
    keep = {n: (old_report / n).read_bytes() for n in ("notes.txt", "runs-7.csv")}
    assert main(["bench", "modes", "--runs", str(runs), "--scenes", "paper", "--out", str(old_report)]) == 0
    assert "wrote 6 files" in capsys.readouterr().out
    assert {n: (old_report / n).read_bytes() for n in keep} == keep
    assert (old_report / "table1-modes.md").read_text() != "# old table\n"
    assert (old_report / "success.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert is_marked(old_report / "ompl", OMPL_MARKER)
    logs = sorted(p.name for p in (old_report / "ompl").iterdir() if p.name != MARKER)
    assert logs == ["table1-paper-3obs.log", "table1-strict-3obs.log"]
    assert "old log" not in (old_report / "ompl" / "table1-paper-3obs.log").read_text()
    assert not [p for p in old_report.rglob(".*") if p.name != MARKER]  # no staged leftovers


def test_table1_refuses_an_output_it_cannot_write_before_any_run(tmp_path, capsys):
    out = tmp_path / "t1"
    (out / "runs.csv").mkdir(parents=True)
    (out / "table1.md").write_text("old\n")
    before = _snapshot(tmp_path)
    rc = main(["bench", "table1", "--out", str(out), "--workers", "0", "--scenarios", "1", "--counts", "1"])
    _one_line(rc, capsys, "--out (runs.csv)", "is a folder")
    assert _snapshot(tmp_path) == before


def test_suite_refuses_outputs_that_are_inputs_or_unwritable(tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    robot = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"
    (out / "suite.md").write_bytes(robot.read_bytes())
    (out / "suite.json").mkdir()
    before = _snapshot(tmp_path)
    rc = main(["bench", "suite", "--scenarios", "1", "--planners", "cspace", "--out", str(out)])
    _one_line(rc, capsys, "--out (suite.json)", "is a folder")
    rc = main(["bench", "suite", "--scenarios", "1", "--robot", str(out / "suite.md"), "--out", str(out)])
    _one_line(rc, capsys, "--out (suite.md)", "is also --robot")
    assert _snapshot(tmp_path) == before


def test_an_interrupted_suite_writes_nothing(tmp_path, capsys, monkeypatch):
    """Ctrl-C during the runs: no scenarios.json, table or results of a half-finished suite."""
    from crtraj.bench import suite

    def interrupted(self, scenarios, on_record=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(suite.SuiteRunner, "run", interrupted)
    out = tmp_path / "s"
    out.mkdir()
    (out / "suite.md").write_text("earlier table\n")
    before = _snapshot(tmp_path)
    assert main(["bench", "suite", "--scenarios", "1", "--planners", "cspace", "--out", str(out)]) == 130
    assert capsys.readouterr().err == "crtraj: interrupted\n"
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------ OutputSet
def test_output_set_writes_nothing_before_commit_and_everything_on_it(tmp_path):
    out = OutputSet()
    out.file(tmp_path / "a" / "x.md", "text\n")
    out.file(tmp_path / "b.bin", b"\x00\x01")
    out.folder(tmp_path / "logs", {"one.log": "1\n", "two.log": b"2\n"}, marker="test-logs")
    assert list(tmp_path.iterdir()) == []
    written = out.commit()
    assert written == [
        tmp_path / "a" / "x.md",
        tmp_path / "b.bin",
        tmp_path / "logs" / "one.log",
        tmp_path / "logs" / "two.log",
    ]
    assert [p.read_bytes() for p in written] == [b"text\n", b"\x00\x01", b"1\n", b"2\n"]
    assert is_marked(tmp_path / "logs", "test-logs")


def test_output_set_refused_folder_leaves_every_file_as_it_was(tmp_path):
    """One target refused (a foreign folder, a folder where a file goes): nothing of the set is written."""
    (tmp_path / "b.bin").write_bytes(b"old")
    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "photo.jpg").write_bytes(b"user")
    before = _snapshot(tmp_path)
    out = OutputSet()
    out.file(tmp_path / "b.bin", b"new")
    out.folder(tmp_path / "logs", {"one.log": "1\n"}, marker="test-logs", replaceable=frozenset({"one.log"}))
    with pytest.raises(InputError, match=r"--out \(logs\): .*photo\.jpg"):
        out.commit()
    assert _snapshot(tmp_path) == before
    (tmp_path / "dir.md").mkdir()
    bad = OutputSet()
    bad.file(tmp_path / "b.bin", b"new")
    bad.file(tmp_path / "dir.md", "x")
    with pytest.raises(InputError, match=r"--out \(dir.md\): .* is a folder"):
        bad.commit()
    assert (tmp_path / "b.bin").read_bytes() == b"old"


def test_output_set_replaces_a_marked_folder_whatever_it_holds(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    mark_folder(logs, "test-logs")
    (logs / "stale.log").write_text("from an older run\n")
    out = OutputSet()
    out.folder(logs, {"one.log": "1\n"}, marker="test-logs")
    out.commit()
    assert sorted(p.name for p in logs.iterdir()) == sorted([MARKER, "one.log"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["logs"]  # the old folder is gone, no leftovers


@pytest.mark.parametrize("content", [b"name,age\nann,3", b"planner,n_obstacles\n", b"\x00\x01binary"])
def test_a_log_crtraj_did_not_write_is_never_appended_to_or_cut(tmp_path, content):
    path = tmp_path / "runs.csv.partial"
    path.write_bytes(content)
    with pytest.raises(InputError, match=r"runs\.csv header"):
        RunLog(path)
    assert path.read_bytes() == content
    (tmp_path / "dir.csv").mkdir()
    with pytest.raises(InputError, match="not a regular file"):
        RunLog(tmp_path / "dir.csv")
