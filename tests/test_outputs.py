"""Nothing already written is lost (issue 11): staged atomic writes, failed results beside good ones,
output paths checked before the run, dry-run frames never truncating anything, and one exit-code rule
(input errors 2, a well-formed task that cannot be solved 1 with its status)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.run_output import write_run
from crtraj.cli import main
from crtraj.control.loop import ClosedLoop
from crtraj.core import fileio
from crtraj.core.errors import InputError
from crtraj.hardware.protocol import MOVE, read_stream_file
from crtraj.io.problem import Problem
from crtraj.io.run_files import RUN_FILES
from crtraj.model.kinematics import Model
from crtraj.world.scene import Scene

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"
STATIC = PROBLEMS / "paper_static.toml"
DYNAMIC = PROBLEMS / "paper_dynamic.toml"
ROBOT = PROBLEMS / "robots" / "cdsr2.toml"


def _variant(tmp_path: Path, base: Path, name: str, **replace: str) -> Path:
    """A copy of a shipped problem with text replaced (the robot path made absolute)."""
    text = base.read_text().replace('robot = "robots/cdsr2.toml"', f'robot = "{ROBOT}"')
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return p


INSIDE_GOAL = {"goal = [10.0, -120.0, 170.0]": "goal = [0.0, 90.0, 330.0]"}  # inside the upper sphere
INSIDE_START = {"start = [-50.0, 100.0, 390.0]": "start = [0.0, 90.0, 330.0]"}


def _digest(path: Path) -> dict[str, str]:
    """Name -> sha256 of a file, or of every file in a folder."""
    files = sorted(path.iterdir()) if path.is_dir() else [path]
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


def _one_err_line(capsys) -> tuple[str, str]:
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1, cap.err
    return cap.out, lines[0]


def _no_temporaries(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if p.name.startswith(".")]
    assert not left, left


# ------------------------------------------------------------------ fileio
def test_staged_dir_swaps_the_whole_set_and_keeps_foreign_folders(tmp_path):
    names = frozenset({"a", "b"})
    out = tmp_path / "run"
    with fileio.StagedDir(out, names) as st:
        (st.path / "a").write_bytes(b"old a")
        (st.path / "b").write_bytes(b"old b")
        assert not out.exists()  # nothing at the target until the commit
        st.commit()
    with fileio.StagedDir(out, names) as st:
        (st.path / "a").write_bytes(b"new a")
        assert (out / "a").read_bytes() == b"old a"  # the old set stays whole while the new one is written
        st.commit()
    # the new set replaced the old one as a whole: no old file survives next to the new ones
    assert sorted(p.name for p in out.iterdir()) == ["a"] and (out / "a").read_bytes() == b"new a"
    _no_temporaries(tmp_path)
    # an error before the commit leaves the target as it was and no temporary folder
    with pytest.raises(RuntimeError), fileio.StagedDir(out, names) as st:
        (st.path / "a").write_bytes(b"half")
        raise RuntimeError("crash")
    assert (out / "a").read_bytes() == b"new a"
    _no_temporaries(tmp_path)
    # a folder with anything else in it is not an output folder: never replaced
    (out / "mine.txt").write_text("user data")
    with pytest.raises(InputError, match=r"mine\.txt"), fileio.StagedDir(out, names) as st:
        st.commit()
    assert (out / "mine.txt").read_text() == "user data" and (out / "a").read_bytes() == b"new a"


def test_staged_dir_without_atomic_exchange_recovers_an_interrupted_swap(tmp_path, monkeypatch):
    names = frozenset({"a"})
    out = tmp_path / "run"
    out.mkdir()
    (out / "a").write_bytes(b"old")
    monkeypatch.setattr(fileio, "_exchange", lambda a, b: False)

    class Killed(BaseException):
        pass

    def die_at(point: str) -> None:
        if point == "dir-aside":
            raise Killed

    monkeypatch.setattr(fileio, "checkpoint", die_at)
    with pytest.raises(Killed), fileio.StagedDir(out, names) as st:
        (st.path / "a").write_bytes(b"new")
        st.commit()
    # interrupted between the two renames: the old folder is set aside, intact
    assert not out.exists()
    fileio.recover_dir(out)
    assert (out / "a").read_bytes() == b"old"
    # the next write recovers by itself too, then swaps (two renames) as usual
    monkeypatch.setattr(fileio, "checkpoint", lambda point: None)
    os.rename(out, tmp_path / ".run.old-1")
    with fileio.StagedDir(out, names) as st:
        assert (out / "a").read_bytes() == b"old"
        (st.path / "a").write_bytes(b"new")
        st.commit()
    assert (out / "a").read_bytes() == b"new"
    _no_temporaries(tmp_path)


def test_atomic_file_write_failure_keeps_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "r.json"
    target.write_bytes(b"good")

    def boom(point: str) -> None:
        if point == "file-partial":
            raise OSError("disk full")

    monkeypatch.setattr(fileio, "checkpoint", boom)
    with pytest.raises(OSError):
        fileio.atomic_write_bytes(target, b"x" * 1000)
    assert target.read_bytes() == b"good"
    _no_temporaries(tmp_path)


def test_failed_sibling_names():
    assert fileio.failed_sibling("o/p.json") == Path("o/p.failed.json")
    assert fileio.failed_sibling("o/replan") == Path("o/replan.failed")


# -------------------------------------------------------- --out checks
def _unwritable(tmp_path: Path) -> Path:
    """A folder no file can be created in (root ignores permission bits, so use /proc then)."""
    if os.geteuid() == 0:
        return Path("/proc") / "crtraj-no-such-dir"
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    return ro


@pytest.mark.parametrize("command", ["plan", "replan"])
def test_bad_out_is_one_line_before_any_work(tmp_path, capsys, monkeypatch, command):
    def never(*a, **k):
        raise AssertionError("the run started before --out was checked")

    monkeypatch.setattr("crtraj.app.plan.plan_problem", never)
    monkeypatch.setattr(ClosedLoop, "from_problem", never)
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    bad = [afile / "sub" / "r.json", _unwritable(tmp_path) / "r"]
    bad.append(foreign if command == "replan" else tmp_path)  # replan: a non-run folder; plan: a folder
    for out in bad:
        assert main([command, str(STATIC), "--out", str(out)]) == 2, out
        _, err = _one_err_line(capsys)
        assert err.startswith("crtraj: error: --out: ") and str(out) in err, err
    assert afile.read_text() == "keep me" and (foreign / "notes.txt").read_text() == "keep me"
    if command == "plan":  # --html is checked before the run too
        assert main(["plan", str(STATIC), "--out", str(tmp_path / "p.json"), "--html", str(afile / "v.html")]) == 2
        _, err = _one_err_line(capsys)
        assert err.startswith("crtraj: error: --html: ")


# ------------------------------------------------------------------- plan
def test_failed_plan_never_replaces_a_good_one(tmp_path, capsys):
    out, html = tmp_path / "p.json", tmp_path / "p.html"
    assert main(["plan", str(STATIC), "--out", str(out), "--html", str(html)]) == 0
    good = {**_digest(out), **_digest(html)}
    assert json.loads(out.read_text())["success"] is True
    capsys.readouterr()
    inside = _variant(tmp_path, STATIC, "inside", **INSIDE_GOAL)
    # a failed plan exits 1 with its status (not 2 with a message about waypoints), writes no HTML,
    # and its result goes beside the good one, which is kept byte for byte
    assert main(["plan", str(inside), "--out", str(out), "--html", str(html)]) == 1
    text, err = _one_err_line(capsys)
    failed = tmp_path / "p.failed.json"
    assert "invalid_goal" in err and str(failed) in err
    assert f"wrote {failed}" in text and "no HTML written" in text and "waypoints" not in err
    assert {**_digest(out), **_digest(html)} == good
    doc = json.loads(failed.read_text())
    assert doc["status"] == "invalid_goal" and doc["success"] is False and doc["waypoints"] == []
    # a failed result may replace a failed one
    failed.write_text('{"success": false, "status": "timeout"}')
    assert main(["plan", str(inside), "--out", str(out)]) == 1
    assert json.loads(failed.read_text())["status"] == "invalid_goal"
    # asked for, a failed plan replaces the good one
    capsys.readouterr()
    assert main(["plan", str(inside), "--out", str(out), "--overwrite-failed"]) == 1
    assert json.loads(out.read_text())["status"] == "invalid_goal"
    # and with no good result at --out, a failed one is written there
    other = tmp_path / "q.json"
    assert main(["plan", str(inside), "--out", str(other), "--html", str(tmp_path / "q.html")]) == 1
    assert json.loads(other.read_text())["status"] == "invalid_goal"
    assert not (tmp_path / "q.failed.json").exists() and not (tmp_path / "q.html").exists()
    _no_temporaries(tmp_path)


# ---------------------------------------------------------- stream --dry-run
def _result(tmp_path: Path, seconds: float, dz: float) -> Path:
    """A plan result moving the base by dz mm in `seconds` s among the static spheres."""
    prob = Problem.load(STATIC)
    model = Model(prob.robot)
    scene = prob.options(Scene, "scene")
    x0, x1 = prob.robot.straight(-100.0), prob.robot.straight(-100.0 + dz)
    wps = [
        {"t": t, "x": list(x), "q": list(model.cables(x)), "tip": list(model.tip_position(x))}
        for t, x in ((0.0, x0), (seconds, x1))
    ]
    res = {"kind": "plan", "success": True, "robot": prob.robot.to_dict(), "scene": scene.to_dict(), "waypoints": wps}
    p = tmp_path / f"r{seconds:g}.json"
    p.write_text(json.dumps(res))
    return p


def test_dry_run_file_is_replaced_only_by_a_complete_stream(tmp_path, capsys):
    frames = tmp_path / "frames.bin"
    frames.write_bytes(b"previous frames")
    log = ["--log", str(tmp_path / "log.jsonl")]
    # 50 mm of base travel in 10 ms breaks the stage's velocity limit: refused, the file untouched
    fast = _result(tmp_path, 0.01, 50.0)
    assert main(["stream", str(fast), "--dry-run", str(frames), *log]) == 1
    err = capsys.readouterr().err.strip().splitlines()  # refused by admission, as sent: one line
    assert len(err) == 1 and "refused: z velocity" in err[0]
    assert frames.read_bytes() == b"previous frames"
    _no_temporaries(tmp_path)
    # a slow move completes: the file now holds exactly the decodable frames of that stream
    slow = _result(tmp_path, 5.0, 10.0)
    assert main(["stream", str(slow), "--dry-run", str(frames), *log]) == 0
    decoded = read_stream_file(frames.read_bytes())
    moves = [f for f in decoded if f.kind == MOVE]
    assert len(moves) >= 400  # 5 s at 100 Hz
    z = np.array([f.values[-1] for f in moves])
    assert z[0] == pytest.approx(-100.0, abs=1e-6) and z[-1] == pytest.approx(-90.0, abs=1e-6)
    _no_temporaries(tmp_path)


def test_dry_run_onto_the_input_is_refused(tmp_path, capsys):
    res = _result(tmp_path, 5.0, 10.0)
    before = res.read_bytes()
    link = tmp_path / "hard.json"
    os.link(res, link)
    for target in (res, link, tmp_path / "." / res.name):
        assert main(["stream", str(res), "--dry-run", str(target)]) == 2
        _, err = _one_err_line(capsys)
        assert err.startswith("crtraj: error: --dry-run: ") and "is also RESULT" in err
    assert main(["stream", str(res), "--dry-run", str(tmp_path / "f.bin"), "--log", str(res)]) == 2
    _, err = _one_err_line(capsys)
    assert err.startswith("crtraj: error: --log: ")
    assert res.read_bytes() == before and not (tmp_path / "f.bin").exists()


# ----------------------------------------------------------------- replan
@pytest.fixture(scope="module")
def good_run(tmp_path_factory) -> Path:
    """A successful replan run folder of simulation 1 (static spheres)."""
    out = tmp_path_factory.mktemp("good") / "run"
    assert main(["replan", str(STATIC), "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["run.html", "run.json", "run.npz", "run.png"]
    return out


def check_run_folder(folder: Path) -> dict:
    """A complete, self-consistent run folder: run.json and run.npz describe the same run."""
    doc = json.loads((folder / "run.json").read_text())
    with np.load(folder / "run.npz", allow_pickle=False) as z:
        t, x = z["t"], z["x"]
    np.testing.assert_array_equal(t, [w["t"] for w in doc["waypoints"]])
    np.testing.assert_array_equal(x, [w["x"] for w in doc["waypoints"]])
    assert (folder / "run.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if (folder / "run.html").exists():
        assert (folder / "run.html").read_text().rstrip().endswith("</html>")
    return doc


def test_failed_replan_never_replaces_a_good_run(tmp_path, good_run, capsys):
    out = tmp_path / "run"
    shutil.copytree(good_run, out)
    good = _digest(out)
    short = _variant(tmp_path, STATIC, "short", **{"[planner]": "[loop]\nduration = 0.5\n\n[planner]"})
    assert main(["replan", str(short), "--out", str(out), "--quiet", "--no-html"]) == 1
    text, err = _one_err_line(capsys)
    failed = tmp_path / "run.failed"
    assert "timeout" in err and str(failed) in err and str(failed) in text
    assert len(text.strip().splitlines()) == 1  # --quiet: where it went is in the one summary line
    assert _digest(out) == good
    doc = check_run_folder(failed)
    assert doc["status"] == "timeout" and doc["success"] is False
    # a failed run may replace a failed one, and --overwrite-failed lets it replace the good one
    assert main(["replan", str(short), "--out", str(out), "--quiet", "--no-html"]) == 1
    assert check_run_folder(failed)["status"] == "timeout"
    assert main(["replan", str(short), "--out", str(out), "--quiet", "--no-html", "--overwrite-failed"]) == 1
    assert check_run_folder(out)["status"] == "timeout" and not (out / "run.html").exists()
    _no_temporaries(tmp_path)


def test_write_run_replaces_the_folder_as_a_whole(tmp_path, good_run):
    out = tmp_path / "run"
    shutil.copytree(good_run, out)
    (out / "stream.jsonl").write_text("{}\n")  # a file the next run does not write
    problem = Problem.load(_variant(tmp_path, STATIC, "short", **{"[planner]": "[loop]\nduration = 0.3\n\n[planner]"}))

    loop = ClosedLoop.from_problem(problem)
    run = loop.run()
    paths = write_run(run, loop, out, problem=problem, html=False)
    assert sorted(p.name for p in out.iterdir()) == ["run.json", "run.npz", "run.png"]  # no old file left
    assert paths["json"] == out / "run.json" and check_run_folder(out)["status"] == str(run.status)
    _no_temporaries(tmp_path)


# ------------------------------------------------------------ exit codes
def test_start_in_collision_is_exit_1_invalid_start_for_plan_and_replan(tmp_path, capsys):
    bad = _variant(tmp_path, STATIC, "badstart", **INSIDE_START)
    for command in ("plan", "replan"):
        out = tmp_path / command
        assert main([command, str(bad), "--out", str(out)]) == 1, command
        text, err = _one_err_line(capsys)
        assert "invalid_start" in err and "invalid_start" in text, (command, err)
    assert json.loads((tmp_path / "plan").read_text())["status"] == "invalid_start"
    assert not (tmp_path / "replan").exists()  # no run: nothing written


def test_replan_unreachable_goal_fails_fast_with_invalid_goal(tmp_path, capsys, monkeypatch):
    def never(*a, **k):
        raise AssertionError("the loop ran for an unreachable goal")

    monkeypatch.setattr(ClosedLoop, "run", never)
    far = {"goal = [10.0, -120.0, 170.0]": "goal = [0.0, 0.0, 800.0]"}  # 300 mm beyond the robot's reach
    for base in (DYNAMIC, STATIC):
        p = _variant(tmp_path, base, base.stem, **far)
        assert main(["replan", str(p), "--out", str(tmp_path / "o")]) == 1
        text, err = _one_err_line(capsys)
        assert "invalid_goal" in err and "task.goal" in err and "invalid_goal" in text
    # among static spheres a goal inside one can never be reached either
    p = _variant(tmp_path, STATIC, "inside", **INSIDE_GOAL)
    assert main(["replan", str(p), "--out", str(tmp_path / "o")]) == 1
    _, err = _one_err_line(capsys)
    assert "invalid_goal" in err
    assert not (tmp_path / "o").exists()


def test_run_files_lists_what_a_run_writes(good_run):
    assert {p.name for p in good_run.iterdir()} <= RUN_FILES
