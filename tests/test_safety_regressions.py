"""Regressions found in review: coarse validators, streaming failed runs, slowed replays among moving obstacles."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.cli import main
from crtraj.core.fields import Table
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.validity import MotionValidator
from crtraj.world.scene import Scene

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"


@pytest.mark.parametrize("check_points", [2, 3, 5])
def test_coarse_validator_never_passes_a_colliding_body(check_points):
    """With few check points the between-points allowance must still cover the whole arc (dense 200-point check)."""
    prob = Problem.load(PROBLEMS / "paper_static.toml")
    scene = prob.options(Scene, "scene")
    model = Model(prob.robot)
    v = MotionValidator(model, scene, check_points=check_points)
    rng = np.random.default_rng(7)
    X = v.sample(rng, 3000)
    ok = v.state_valid(X, 0.0)
    centers, radii = scene.states(0.0)
    pts = model.points(X[ok], 200)  # (N, 200, 3)
    d = np.linalg.norm(pts[:, :, None, :] - centers[None, None], axis=-1) - radii - prob.robot.body_radius
    assert ok.sum() > 50
    assert d.min() > 0.0, f"a configuration the validator passed has its body {-d.min():.2f} mm inside an obstacle"


def test_replan_refuses_to_stream_a_run_without_safety(tmp_path, capsys):
    rc = main(
        [
            "replan",
            str(PROBLEMS / "paper_dynamic.toml"),
            "--no-safety",
            "--out",
            str(tmp_path / "o"),
            "--stream",
            f"file://{tmp_path / 'f.bin'}",
        ]
    )
    assert rc == 1  # an admission refusal (the library refuses it, before the run)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--stream: refused with --no-safety" in err[0]
    assert not (tmp_path / "f.bin").exists() and not (tmp_path / "o").exists()


def test_stream_refuses_a_slowed_replay_among_moving_obstacles(tmp_path, capsys):
    prob = Problem.load(PROBLEMS / "paper_dynamic.toml")
    scene = prob.options(Scene, "scene")
    assert any(o.amplitude != 0 for o in scene.obstacles)
    model = Model(prob.robot)
    x0, x1 = prob.robot.straight(0.0), prob.robot.straight(10.0)
    wps = [
        {"t": t, "x": list(x), "q": list(model.cables(x)), "tip": list(model.tip_position(x))}
        for t, x in ((0.0, x0), (5.0, x1))
    ]
    res = {"kind": "replan", "robot": prob.robot.to_dict(), "scene": scene.to_dict(), "success": True, "waypoints": wps}
    path = tmp_path / "run.json"
    path.write_text(json.dumps(res))
    rc = main(["stream", str(path), "--dry-run", str(tmp_path / "f.bin"), "--time-scale", "2"])
    assert rc == 1  # refused by admission: a readable result that may not drive a device
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("crtraj: error: --time-scale: 2 refused")
    assert not (tmp_path / "f.bin").exists()
    # the same scene frozen (no breathing, no motion) may be slowed down
    static = Scene.from_table(Table(scene.to_dict(), "scene")).with_obstacles(
        [type(o)(center=o.center, radius=o.radius) for o in scene.obstacles]
    )
    res["scene"] = static.to_dict()
    path.write_text(json.dumps(res))
    argv = [
        "stream",
        str(path),
        "--dry-run",
        str(tmp_path / "g.bin"),
        "--time-scale",
        "2",
        "--log",
        str(tmp_path / "l"),
    ]
    assert main(argv) == 0 and (tmp_path / "g.bin").stat().st_size > 0
