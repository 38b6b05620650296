"""`crtraj replan` end to end on the paper's simulation 2 (problems/paper_dynamic.toml)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from crtraj.cli import main
from crtraj.problem import Problem
from crtraj.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PAPER = ROOT / "problems" / "paper_dynamic.toml"


def _clearance_from_waypoints(res: dict) -> np.ndarray:
    """Clearance (mm, minus D_sf) of each recorded backbone, from the file alone (obstacle states included)."""
    out = []
    body = res["robot"]["body_radius"]
    dsf = res["scene"]["safety_distance"]
    for w in res["waypoints"]:
        P = np.array(w["backbone"])
        C = np.array(w["obstacles"]["centers"])
        R = np.array(w["obstacles"]["radii"])
        d = np.linalg.norm(P[:, None, :] - C[None], axis=-1).min(axis=0) - R
        out.append(d.min() - body - dsf)
    return np.array(out)


def test_paper_simulation_2_reaches_the_goal_without_collision(tmp_path, capsys):
    out = tmp_path / "replan"
    assert main(["replan", str(PAPER), "--out", str(out), "--no-html"]) == 0
    text = capsys.readouterr().out
    assert "reached goal yes" in text and "collisions 0" in text
    res = json.loads((out / "run.json").read_text())
    assert res["kind"] == "replan" and res["status"] == "reached" and res["success"]
    s = res["summary"]
    assert s["collisions"] == 0 and s["safety_violations"] == 0
    assert s["final_tip_error_mm"] <= 0.5
    assert _clearance_from_waypoints(res).min() > 0.0
    # the obstacle states in the file are the scene's
    scene = Scene.from_table(Problem.load(PAPER).section("scene"))
    w = res["waypoints"][-1]
    _, R = scene.states(w["t"])
    np.testing.assert_allclose(w["obstacles"]["radii"], R)
    for name in ("run.json", "run.npz", "run.png"):
        assert (out / name).stat().st_size > 0


def test_paper_simulation_2_without_safety_collides(tmp_path, capsys):
    out = tmp_path / "nosafe"
    assert main(["replan", str(PAPER), "--out", str(out), "--no-safety", "--no-html", "--quiet"]) == 0
    res = json.loads((out / "run.json").read_text())
    s = res["summary"]
    assert not res["success"]
    assert s["min_clearance_mm"] < 0.0 and s["collisions"] > 0
    assert _clearance_from_waypoints(res).min() < 0.0


def test_bad_problem_is_one_line_error(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    text = PAPER.read_text().replace(
        'robot = "robots/cdsr2.toml"', f'robot = "{PAPER.parent / "robots" / "cdsr2.toml"}"'
    )
    bad.write_text(text.replace("horizon = 10", "horizon = 0"))
    assert main(["replan", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "replan.horizon" in err[0]
