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


def test_stream_reverifies_a_slowed_replay_among_moving_obstacles(tmp_path, capsys):
    """Issue 13: a slowed replay among breathing spheres is no longer refused outright; its set-points are
    verified at their new times. This one (the straight robot rising 10 mm, far from the spheres' reach)
    stays safe and streams; the same motion with a sphere breathing over the tip at t ~ 7 s is refused
    slowed (it then lasts 10 s) but streams as planned (5 s)."""
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
    argv = ["stream", str(path), "--dry-run", str(tmp_path / "f.bin"), "--log", str(tmp_path / "l"), "--time-scale"]
    assert main([*argv, "2"]) == 0 and (tmp_path / "f.bin").stat().st_size > 0
    capsys.readouterr()
    # a sphere above the tip that swells from 5 to 35 mm radius, largest at t = 7.5 s (period 10 s)
    tip = model.tip_position(x1)
    radius = {"mean": 20.0, "amplitude": 15.0, "omega": 2 * np.pi / 10.0, "phase": -np.pi}
    swell = {"center": [float(tip[0]), float(tip[1]), float(tip[2]) + 40.0], "radius": radius}
    res["scene"] = Scene.from_table(Table({"obstacle": [swell]}, "scene")).to_dict()
    path.write_text(json.dumps(res))
    (tmp_path / "f.bin").unlink()
    assert main([*argv, "2"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "slowed 2 times" in err[0] and "body closer than the safety distance" in err[0]
    assert not (tmp_path / "f.bin").exists()
    assert main([*argv, "1"]) == 0 and (tmp_path / "f.bin").stat().st_size > 0
