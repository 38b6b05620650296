"""Table I bench: scenario generator bounds (property tests), the independent dense check,
the runner (in-process, Dask, CLI) and the OMPL adapter."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import plan_result, require_module
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crtraj.bench.check import _dense_path, dense_check
from crtraj.bench.records import PAPER_TABLE1, BenchOptions, RunRecord
from crtraj.bench.report import BenchReport
from crtraj.bench.runner import Table1Bench, bench_stop
from crtraj.bench.scenarios import Scenario, ScenarioGenerator, ScenarioOptions
from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.planning.context import PlanningContext
from crtraj.planning.ik import SafeIK
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import OMPLPlanner, PlannerSpec, import_ompl
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------- helpers
def _centre_track(ob: Obstacle, n: int = 4001) -> tuple[np.ndarray, np.ndarray]:
    """Times over one full period of the motion (grid through every extreme) and centres there."""
    period = 2.0 * ob.duration if ob.profile == "cos" else 4.0 * ob.duration
    t = np.linspace(0.0, period, n)
    c, _ = Scene(obstacles=(ob,)).states(t)
    return t, c[:, 0, :]


def _body_clearance(model, scene: Scene, x: np.ndarray, t: np.ndarray, n_points: int = 200) -> float:
    """Brute force: min over times, points and obstacles of |p - c| - R - body radius (mm)."""
    p = model.points(x, n_points)  # (n, 3)
    c, r = scene.states(t)  # (T, M, 3), (T, M)
    d = np.linalg.norm(p[None, :, None, :] - c[:, None, :, :], axis=-1) - r[:, None, :]
    return float(d.min()) - model.robot.body_radius


# ----------------------------------------------------------- the generator
@pytest.fixture(scope="module")
def generator(model):
    return ScenarioGenerator(model)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    seed=st.integers(0, 2**31 - 1),
    count=st.sampled_from([1, 3, 5, 7]),
    index=st.integers(0, 99),
)
def test_generator_respects_every_bound_of_the_paper(model, seed, count, index):
    o = ScenarioOptions(seed=seed)
    sc = ScenarioGenerator(model, o).generate(count, index)
    assert sc.scene.n_obstacles == count and sc.n_obstacles == count
    seg = sc.goal - sc.start_tip
    for ob in sc.scene.obstacles:
        # radius A + B sin(t), A in [30, 50], B in [10, 20]: read it back from the states
        tt = np.linspace(0.0, 2.0 * math.pi, 721)
        _, r = Scene(obstacles=(ob,)).states(tt)
        A = 0.5 * (r.max() + r.min())
        B = 0.5 * (r.max() - r.min())
        assert 30.0 - 1e-6 <= A <= 50.0 + 1e-6
        assert 10.0 - 1e-3 <= B <= 20.0 + 1e-6
        np.testing.assert_allclose(r[:, 0], A + B * np.sin(tt), atol=1e-3)
        # linear motion covering 50-100 mm, modulated by sin or cos, mean speed < 15 mm/s
        assert ob.profile in ("sin", "cos")
        t, c = _centre_track(ob)
        d = c - c.mean(axis=0)
        _, sv, vt = np.linalg.svd(d, full_matrices=False)
        assert sv[1] < 1e-6 * max(sv[0], 1.0)  # on a straight line
        proj = d @ vt[0]
        travel = proj.max() - proj.min()
        assert 50.0 - 1e-6 <= travel <= 100.0 + 1e-6
        path = np.linalg.norm(np.diff(c, axis=0), axis=1).sum()
        mean_speed = path / t[-1]
        assert mean_speed < 15.0
        assert mean_speed >= 5.0 - 1e-3
        # the motion is centred near the straight start -> goal tip segment
        mid = 0.5 * (c[np.argmin(proj)] + c[np.argmax(proj)])
        f = float(np.dot(mid - sc.start_tip, seg) / np.dot(seg, seg))
        assert 0.2 - 1e-9 <= f <= 0.8 + 1e-9
        off = np.linalg.norm(mid - (sc.start_tip + f * seg))
        assert off <= ob.radius + 1e-6
    # start and goal: within limits, tips where documented, far enough apart
    robot = model.robot
    assert robot.limit_violation(sc.start)[0] <= 0.0 and robot.limit_violation(sc.goal_config)[0] <= 0.0
    np.testing.assert_allclose(model.tip_position(sc.start), sc.start_tip, atol=1e-9)
    np.testing.assert_allclose(model.tip_position(sc.goal_config), sc.goal, atol=1e-9)
    assert np.linalg.norm(seg) >= o.min_tip_distance
    for p in (sc.start_tip, sc.goal):
        assert np.all(p >= np.array(o.tip_box_lo)) and np.all(p <= np.array(o.tip_box_hi))
    # screens, re-checked by brute force: start body clear over the first step,
    # goal witness clear at t = 0, goal tip clear at all times
    D = sc.scene.safety_distance
    assert _body_clearance(model, sc.scene, sc.start, np.linspace(0.0, 1.0, 41)) >= D - 1e-6
    assert _body_clearance(model, sc.scene, sc.goal_config, np.array([0.0])) >= D - 1e-6
    t_all = np.linspace(0.0, 4.0 * max(ob.duration for ob in sc.scene.obstacles) + 2 * math.pi, 4001)
    c, r = sc.scene.states(t_all)
    gap = np.linalg.norm(c - sc.goal, axis=-1) - r - robot.body_radius - D
    assert gap.min() >= -1e-6


def test_generator_is_deterministic_and_order_independent(model):
    a = ScenarioGenerator(model, ScenarioOptions(seed=11))
    b = ScenarioGenerator(model, ScenarioOptions(seed=11))
    keys = [(c, i) for c in (1, 3) for i in range(3)]
    first = {k: json.dumps(a.generate(*k).to_dict()) for k in keys}
    # b draws the same scenarios in reverse order: each depends only on (seed, count, index)
    second = {k: json.dumps(b.generate(*k).to_dict()) for k in reversed(keys)}
    assert first == second
    assert len(set(first.values())) == len(keys)
    other = ScenarioGenerator(model, ScenarioOptions(seed=12)).generate(1, 0).to_dict()
    assert json.dumps(other) != first[(1, 0)]


def test_scenario_round_trip(generator):
    sc = generator.generate(3, 4)
    back = Scenario.from_dict(json.loads(json.dumps(sc.to_dict())))
    assert back.to_dict() == sc.to_dict()
    t = np.linspace(0.0, 20.0, 50)
    for x, y in zip(sc.scene.states(t), back.scene.states(t), strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"radius_mean": (50.0, 30.0)}, "radius_mean"),
        ({"radius_amplitude": (10.0, 40.0)}, "radius_amplitude"),
        ({"mean_speed": (0.0, 15.0)}, "mean_speed"),
        ({"travel": (-1.0, 100.0)}, "travel"),
        ({"fraction": (0.2, 1.5)}, "fraction"),
        ({"seed": -1}, "seed"),
        ({"tip_box_lo": (0.0, 0.0, 500.0)}, "tip_box"),
    ],
)
def test_generator_options_reject_bad_values(kwargs, field):
    with pytest.raises(InputError, match=field):
        ScenarioOptions(**kwargs)


# -------------------------------------------------------------- dense check
def test_dense_check_clearance_and_length_match_closed_forms(model):
    """Straight robot on the z axis, sphere beside it: clearance is |offset| - R - body radius."""
    ob = Obstacle(center=(50.0, 0.0, 200.0), radius=20.0)
    scene = Scene(obstacles=(ob,))
    x0 = model.robot.straight(-100.0)
    x1 = model.robot.straight(0.0)
    res = plan_result(model, [0.0, 4.0], [x0, x1])
    chk = dense_check(model, scene, res, x0, model.tip_position(x1), n_points=129)
    assert chk.is_success(), chk.reason
    assert chk.min_clearance == pytest.approx(50.0 - 20.0 - model.robot.body_radius, abs=1e-9)
    assert chk.length == pytest.approx(100.0, abs=1e-9)  # the tip rises 100 mm
    assert chk.goal_error == pytest.approx(0.0, abs=1e-9)


def test_dense_check_catches_a_collision_between_waypoints(model):
    """Both waypoints are clear; the straight motion between them sweeps the body through a sphere."""
    scene = Scene(obstacles=(Obstacle(center=(0.0, 0.0, 450.0), radius=20.0),))
    xa = model.robot.straight(-200.0)  # tip at z = 200
    xb = model.robot.straight(100.0)  # tip at z = 500: the body passes z = 450
    # both ends held: the end configuration itself collides too, so put the sphere only mid-way in time
    moving = Scene(
        obstacles=(
            Obstacle(center=(0.0, 0.0, 300.0), radius=20.0, to=(300.0, 0.0, 300.0), duration=10.0, profile="cos"),
        )
    )
    res = plan_result(model, [0.0, 1.0], [xa, xb])
    chk = dense_check(model, scene, res, xa, model.tip_position(xb))
    assert not chk.is_success() and "collides" in chk.reason
    # the moving sphere sits on the axis at z = 300 at t = 0 and leaves it: a slow motion is clear,
    # yet with a fast one the robot reaches z = 300 while the sphere is still there
    slow = plan_result(model, [0.0, 1.0, 11.0], [xa, xa, xb])
    assert dense_check(model, moving, slow, xa, model.tip_position(xb)).is_success()
    fast = plan_result(model, [0.0, 1.0], [xa, xb])
    chk = dense_check(model, moving, fast, xa, model.tip_position(xb))
    assert not chk.is_success() and "collides" in chk.reason and chk.t_worst <= 1.0


def test_dense_samples_keep_every_backbone_point_within_the_step(model):
    """A fast, large bend: consecutive dense samples move no backbone point more than `step` mm."""
    xa = model.robot.straight(0.0)
    xb = xa.copy()
    xb[:4] = [1.2, -0.4, 0.3, 1.0]
    times, configs, pts = _dense_path(model, np.array([0.0, 0.5]), np.stack([xa, xb]), 64, 0.01, 1.0)
    assert times[0] == 0.0 and times[-1] == 0.5 and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(configs[[0, -1]], np.stack([xa, xb]))
    np.testing.assert_allclose(pts, model.points(configs, 64))
    move = np.linalg.norm(np.diff(pts, axis=0), axis=-1).max()
    assert move <= 1.0 + 1e-9
    assert len(times) > 51  # far more than the time step alone asks for


def test_dense_check_rejects_malformed_paths(model):
    scene = Scene()
    xa = model.robot.straight(-100.0)
    xb = model.robot.straight(0.0)
    goal = model.tip_position(xb)
    assert "start configuration" in dense_check(model, scene, plan_result(model, [0, 1], [xb, xb]), xa, goal).reason
    assert "decrease" in dense_check(model, scene, plan_result(model, [1, 0], [xa, xb]), xa, goal).reason
    assert "from the goal" in dense_check(model, scene, plan_result(model, [0, 1], [xa, xa]), xa, goal).reason
    bent = xb.copy()
    bent[0] = 4.0  # theta far above pi: out of limits
    assert "limits" in dense_check(model, scene, plan_result(model, [0, 1], [xa, bent]), xa, goal).reason
    assert dense_check(model, scene, plan_result(model, [0, 1], [xa, xb]), xa, goal).is_success()


# ------------------------------------------------------------ fake planners
class StraightToGoal:
    """Claims an exact solution: the straight motion from the start to a goal configuration (safe IK in
    an empty scene, so it ignores obstacles) at 20 mm/s of tip. A `Planner` like crtraj's own."""

    name = "straight"

    def __init__(self, model):
        self.model = model
        self.v = MotionValidator(model, Scene())
        self.ik = SafeIK(model, self.v, 1)

    def goal_config(self, goal, x0, seed):
        seeds = np.concatenate([x0[None], self.v.sample(np.random.default_rng(seed), 15)])
        batch = self.ik.solve(goal, Scene().pack(0.0, 1), seeds, want=1, validator=self.v, tip_tolerance=1e-4)
        return batch.safe[0]

    def plan(self, goal, *, start_config=None, start_tip=None, t0=0.0, stop=None, seed=None, scene=None, **kw):
        x0 = np.asarray(start_config, dtype=float)
        d = np.linalg.norm(goal - self.model.tip_position(x0))
        return plan_result(self.model, [t0, t0 + d / 20.0], [x0, self.goal_config(goal, x0, seed)])


class Collider(StraightToGoal):
    """Claims an exact solution through a configuration whose body is inside an obstacle at t = 1 s."""

    name = "collider"

    def plan(self, goal, *, start_config=None, start_tip=None, t0=0.0, stop=None, seed=None, scene=None, **kw):
        if scene.n_obstacles == 0:  # nothing to hit: behave honestly
            return super().plan(goal, start_config=start_config, seed=seed, scene=scene)
        X = self.v.sample(np.random.default_rng(seed), 3000)
        P = self.model.points(X, 64)
        c, r = scene.states(1.0)
        depth = (np.linalg.norm(P[:, :, None, :] - c[None, None], axis=-1) - r).min(axis=(1, 2))
        x_bad = X[int(np.argmin(depth))]
        assert depth.min() < -5.0
        x0 = np.asarray(start_config, dtype=float)
        return plan_result(self.model, [0.0, 1.0, 2.0], [x0, x_bad, self.goal_config(goal, x0, seed)])


def _straight(context):
    return StraightToGoal(context.model)


def _collider(context):
    return Collider(context.model)


FAKES = (PlannerSpec("straight", _straight), PlannerSpec("collider", _collider))


def test_a_claimed_success_that_collides_counts_as_a_failure(robot):
    bench = Table1Bench(
        robot,
        BenchOptions(counts=(0, 3), scenarios=3, planners=("straight", "collider"), time_limit=1.0, seed=5),
        extra_planners=FAKES,
    )
    report = bench.run(None, progress=False)
    assert len(report.records) == 2 * 3 * 2
    for r in report.records:
        assert isinstance(r, RunRecord)
        if r.planner == "collider" and r.n_obstacles > 0:
            assert r.claimed and not r.verified and not r.success
            assert "collides" in r.check
            assert r.min_clearance_mm < 0
            assert r.length_mm > 0  # measured on the rejected path too (the paper mode's lengths need it)
        elif r.n_obstacles == 0:  # nothing to hit: the straight motion is a verified success
            assert r.claimed and r.verified and r.success
            assert r.length_mm > 0
    assert report.stats("collider", 3)["success"] == 0.0
    assert report.stats("collider", 3)["rejected"] == 3
    assert report.stats("straight", 0)["success"] == 1.0


def test_report_files_follow_the_paper_layout(robot, tmp_path):
    bench = Table1Bench(
        robot,
        BenchOptions(counts=(1, 3), scenarios=2, planners=("straight",), time_limit=1.0),
        extra_planners=FAKES,
    )
    report = bench.run(None, progress=False)
    files = report.write(tmp_path)
    assert {f.name for f in files} == {"table1.md", "runs.csv", "scenarios.json"}
    rows = list(csv.DictReader((tmp_path / "runs.csv").open()))
    assert len(rows) == 4 and set(rows[0]) == set(RunRecord.fields())
    # the CSV's success column is the conjunction of the claim and the dense check
    for row in rows:
        assert (row["success"] == "True") == (row["claimed"] == "True" and row["verified"] == "True")
    saved = json.loads((tmp_path / "scenarios.json").read_text())
    assert len(saved["scenarios"]) == 4
    assert Scenario.from_dict(saved["scenarios"][0]).to_dict() == report.scenarios[0].to_dict()
    md = (tmp_path / "table1.md").read_text()
    assert "| 1 obs: time (s) | 1 obs: succ | 3 obs: time (s) | 3 obs: succ |" in md
    assert "Average path length" in md


def test_markdown_puts_the_papers_numbers_beside_ours(robot):
    bench = Table1Bench(robot, BenchOptions(scenarios=1, planners=("straight",)), extra_planners=FAKES)
    opts = BenchOptions(counts=(1, 3, 5, 7), scenarios=1, planners=("rrtstar",))
    rep = BenchReport(opts, bench.scenario_options, PlannerOptions(), [], [], 0.0, "none", 1)
    md = rep.markdown()
    paper = PAPER_TABLE1["rrtstar"]
    row = next(line for line in md.splitlines() if line.startswith("| RRT* (Alg. 1) — paper | 3.66"))
    assert row.count("|") == 1 + 1 + 2 * 4
    for t, s in zip(paper["time_s"], paper["success"], strict=True):
        assert f"{t:.2f} | {100 * s:.0f}%" in row
    assert "| RRT* (Alg. 1) — paper | 609.07 | 626.70 | 625.46 | 597.45 |" in md


def test_bench_options_reject_bad_values(robot):
    with pytest.raises(InputError, match="counts"):
        BenchOptions(counts=(1, 1))
    with pytest.raises(InputError, match="time_limit"):
        BenchOptions(time_limit=0.0)
    with pytest.raises(InputError, match="unknown planner 'nope'"):
        Table1Bench(robot, BenchOptions(planners=("nope",)))


def test_cli_reports_bad_arguments_in_one_line(capsys, tmp_path):
    assert main(["bench", "table1", "--counts", "1,x", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("crtraj: error: --counts") and "\n" not in err
    assert main(["bench", "table1", "--planners", "cspace,bogus", "--out", str(tmp_path)]) == 2
    assert "bogus" in capsys.readouterr().err


# ----------------------------------------------------------------- executors
def test_dask_local_cluster_runs_the_bench(robot):
    distributed = require_module("distributed", hint="pip install -e '.[bench]'")
    with (
        distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        distributed.Client(cluster) as client,
    ):
        bench = Table1Bench(
            robot,
            BenchOptions(counts=(0, 1), scenarios=2, planners=("straight", "collider"), time_limit=1.0),
            extra_planners=FAKES,
        )
        report = bench.run(client.get_executor(), workers=1, progress=False)
    assert len(report.records) == 8
    assert all(r.worker for r in report.records)
    assert report.stats("collider", 1)["rejected"] == 2
    assert report.stats("collider", 0)["success"] == 1.0
    # the same runs in this process give the same verdicts (the scenarios are seeded)
    local = bench.run(None, progress=False)
    key = lambda r: (r.planner, r.n_obstacles, r.index)  # noqa: E731
    assert [(key(r), r.is_success(), r.check) for r in sorted(report.records, key=key)] == [
        (key(r), r.is_success(), r.check) for r in sorted(local.records, key=key)
    ]


# ------------------------------------------------------------------- OMPL
def test_ompl_missing_gives_an_install_hint(monkeypatch):
    monkeypatch.setitem(sys.modules, "ompl", None)
    with pytest.raises(InputError, match="pip install"):
        import_ompl()


def test_ompl_plans_in_space_time_and_passes_the_dense_check(model, generator):
    require_module("ompl", hint="pip install -e '.[bench]'")
    sc = generator.generate(1, 1)
    planner = OMPLPlanner(PlanningContext(model), algorithm="RRTConnect")
    # a generous budget: RRTConnect stops at its first solution, the limit only bounds a failure
    res = planner.plan(sc.goal, start_config=sc.start, scene=sc.scene, stop=StopCondition(time_limit=30.0), seed=3)
    assert res.is_success(), res.message  # one sphere beside the way: solvable
    assert np.all(np.diff(res.t) >= 0)  # time runs forward along the path
    np.testing.assert_allclose(res.configs[0], sc.start)
    chk = dense_check(model, sc.scene, res, sc.start, sc.goal)
    assert chk.is_success(), chk.reason
    assert res.goal_error <= 1.0
    with pytest.raises(InputError, match="time_limit"):
        planner.plan(sc.goal, start_config=sc.start, scene=sc.scene, stop=StopCondition(max_iterations=10))
    # a start tip resolved by safe IK, a spent budget and a blocked start: every registered planner's contract
    # (test_planner_contract.py)
    with pytest.raises(InputError, match="start"):
        planner.plan(sc.goal, scene=sc.scene, stop=StopCondition(time_limit=1.0))


def test_bench_calls_every_builtin_planner_through_the_registry(robot):
    """The bench has no adapters: each built-in name builds a `Planner` whose stop matches its registry entry."""
    bench = Table1Bench(robot, BenchOptions(scenarios=1, planners=("cspace",)))
    reg = bench.spec.registry
    assert reg.names[:5] == ("rrt", "rrtstar", "cspace", "ompl-rrtstar", "ompl-rrtconnect")
    o = bench.planner_options
    assert bench_stop(reg.spec("cspace"), o, 2.0) == StopCondition(2.0, o.max_iterations, o.first_solution)
    assert bench_stop(reg.spec("ompl-rrtstar"), o, 2.0) == StopCondition(time_limit=2.0)


@pytest.mark.slow
def test_cli_two_scenario_run_of_every_planner(tmp_path, capsys):
    out = tmp_path / "t1"
    code = main(
        [
            "bench",
            "table1",
            "--scenarios",
            "2",
            "--counts",
            "1,3",
            "--time-limit",
            "1",
            "--workers",
            "2",
            "--no-progress",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "wrote" in printed
    rows = list(csv.DictReader((out / "runs.csv").open()))
    assert len(rows) == 2 * 2 * 5
    assert {r["planner"] for r in rows} == {"rrt", "rrtstar", "cspace", "ompl-rrtstar", "ompl-rrtconnect"}
    assert all(r["status"] != "error" for r in rows), [r["message"] for r in rows if r["status"] == "error"]
    md = (out / "table1.md").read_text()
    for label in ("RRT (Alg. 1) — paper", "RRT* (Alg. 1) — crtraj", "C-space (default)", "OMPL RRTstar"):
        assert label in md


def test_cli_dask_address_runs_on_the_cluster(tmp_path, capsys):
    distributed = require_module("distributed", hint="pip install -e '.[bench]'")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl:
        out = tmp_path / "dask"
        code = main(
            [
                "bench",
                "table1",
                "--dask",
                cl.scheduler_address,
                "--scenarios",
                "1",
                "--counts",
                "1",
                "--planners",
                "cspace",
                "--time-limit",
                "3",
                "--no-progress",
                "--out",
                str(out),
            ]
        )
    assert code == 0
    assert "Dask at" in capsys.readouterr().out
    rows = list(csv.DictReader((out / "runs.csv").open()))
    assert len(rows) == 1 and rows[0]["planner"] == "cspace" and rows[0]["status"] != "error"
    assert "ClientExecutor" in (out / "table1.md").read_text()


def test_cli_dask_unreachable_is_one_line(capsys, tmp_path):
    code = main(["bench", "table1", "--dask", "tcp://127.0.0.1:9", "--planners", "cspace", "--out", str(tmp_path)])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("crtraj: error: --dask") and "\n" not in err
