"""The crtraj command as a user runs it: command list, plan with its standalone view, one-line errors."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from crtraj.cli import build_parser, main

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"


def test_every_documented_command_is_registered():
    """The README's command table and the parser name the same commands."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    readme = (PROBLEMS.parent / "README.md").read_text()
    first_cells = re.findall(r"^\| (`crtraj (?:[^|\\]|\\.)*?) \|", readme, flags=re.M)  # \| is a pipe in a cell
    documented = {m for cell in first_cells for m in re.findall(r"`(?:crtraj )?([a-z0-9-]+)", cell)}
    assert {"plan", "replan", "view", "stream", "sim-device", "feed-replay", "record", "calibrate"} <= documented
    assert set(sub.choices) == documented


def test_plan_writes_result_and_standalone_view(tmp_path, capsys):
    out, html = tmp_path / "plan.json", tmp_path / "plan.html"
    assert main(["plan", str(PROBLEMS / "paper_static.toml"), "--out", str(out), "--html", str(html)]) == 0
    printed = capsys.readouterr().out
    assert "exact" in printed and str(html) in printed
    result = json.loads(out.read_text())
    assert result["kind"] == "plan" and result["success"] is True
    page = html.read_text()
    # a standalone page: meshcat's viewer and the packed scene are inlined, no server needed
    assert "<html" in page.lower() and len(page) > 100_000
    assert len(result["waypoints"]) >= 2


def test_bad_problem_is_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('robot = "robots/none.toml"\n')
    proc = subprocess.run(
        [sys.executable, "-m", "crtraj.cli", "plan", str(bad), "--out", str(tmp_path / "r.json")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "none.toml: no such file" in lines[0]
    assert not (tmp_path / "r.json").exists()
