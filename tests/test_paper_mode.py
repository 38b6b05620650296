"""The paper's checking mode (issue 15): collision points at 1-s step ends only, against independent computations.

A configuration that collides only between two step ends passes the paper's
check and fails the strict one; timed so that a step end falls on the
collision, it fails both. Success in the benchmark means D_sf is kept.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import plan_result

from crtraj.app.bench import OMPL_MARKER
from crtraj.bench.check import dense_check, paper_check
from crtraj.bench.modes import rejections, wilson
from crtraj.bench.records import RunRecord
from crtraj.bench.runner import _Task, judge
from crtraj.bench.scenarios import Scenario
from crtraj.core.fileio import MARKER, is_marked
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import CheckOptions, PlannerOptions
from crtraj.planning.validity._motion import MotionValidator
from crtraj.planning.validity._paper_check import PaperValidator, step_end_fractions
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene


def _point_clearance(model, scene, x, t) -> float:
    """Brute force over the 10 collision points: min |p - c(t)| - R(t) - body - D_sf (mm)."""
    p = model.points(np.asarray(x, dtype=float), model.robot.collision_points)
    c, r = scene.states(t)
    return float((np.linalg.norm(p[:, None, :] - c[None], axis=-1) - r[None]).min()) - (
        model.robot.body_radius + scene.safety_distance
    )


@pytest.fixture(scope="module")
def sweep(model):
    """A lateral sweep of the whole robot through a small sphere on its straight axis: the two ends are
    clear, the middle of the motion (the straight robot) collides."""
    xa = model.robot.straight(0.0)
    xa[0] = 0.6  # segment 1 bent 0.6 rad one way ...
    xb = xa.copy()
    xb[0] = -0.6  # ... then the other: half-way the robot is straight
    mid = 0.5 * (xa + xb)
    tip_mid = model.tip_position(mid)
    scene = Scene(obstacles=(Obstacle(center=tuple(tip_mid - [0.0, 0.0, 60.0]), radius=8.0),), safety_distance=5.0)
    # the premises, computed independently of both checks
    assert _point_clearance(model, scene, xa, 0.0) > 5.0 and _point_clearance(model, scene, xb, 0.0) > 5.0
    assert _point_clearance(model, scene, mid, 0.0) < 0.0
    return xa, xb, scene


def test_step_end_fractions_closed_form():
    assert np.allclose(step_end_fractions(0.2, 0.8, 1.0), [1.0])  # no step end inside: only the end
    assert np.allclose(step_end_fractions(0.5, 1.5, 1.0), [0.5, 1.0])  # t = 1 half-way
    assert np.allclose(step_end_fractions(0.0, 3.0, 1.0), [1 / 3, 2 / 3, 1.0])  # t = 3 is the end itself
    assert np.allclose(step_end_fractions(1.0, 1.0, 1.0), [1.0])  # a zero-length motion: its end
    assert np.allclose(step_end_fractions(0.1, 0.6, 0.25), [0.3, 0.8, 1.0])  # t = 0.25, 0.5 of [0.1, 0.6]


def test_a_collision_between_step_ends_passes_the_paper_check_only(model, sweep):
    xa, xb, scene = sweep
    paper = PaperValidator(model, scene, step=1.0, check_points=model.robot.collision_points)
    strict = MotionValidator(model, scene)
    # the sweep within one step (0.2 s -> 0.8 s): the paper looks at the end only
    assert paper.edges_valid(xa[None], xb[None], 0.2, 0.8)[0]
    assert not strict.edges_valid(xa[None], xb[None], 0.2, 0.8)[0]
    # timed so that the step end t = 1 s falls half-way, on the straight robot: the paper sees it
    f, lower = paper.check_edges(xa[None], xb[None], 0.5, 1.5)
    assert f[0] == 0.0  # the first sample (tau = 0.5) fails: nothing before it was checked
    assert lower[0] == pytest.approx(_point_clearance(model, scene, 0.5 * (xa + xb), 1.0), abs=1e-6)
    # a path: the same two timings; the paper check's verdict does not depend on extra waypoints
    for T, ok in (([0.0, 0.2, 0.8, 1.0], True), ([0.0, 0.5, 1.5, 2.0], False)):
        X = np.array([xa, xa, xb, xb])
        assert paper.path_valid(X, np.array(T)) is ok
        fine_T = np.linspace(T[0], T[-1], 41)
        fine_X = np.stack([np.interp(fine_T, T, X[:, j]) for j in range(X.shape[1])], axis=-1)
        assert paper.path_valid(fine_X, fine_T) is ok
        assert not strict.path_valid(X, np.array(T))


def test_bench_paper_check_against_the_dense_check(model, sweep):
    xa, xb, scene = sweep
    goal = model.tip_position(xb)
    between = plan_result(model, [0.0, 0.2, 0.8, 1.0], [xa, xa, xb, xb])
    on_step = plan_result(model, [0.0, 0.5, 1.5, 2.0], [xa, xa, xb, xb])
    pc = paper_check(model, scene, between, goal)
    assert pc.passed and pc.times == 2  # t = 0 and the arrival t = 1
    assert pc.clearance == pytest.approx(min(_point_clearance(model, scene, x, t) for x, t in ((xa, 0), (xb, 1))))
    chk = dense_check(model, scene, between, xa, goal)
    assert not chk.is_success() and chk.min_clearance < 0.0  # the strict check sees the body hit the sphere
    pc = paper_check(model, scene, on_step, goal)
    assert not pc.passed and pc.times == 3
    assert pc.clearance == pytest.approx(_point_clearance(model, scene, 0.5 * (xa + xb), 1.0), abs=1e-6)


def test_paper_option_builds_the_paper_validator_and_relaxes_the_rrt_steer(model):
    from crtraj.planning.planners import RRT

    scene = Scene(obstacles=(Obstacle(center=(80.0, 0.0, 300.0), radius=30.0),))
    v = PlanningContext(model, scene, PlannerOptions(check=CheckOptions(mode="paper", step=0.5))).validator
    assert isinstance(v, PaperValidator) and v.step == 0.5 and v.check_points == model.robot.collision_points
    assert type(PlanningContext(model, scene, PlannerOptions()).validator) is MotionValidator
    paper = RRT(PlanningContext(model, scene, PlannerOptions(check=CheckOptions(mode="paper"))))
    strict = RRT(PlanningContext(model, scene, PlannerOptions()))
    assert paper.steer_options.margin == 0.0 < strict.steer_options.margin
    assert paper.steer_options.n_points == model.robot.collision_points


def _scenario(model, scene, x) -> Scenario:
    tip = model.tip_position(x)
    return Scenario(1, 0, 0, scene, x, tip, tip, x)


def test_success_means_the_body_keeps_dsf(model):
    """A path 2 mm from a sphere: clear of it, but within D_sf = 5 mm -- a failure unless the margin is 0."""
    x = model.robot.straight(0.0)
    pts = model.points(x, 128)
    body = model.robot.body_radius
    # a sphere beside the straight backbone (x = y = 0), its surface 2 mm from the body
    centre = (20.0 + body + 2.0, 0.0, float(pts[64, 2]))
    scene = Scene(obstacles=(Obstacle(center=centre, radius=20.0),), safety_distance=5.0)
    sc = _scenario(model, scene, x)
    res = plan_result(model, [0.0, 1.0], [x, x])
    base = {"planner": "p", "n_obstacles": 1, "index": 0, "seed": 0, "worker": "w"}
    strict = judge(model, sc, res, 0.1, _Task("p", {}, 0, 1.0, 1.0, (128, 0.01, 1.0, None)), base)
    assert strict.claimed and not strict.success
    assert strict.min_clearance_mm == pytest.approx(2.0, abs=0.05)  # surface clearance
    assert strict.dsf_clearance_mm == pytest.approx(-3.0, abs=0.05)  # beyond D_sf
    assert "within 5 mm" in strict.check
    loose = judge(model, sc, res, 0.1, _Task("p", {}, 0, 1.0, 1.0, (128, 0.01, 1.0, 0.0)), base)
    assert loose.success  # merely not touching
    # the sphere sits half-way between two of the paper's 10 collision points (pts[64] is z = 200 mm,
    # the points are 400 / 9 mm apart): the paper check, which sees only those points, passes
    assert strict.paper_success
    assert strict.paper_clearance_mm == pytest.approx(_point_clearance(model, scene, x, 0.0), abs=1e-6)
    assert strict.paper_clearance_mm > 0.0
    # on a collision point instead, the paper check demands D_sf there and fails
    on = Scene(obstacles=(Obstacle(center=(centre[0], 0.0, float(model.points(x)[4, 2])), radius=20.0),))
    rec = judge(model, _scenario(model, on, x), res, 0.1, _Task("p", {}, 0, 1.0, 1.0, (128, 0.01, 1.0, None)), base)
    assert not rec.paper_success and rec.paper_clearance_mm == pytest.approx(-3.0, abs=1e-6)


def _rec(planner: str, paper_ok: bool, ok: bool, clr: float, dsf: float = 5.0) -> RunRecord:
    nan = math.nan
    return RunRecord(
        planner, 3, 0, 0, "exact", True, ok, ok, 1.0, 100.0, clr, 0.0, 1.0, 2, "w", "", "",
        paper_success=paper_ok, dsf_clearance_mm=clr - dsf, paper_clearance_mm=nan,
    )  # fmt: skip


def test_rejections_split_collisions_from_dsf_breaches():
    recs = [
        _rec("rrt-paper", True, True, 9.0),  # safe both ways
        _rec("rrt-paper", True, False, -1.0),  # the body hits a sphere between step ends
        _rec("rrt-paper", True, False, 3.0),  # clear, but within D_sf
        _rec("rrt-paper", False, False, -4.0),  # the paper check failed it too: not counted
    ]
    j = rejections(recs, "rrt-paper", 3)
    assert (j.paper_successes, j.rejected, j.collisions, j.within_dsf) == (3, 2, 1, 1)


def test_wilson_interval_closed_forms():
    z2 = 1.959963984540054**2
    assert wilson(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))  # k = 0: upper end n z^2 / (n (n + z^2))
    lo, hi = wilson(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(10 / (10 + z2))
    lo, hi = wilson(89, 100)
    assert lo < 0.89 < hi and hi - lo == pytest.approx(0.1226, abs=2e-3)


def test_cli_modes_report_writes_tables_figures_and_logs(tmp_path, capsys):
    from crtraj.bench.runlog import RunLog
    from crtraj.cli import main

    log = RunLog(tmp_path / "runs.csv")
    for r in (
        _rec("rrt-paper", True, False, 3.0),
        _rec("rrt", True, True, 9.0),
        RunRecord(
            "rrt-paper", 3, 1, 0, "approximate", False, False, False, 10.0, math.nan, math.nan, 80.0, 5.0, 9, "w",
            "", "", check_mode="paper",
        ),
    ):  # fmt: skip
        log.append(r)
    log.close()
    out = tmp_path / "report"
    assert main(["bench", "modes", "--runs", str(tmp_path / "runs.csv"), "--scenes", "paper", "--out", str(out)]) == 0
    assert "wrote 6 files" in capsys.readouterr().out
    md = (out / "table1-modes.md").read_text()
    # rrt-paper at 3 obstacles: 1 of 2 runs passes the paper's check; the paper's 97 % is outside [9 %, 91 %]
    assert "| RRT (Alg. 1), paper check | 3 | 2 | 50% (9%–91%) |" in md and "| OUT |" in md
    assert "| RRT (Alg. 1), paper check | 3 | 1 | 1 (100%) | 0 | 1 |" in md  # rejected: within D_sf only
    for png in ("success.png", "time_cdf.png", "length.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    logs = sorted(p.name for p in (out / "ompl").iterdir() if p.name != MARKER)
    assert logs == ["table1-paper-3obs.log", "table1-strict-3obs.log"]
    assert is_marked(out / "ompl", OMPL_MARKER)  # crtraj's folder: a later run may replace it as a whole
