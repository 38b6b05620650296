"""crtraj.viz.timeline: the page's per-waypoint numbers against independent computations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.cli import main
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model
from crtraj.viz.timeline import build_timeline

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"


@pytest.fixture(scope="module")
def plan(tmp_path_factory):
    out = tmp_path_factory.mktemp("plan") / "plan.json"
    assert main(["plan", str(PROBLEMS / "paper_static.toml"), "--out", str(out)]) == 0
    return json.loads(out.read_text())


def test_actuator_fractions_peak_where_the_planner_says(plan):
    """The largest per-step velocity and acceleration fractions equal the plan's summary (computed by the
    planning pipeline from the streamer's set-points); every step has both."""
    run = read_result(plan)
    tl = build_timeline(run, Model(run.robot))
    s = plan["summary"]
    assert np.nanmax(tl.velocity) == pytest.approx(s["max_velocity_fraction"], rel=1e-6)
    assert np.nanmax(tl.acceleration) == pytest.approx(s["max_acceleration_fraction"], rel=1e-6)
    assert np.isfinite(tl.velocity).all() and np.isfinite(tl.acceleration).all()


def test_clearance_is_the_distance_to_the_sphere_less_body_and_d_sf(plan):
    """Per obstacle: min over 2001 backbone points of |p - c| - r - body radius - D_sf, within 0.1 mm."""
    run = read_result(plan)
    model = Model(run.robot)
    tl = build_timeline(run, model)
    k = np.linspace(0, len(run.t) - 1, 7).astype(int)
    P = np.asarray(model.points(run.x[k], 2001)).reshape(len(k), -1, 3)
    d = np.linalg.norm(P[:, :, None] - run.centers[k][:, None], axis=-1).min(axis=1) - run.radii[k]
    expect = d - run.robot.body_radius - run.scene.safety_distance
    np.testing.assert_allclose(tl.clearance[k], expect, atol=0.1)
    assert tl.closest_index == int(np.argmin(tl.clearance.min(axis=1)))
