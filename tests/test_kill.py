"""SIGKILL while `crtraj plan` / `crtraj replan` write over an existing good result (issue 11).

The writer is paused at a named point by the `crtraj.core.fileio.checkpoint` hook (CRTRAJ_PAUSE_AT): it
creates a signal file there and waits, the test sees the file and kills it. No timers: the only
deadline is a generous guard against a hung child. Afterwards the old result must be byte-identical,
or the new one complete and self-consistent - never a mix, never truncated.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"
STATIC = PROBLEMS / "paper_static.toml"
GUARD_S = 600.0  # only a hung child ever reaches this


def _digest(path: Path) -> dict[str, str]:
    files = sorted(p for p in path.iterdir() if not p.name.startswith(".")) if path.is_dir() else [path]
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


def check_run_folder(folder: Path) -> dict:
    """A complete, self-consistent run folder: run.json and run.npz describe the same run."""
    doc = json.loads((folder / "run.json").read_text())
    with np.load(folder / "run.npz", allow_pickle=False) as z:
        t, x = z["t"], z["x"]
    np.testing.assert_array_equal(t, [w["t"] for w in doc["waypoints"]])
    np.testing.assert_array_equal(x, [w["x"] for w in doc["waypoints"]])
    assert (folder / "run.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (folder / "run.html").read_text().rstrip().endswith("</html>")
    return doc


def _run_and_kill(args: list[str], point: str, tmp_path: Path) -> None:
    """Run the CLI until it reaches `point`, then SIGKILL it."""
    signal_file = tmp_path / f"paused-{point}"
    env = {**os.environ, "CRTRAJ_PAUSE_AT": point, "CRTRAJ_PAUSE_SIGNAL": str(signal_file)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "crtraj.cli", *args],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    guard = time.monotonic() + GUARD_S
    try:
        while not signal_file.exists():  # the event: the writer announced the pause point
            assert proc.poll() is None, f"exited {proc.returncode} before {point}: {proc.stderr.read()[-2000:]!r}"
            assert time.monotonic() < guard, f"never reached {point}"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL


@pytest.fixture(scope="module")
def old_plan(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("oldplan") / "p.json"
    subprocess.run([sys.executable, "-m", "crtraj.cli", "plan", str(STATIC), "--out", str(out)], check=True)
    return out


@pytest.mark.parametrize("point", ["file-partial", "file-written", "file-renamed"])
def test_kill_plan_over_a_good_result(tmp_path, old_plan, point):
    out = tmp_path / "p.json"
    shutil.copy(old_plan, out)
    before = out.read_bytes()
    # another seed gives another (also successful) plan, so old and new differ
    _run_and_kill(["plan", str(STATIC), "--out", str(out), "--seed", "7"], point, tmp_path)
    after = out.read_bytes()
    if point == "file-renamed":  # killed after the rename: the new plan, whole
        doc = json.loads(after)
        assert after != before and doc["success"] is True and doc["problem"]["seed"] == 7
        assert len(doc["waypoints"]) >= 2
    else:
        assert after == before


@pytest.fixture(scope="module")
def old_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("oldrun") / "run"
    subprocess.run(
        [sys.executable, "-m", "crtraj.cli", "replan", str(STATIC), "--out", str(out), "--quiet"], check=True
    )
    return out


@pytest.mark.parametrize("point", ["file-partial", "dir-staged", "dir-swapped"])
def test_kill_replan_over_a_good_run(tmp_path, old_run, point):
    out = tmp_path / "run"
    shutil.copytree(old_run, out)
    before = _digest(out)
    assert set(before) == {"run.json", "run.npz", "run.png", "run.html"}
    # 10 mm further from the upper sphere: another run (other steps), so any mix would show
    text = STATIC.read_text().replace('robot = "robots/cdsr2.toml"', f'robot = "{PROBLEMS / "robots" / "cdsr2.toml"}"')
    problem = tmp_path / "other.toml"
    problem.write_text(text.replace("start = [-50.0, 100.0, 390.0]", "start = [-50.0, 110.0, 400.0]"))
    _run_and_kill(["replan", str(problem), "--out", str(out), "--quiet"], point, tmp_path)
    after = _digest(out)
    if point == "dir-swapped":  # killed after the swap: the new set, whole, none of the old files
        assert set(after) == set(before) and all(after[k] != before[k] for k in before)
        doc = check_run_folder(out)
        assert doc["success"] is True and doc["task"]["start"] == [-50.0, 110.0, 400.0]
    else:
        assert after == before
        check_run_folder(out)
