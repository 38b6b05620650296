"""The planners' building blocks against independent computations: stop conditions, nearest
neighbours, the search tree, the collision bounds of MotionValidator, safe IK, shortcuts and splines."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_planner_helpers import body_motion_bound, dense_path_check, full_speed_times, paper_static

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.planning.ik import SafeIK
from crtraj.planning.options import CheckOptions, CSpaceOptions, IKOptions, PlannerOptions
from crtraj.planning.planners._nn import NearestNeighbors
from crtraj.planning.planners._tree import SearchTree
from crtraj.planning.postprocess import PathPostprocessor, dedup, dedup_timed
from crtraj.planning.stop import StopCondition
from crtraj.planning.validity import MotionValidator
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene


@pytest.fixture(scope="module")
def sim1():
    return paper_static()


@pytest.fixture(scope="module")
def validator(sim1):
    _, model, scene = sim1
    return MotionValidator(model, scene)


# ---------------------------------------------------------------- stop conditions
def test_stop_condition_combines_and_validates():
    a = StopCondition(time_limit=2.0) | StopCondition(max_iterations=10, time_limit=5.0)
    assert a == StopCondition(time_limit=2.0, max_iterations=10, first_solution=False)
    assert (a | StopCondition(first_solution=True)).first_solution
    with pytest.raises(InputError, match="time_limit"):
        StopCondition(time_limit=-1.0)
    with pytest.raises(InputError, match="max_iterations"):
        StopCondition(max_iterations=0)
    with pytest.raises(InputError, match="time_limit or max_iterations"):
        StopCondition(first_solution=True).check_bounded()


def test_stop_clock_reasons():
    clock = StopCondition(max_iterations=3, first_solution=True).start()
    assert not clock.should_stop(False)
    assert clock.should_stop(True) and clock.reason == "first solution"
    clock = StopCondition(max_iterations=3).start()
    for _ in range(3):
        assert not clock.should_stop(False)
        clock.tick()
    assert clock.should_stop(False) and "iteration limit" in clock.reason
    clock = StopCondition(time_limit=1e-12).start()
    while clock.elapsed() <= 1e-12:
        pass
    assert clock.should_stop(False) and "time limit" in clock.reason


# ------------------------------------------------------------- nearest neighbours
@pytest.mark.parametrize("tree_min", [32, 1024])  # KD-tree plus buffer, and the scan alone
def test_nearest_neighbors_match_brute_force(tree_min):
    rng = np.random.default_rng(3)
    nn = NearestNeighbors(5, capacity=16, min_buffer=8, tree_min=tree_min)
    pts = rng.normal(size=(700, 5)) * 100
    for i, p in enumerate(pts):
        assert nn.add(p) == i
        if i % 37 == 0:
            q = rng.normal(size=5) * 100
            d = np.linalg.norm(pts[: i + 1] - q, axis=1)
            j, dist = nn.nearest(q)
            assert dist == pytest.approx(d.min())
            assert d[j] == pytest.approx(d.min())
            np.testing.assert_array_equal(nn.within(q, 80.0), np.flatnonzero(d <= 80.0))
    np.testing.assert_array_equal(nn.points, pts)
    assert (nn.indexed > 0) == (tree_min < len(pts))
    with pytest.raises(IndexError):
        NearestNeighbors(2).nearest(np.zeros(2))


def test_search_tree_paths_and_subtrees():
    tr = SearchTree(2, 3, capacity=2)  # forces growth
    root = tr.add(np.zeros(2), np.zeros(3), 0.0, 0.0, -1)
    a = tr.add(np.ones(2), np.ones(3), 1.0, 1.0, root)
    b = tr.add(2 * np.ones(2), 2 * np.ones(3), 2.0, 2.0, a)
    c = tr.add(np.array([0.0, 3.0]), 3 * np.ones(3), 3.0, 3.0, root)
    np.testing.assert_array_equal(tr.path_to(b), [root, a, b])
    assert set(tr.subtree(a)) == {a, b}
    par, child = tr.edges()
    assert sorted(zip(par.tolist(), child.tolist(), strict=True)) == [(0, 1), (0, 3), (1, 2)]
    tr.set_parent(b, c, 5.0, 4.0)
    np.testing.assert_array_equal(tr.path_to(b), [root, c, b])
    assert tr.nearest(np.array([0.1, 2.9]))[0] == c


# ------------------------------------------------------------------- the validator
def test_motion_bound_bounds_every_backbone_point(sim1, validator):
    _, model, _ = sim1
    rng = np.random.default_rng(0)
    X = validator.sample(rng, 400)
    dX = rng.normal(size=X.shape) * rng.uniform(1e-3, 0.5, (len(X), 1))
    dX[:, -1] *= 80.0
    moved = np.linalg.norm(model.points(X + dX, 120) - model.points(X, 120), axis=-1).max(axis=1)
    bound = validator.motion_bound(dX)
    assert np.all(moved <= bound * (1 + 1e-9))
    assert np.max(moved / bound) > 0.5  # the bound is not wildly loose


def test_clearance_bounds_the_dense_body(sim1, validator):
    _, model, scene = sim1
    X = validator.sample(np.random.default_rng(1), 300)
    P = model.points(X, 800)
    c, r = scene.states(0.0)
    dense = (np.linalg.norm(P[:, :, None] - c, axis=-1) - r).min(axis=(1, 2))
    dense -= model.robot.body_radius + scene.safety_distance
    cons = validator.clearance(X)
    assert np.all(cons <= dense + 1e-9)
    assert np.max(dense - cons) < 2.0 * validator.sagitta + 0.5  # tight up to the sagitta
    np.testing.assert_allclose(validator.points(X[:5]), model.points(X[:5], validator.check_points), atol=1e-9)


def test_clearance_over_a_window_bounds_moving_obstacles(sim1):
    _, model, _ = sim1
    scene = Scene(
        (
            Obstacle(
                (80.0, 0.0, 250.0),
                30.0,
                amplitude=10.0,
                omega=2.0,
                to=(-40.0, 60.0, 300.0),
                duration=3.0,
                profile="cos",
            ),
        )
    )
    v = MotionValidator(model, scene)
    assert not v.static
    X = v.sample(np.random.default_rng(2), 60)
    t_lo, t_hi = 0.7, 2.1
    bound = v.clearance(X, t_lo, t_hi)
    P = model.points(X, 400)
    worst = np.full(len(X), np.inf)
    for t in np.linspace(t_lo, t_hi, 300):
        c, r = scene.states(t)
        d = (np.linalg.norm(P - c[0], axis=-1) - r[0]).min(axis=1)
        worst = np.minimum(worst, d - model.robot.body_radius - scene.safety_distance)
    assert np.all(bound <= worst + 1e-9)


def test_edge_checks_agree_with_an_independent_dense_check(sim1, validator):
    _, model, scene = sim1
    rng = np.random.default_rng(4)
    XA, XB = validator.sample(rng, 120), validator.sample(rng, 120)
    XA = XA[validator.clearance(XA) >= 0][:40]
    XB = XB[validator.clearance(XB) >= 0][:40]
    f, lower = validator.check_edges(XA, XB)
    ok = validator.edges_valid(XA, XB)
    np.testing.assert_array_equal(ok, f >= 1.0)
    assert ok.any() and (~ok).any()
    for a, b, fa, good in zip(XA, XB, f, ok, strict=True):
        clear, _, _ = dense_path_check(model, scene, np.array([0.0, 1.0]), np.stack([a, b]), dt=0.002)
        if good:
            assert clear >= 0.0
        if fa > 0:  # the certified prefix is safe
            clear_p, _, _ = dense_path_check(model, scene, np.array([0.0, 1.0]), np.stack([a, a + fa * (b - a)]), 0.002)
            assert clear_p >= 0.0
    # motions that truly collide are rejected
    assert np.all(lower[ok] >= 0.0)


def test_sampler_covers_the_limits(validator):
    X = validator.sample(np.random.default_rng(5), 2000)
    assert np.all(validator.within_limits(X))
    theta = np.linalg.norm(validator.robot.bending(X), axis=-1)
    assert theta.max() > 0.95 * np.pi
    lo, hi = validator.robot.z_range
    assert X[:, -1].min() < lo + 10 and X[:, -1].max() > hi - 10


def test_validator_rejects_bad_settings(sim1):
    _, model, scene = sim1
    with pytest.raises(InputError, match="check_points"):
        MotionValidator(model, scene, check_points=1)
    with pytest.raises(InputError, match="resolution"):
        MotionValidator(model, scene, resolution=0.0)


# -------------------------------------------------------------------------- safe IK
def test_safe_ik_solutions_are_on_target_within_limits_and_clear(sim1, validator):
    problem, model, scene = sim1
    ik = SafeIK(model, validator, scene.n_obstacles)
    goal = problem.task.goal
    batch = ik.solve(goal, scene.pack(0.0, 2), validator.sample(np.random.default_rng(0), 32), want=32)
    assert len(batch.safe) >= 2
    np.testing.assert_allclose(model.tip_position(batch.safe), np.tile(goal, (len(batch.safe), 1)), atol=1e-3)
    assert np.all(validator.within_limits(batch.safe))
    for x in batch.safe:
        clear, _, _ = dense_path_check(model, scene, np.array([0.0]), x[None])
        assert clear >= 0.0
    # distinct: no two kept solutions within the dedup distance
    d = validator.motion_bound(batch.safe[:, None] - batch.safe[None])
    assert np.all(d[~np.eye(len(d), dtype=bool)] >= 5.0)


def test_safe_ik_nlp_stage_alone(sim1, validator):
    problem, model, scene = sim1
    ik = SafeIK(model, validator, 4)  # more slots than obstacles: padding must be inert
    seeds = validator.sample(np.random.default_rng(1), 6)
    batch = ik.solve(problem.task.goal, scene.pack(0.0, 4), seeds, newton_iterations=0, want=6)
    assert "projection" in batch.statuses and batch.statuses["projection"] == 0
    assert any(s.solver_status == "Solve_Succeeded" for s in batch.solutions)
    assert len(batch.safe) >= 1
    for x in batch.safe:
        assert np.linalg.norm(model.tip_position(x) - problem.task.goal) <= 1e-3
        assert validator.clearance(x[None])[0] >= 0.0


def test_safe_ik_push_out_finds_the_start_the_projection_misses(sim1, validator):
    """Sim 1's start tip sits between the spheres: from these 64 seeds no projection clears them. The push-out
    stage (no NLP allowed) finds safe configurations, each checked here by independent FK and a dense check."""
    problem, model, scene = sim1
    start = problem.task.start
    seeds = validator.sample(np.random.default_rng(5), 64)
    kw = {"want": 1, "max_nlp": 0}
    plain = SafeIK(model, validator, 2, push_rounds=0).solve(start, scene.pack(0.0, 2), seeds, **kw)
    assert len(plain.safe) == 0 and plain.statuses == {"projection": 0}
    ik = SafeIK(model, validator, 2)
    batch = ik.solve(start, scene.pack(0.0, 2), seeds, **kw)
    assert batch.statuses["push-out"] >= 1 and len(batch.safe) >= 1
    pushed = [s for s in batch.solutions if s.solver_status == "push-out"]
    assert len(pushed) == batch.statuses["push-out"]
    for s in pushed:
        assert np.linalg.norm(model.tip_position(s.x) - start) <= 1e-3
        assert validator.within_limits(s.x[None])[0]
        assert s.clearance >= ik.margin - 0.25  # the NLP's required margin on top of the validator's
        clear, _, _ = dense_path_check(model, scene, np.array([0.0]), s.x[None])
        assert clear >= 0.0
    # the same query without the push-out stage needs the NLP: more IPOPT solves, never fewer safe results
    with_nlp = SafeIK(model, validator, 2, push_rounds=0).solve(start, scene.pack(0.0, 2), seeds, want=1, max_nlp=8)
    assert any(k not in ("projection", "push-out") for k in with_nlp.statuses)


def test_push_out_steps_keep_the_tip_and_raise_the_clearance(sim1, validator):
    """One push-out round from on-target configurations too close to a sphere: the tip stays on the target
    (independent FK) and the clearance grows for every configuration that stays on it."""
    problem, model, _ = sim1
    goal = problem.task.goal
    ik = SafeIK(model, validator, 2)
    X, err = ik.project(goal, validator.sample(np.random.default_rng(3), 64), 30)
    c = validator.clearance(X)
    near = (err <= 1e-3) & (c < 0.0) & (c > -30.0)
    assert near.sum() >= 2
    X1, c1 = ik.push_out(
        goal, X[near], required=1.5, rounds=1, validator=validator, t_check=(0.0, 0.0), tol=1e-3, enough=99
    )
    on = np.isfinite(c1)
    assert on.any()
    np.testing.assert_allclose(model.tip_position(X1[on]), np.tile(goal, (on.sum(), 1)), atol=1e-3)
    np.testing.assert_allclose(c1[on], validator.clearance(X1[on]), atol=1e-8)
    assert np.all(c1[on] > c[near][on])
    # a deadline already passed: no round runs, nothing moves
    X0, c0 = ik.push_out(
        goal,
        X[near],
        required=1.5,
        rounds=5,
        validator=validator,
        t_check=(0.0, 0.0),
        tol=1e-3,
        enough=99,
        deadline=0.0,
    )
    np.testing.assert_array_equal(X0, X[near])
    np.testing.assert_allclose(c0, c[near], atol=1e-8)


def test_safe_ik_unreachable_target(sim1, validator):
    _, model, scene = sim1
    ik = SafeIK(model, validator, 2)
    far = np.array([0.0, 0.0, 900.0])  # beyond 400 mm of robot on a base that rises 100 mm
    batch = ik.solve(far, scene.pack(0.0, 2), validator.sample(np.random.default_rng(2), 8), max_nlp=2)
    assert len(batch.safe) == 0
    assert sum(1 for s in batch.solutions if s.solver_status != "projection") == 2
    assert not any(s.safe for s in batch.solutions)


# ----------------------------------------------------------------- post-processing
def _zigzag(validator):
    """A safe, needlessly long path in free space: the straight pose bent back and forth."""
    robot = validator.robot
    base = robot.straight(0.0)
    X = []
    for k, a in enumerate(np.linspace(-0.4, 0.4, 7)):
        x = base.copy()
        x[0] = a
        x[1] = 0.3 * (-1) ** k
        x[-1] = -20.0 + 5 * k
        X.append(x)
    return np.array(X)


def test_shortcut_and_spline_keep_the_path_safe_and_shorter(sim1):
    _, model, _ = sim1
    empty = Scene((Obstacle((400.0, 400.0, 900.0), 1.0),))  # far away
    v = MotionValidator(model, empty)
    X = _zigzag(v)
    post = PathPostprocessor(v, PlannerOptions(shortcut_rounds=6), np.random.default_rng(0), t0=2.0)
    assert post.valid(X)
    short = post.shortcut(X)
    assert np.sum(v.motion_bound(np.diff(short, axis=0))) < np.sum(v.motion_bound(np.diff(X, axis=0)))
    np.testing.assert_array_equal(short[0], X[0])
    np.testing.assert_array_equal(short[-1], X[-1])
    Y = post.spline(X, corner=40.0)
    np.testing.assert_array_equal(Y[0], X[0])
    np.testing.assert_array_equal(Y[-1], X[-1])
    assert np.all(v.within_limits(Y))
    assert np.max(v.motion_bound(np.diff(Y, axis=0))) <= post.o.waypoint_step + 1e-9
    T = post.times(Y)
    assert T[0] == 2.0
    np.testing.assert_allclose(T, full_speed_times(model.robot, Y, v.max_speed, 2.0))
    Z, smoothed = post.smooth(X)
    assert smoothed and post.valid(Z)


def test_smoothing_falls_back_when_the_spline_collides(sim1):
    _, model, _ = sim1
    robot = model.robot
    v0 = MotionValidator(model, Scene((Obstacle((400.0, 400.0, 900.0), 1.0),)))
    # lower the straight robot by 300 mm, then bend it by 1.5 rad: the rounded corner bends while still
    # lowering, so its body passes places the two straight motions never visit
    X = np.stack([robot.straight(100.0), robot.straight(-200.0), robot.straight(-200.0)])
    X[2, 0] = 1.5
    opts = PlannerOptions(corner=150.0)
    Y = PathPostprocessor(v0, opts, np.random.default_rng(0)).spline(X, 150.0)
    poly = model.points(PathPostprocessor(v0, opts, np.random.default_rng(0)).resample(X, 1.0), 60).reshape(-1, 3)
    spl = model.points(Y, 60).reshape(-1, 3)
    gap, _ = cKDTree(poly).query(spl)
    centre = spl[int(np.argmax(gap))]
    # the polyline keeps its sagitta bound, half the finest check spacing and 1 mm beyond D_sf
    radius = float(gap.max()) - robot.body_radius - 5.0 - (v0.sagitta + v0.resolution / 2 + 1.0)
    assert radius > 2.0
    v = MotionValidator(model, Scene((Obstacle(tuple(centre), radius),)))
    post = PathPostprocessor(v, opts, np.random.default_rng(0))
    assert post.valid(X)
    assert not post.valid(Y)
    Z, smoothed = post.smooth(X)
    assert post.valid(Z)
    if not smoothed:  # fell back: the raw path, resampled
        np.testing.assert_allclose(Z, post.resample(X))
    clear, _, _ = dense_path_check(model, v.scene, post.times(Z), Z)
    assert clear >= 0.0


def test_dedup_removes_repeats_only():
    X = np.array([[0.0, 1.0], [0.0, 1.0], [1.0, 1.0], [1.0, 1.0], [0.0, 1.0]])
    np.testing.assert_array_equal(dedup(X), [[0.0, 1.0], [1.0, 1.0], [0.0, 1.0]])


# ------------------------------------------------------------------------- options
def test_planner_options_from_table_and_errors():
    table = {"algorithm": "rrtstar", "time_limit": 2.5, "rrt": {"range": 30.0}, "cspace": {"range": 90.0}}
    o = PlannerOptions.from_table(Table(table, "planner"))
    assert (
        o.algorithm == "rrtstar" and o.time_limit == 2.5 and o.step == 30.0 and o.with_(algorithm="cspace").step == 90.0
    )
    assert PlannerOptions().step == 150.0 and PlannerOptions(algorithm="rrt").step == 40.0
    assert o.stop() == StopCondition(2.5, o.max_iterations, o.first_solution)
    with pytest.raises(InputError, match=r"planner\.algorithm"):
        PlannerOptions.from_table(Table({"algorithm": "prm"}, "planner"))
    with pytest.raises(InputError, match=r"planner\.tim_limit: unknown key"):
        PlannerOptions.from_table(Table({"tim_limit": 1.0}, "planner"))
    with pytest.raises(InputError, match=r"planner\.goal_bias"):
        PlannerOptions(goal_bias=1.5)
    changed = PlannerOptions(cspace=CSpaceOptions(range=12.0), ik=IKOptions(seeds=3), check=CheckOptions(mode="paper"))
    assert PlannerOptions.from_table(Table(changed.to_dict(), "planner")) == changed


# ------------------------------------------------------------ waits and timed paths
def _crossing_scene():
    """A sphere that crosses the straight robot (base at z = 0) during [0, 4] s, then rests 150 mm away."""
    return Scene(
        (Obstacle((150.0, 0.0, 330.0), 40.0, amplitude=10.0, omega=1.0, to=(-150.0, 0.0, 330.0), duration=4.0),)
    )


def test_wait_edges_are_certified_in_time_and_agree_with_a_dense_check(sim1):
    _, model, _ = sim1
    scene = _crossing_scene()
    v = MotionValidator(model, scene, time_resolution=0.25)
    x = model.robot.straight(0.0)  # the sphere passes through the straight body at about t = 2 s
    starts = np.linspace(0.0, 6.0, 13)
    waits = np.array([0.5, 1.0, 2.0, 4.0])
    TA = np.repeat(starts, len(waits))
    TB = TA + np.tile(waits, len(starts))
    X = np.repeat(x[None], len(TA), axis=0)
    ok = v.edges_valid(X, X, TA, TB)
    assert ok.any() and (~ok).any()
    for ta, tb, good in zip(TA, TB, ok, strict=True):
        clear, _, _ = dense_path_check(model, scene, np.array([ta, tb]), np.stack([x, x]), dt=0.005)
        if good:
            assert clear >= 0.0
    # a wait over a window the sphere never comes near is certified even though the window is long
    assert v.edges_valid(x[None], x[None], 10.0, 30.0)[0]
    # the split in time: one coarse swept sphere over [0, 8] s covers the body, the pieces do not
    assert v.clearance(x[None], 0.0, 8.0)[0] < 0.0
    with pytest.raises(InputError, match="time_resolution"):
        MotionValidator(model, scene, time_resolution=0.0)


def test_timed_shortcut_and_spline_keep_times_speed_and_safety(sim1):
    _, model, _ = sim1
    # a moving, breathing sphere beside the motion (the validator checks times)
    scene = Scene(
        (Obstacle((150.0, 260.0, 200.0), 40.0, amplitude=10.0, omega=1.0, to=(-150.0, 260.0, 200.0), duration=4.0),)
    )
    v = MotionValidator(model, scene)
    assert not v.static
    X = _zigzag(v)
    # a timed path with a wait in the middle and one slow motion
    X = np.concatenate([X[:3], X[2:3], X[3:]])
    dur = v.durations(X)
    dur[2] = 0.7  # wait
    dur[4] *= 2.5  # slow
    T = 1.0 + np.concatenate([[0.0], np.cumsum(dur)])
    post = PathPostprocessor(v, PlannerOptions(shortcut_rounds=6), np.random.default_rng(0), t0=1.0)
    assert v.path_valid(X, T)
    S, TS = post.shortcut_timed(X, T)
    assert TS[0] == T[0] and TS[-1] == T[-1]  # shortcuts keep the times of their ends
    np.testing.assert_array_equal(S[0], X[0])
    np.testing.assert_array_equal(S[-1], X[-1])
    assert np.sum(v.motion_bound(np.diff(S, axis=0))) < np.sum(v.motion_bound(np.diff(X, axis=0)))
    assert np.all(body_motion_bound(model.robot, np.diff(S, axis=0)) <= v.max_speed * np.diff(TS) * (1 + 1e-9) + 1e-12)
    assert v.path_valid(S, TS)
    Y, TY, smoothed = post.smooth_timed(X, T)
    assert smoothed or len(Y) >= len(X)
    assert TY[0] == T[0] and TY[-1] == T[-1] and np.all(np.diff(TY) >= 0.0)
    assert np.all(v.within_limits(Y))
    # the spline keeps the polygon's speed bound (up to round-off)
    assert np.all(body_motion_bound(model.robot, np.diff(Y, axis=0)) <= v.max_speed * np.diff(TY) * (1 + 1e-6) + 1e-9)
    assert v.path_valid(Y, TY)
    clear, limit, _ = dense_path_check(model, scene, TY, Y)
    assert clear >= 0.0 and limit <= 1e-9
    # a wait (same configuration, later time) survives timed dedup; an exact repeat does not
    Z, TZ = dedup_timed(np.stack([X[0], X[0], X[0], X[1]]), np.array([0.0, 0.0, 1.0, 2.0]))
    np.testing.assert_array_equal(TZ, [0.0, 1.0, 2.0])
    assert len(Z) == 3


def test_rescue_replaces_the_nlp_with_batched_starts(sim1, validator):
    """Sim 1's start tip sits between the spheres: from these 64 seeds no projection clears them, and without
    the push-out stage the NLP runs. The rescue stage's batched starts around the projections find safe
    configurations instead: no IPOPT solve runs, and each rescued configuration has its tip on the target
    (independent FK), is within limits, keeps the NLP's margin and passes a dense check."""
    problem, model, scene = sim1
    start = problem.task.start
    seeds = validator.sample(np.random.default_rng(5), 64)
    kw = {"want": 2, "max_nlp": 8}
    old = SafeIK(model, validator, 2, push_rounds=0)
    old.solve(start, scene.pack(0.0, 2), seeds, **kw)
    assert old.nlp_solves >= 2
    ik = SafeIK(model, validator, 2, push_rounds=0, rescue_starts=32)
    batch = ik.solve(start, scene.pack(0.0, 2), seeds, **kw)
    assert ik.nlp_solves == 0 and batch.statuses["rescue"] == len(batch.safe) == 2
    rescued = [s for s in batch.solutions if s.solver_status == "rescue"]
    assert len(rescued) == 2
    for s in rescued:
        assert s.safe
        assert np.linalg.norm(model.tip_position(s.x) - start) <= 1e-3
        assert validator.within_limits(s.x[None])[0]
        assert s.clearance >= ik.margin - 0.25
        clear, _, _ = dense_path_check(model, scene, np.array([0.0]), s.x[None])
        assert clear >= 0.0


def test_shortcut_pairs_draw_what_choice_drew():
    """The shortcuts draw their waypoint pairs with `Generator.integers(0, n, dtype=int64)`, which is what
    `Generator.choice(n, size)` computes (half its cost): the same pairs and the same stream after them, so the
    plans of the earlier code are unchanged."""
    for n in (2, 3, 7, 40):
        for seed in range(20):
            a, b = np.random.default_rng(seed), np.random.default_rng(seed)
            x, y = a.choice(n, size=(5, 2)), b.integers(0, n, size=(5, 2), dtype=np.int64)
            np.testing.assert_array_equal(x, y)
            assert x.dtype == y.dtype and a.random() == b.random()
