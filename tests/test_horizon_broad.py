"""The horizon's broad phase (crtraj.control.horizon._broad): its gap is a lower bound of every obstacle row of
every plan within reach, so it never leaves out an obstacle the narrow phase (the NLP's rows) would find; and a
QP with fewer slots than the scene's obstacles plans what the full one plans."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.control.horizon._broad import ROW_TOLERANCE, BroadPhase, Selection, step_reach
from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.horizon._replanner import Replanner
from crtraj.control.loop import ClosedLoop, LoopOptions, RunStatus
from crtraj.planning.metric import BodyMetric
from crtraj.world import packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
OPTS = ReplanOptions(horizon=6, points=12, solver="sqp")
SLOTS = 8


@pytest.fixture(scope="module")
def full(model) -> Replanner:
    """A replanner whose QP has a slot for every obstacle of the scenes below (the narrow phase's rows)."""
    return Replanner(model, OPTS, max_obstacles=SLOTS, safety_distance=5.0)


def _reachable(rng: np.random.Generator, rp: Replanner, x0: np.ndarray) -> np.ndarray:
    """A plan x_1..x_N (N nx,) whose every step keeps |A dx| within the step limit, many steps at the limit."""
    xs, x = [], x0
    for _ in range(rp.N):
        d = rng.normal(size=rp.nx)
        scale = np.max(np.abs(rp.model.robot.cable_matrix()[0] @ d) / rp.step_limit)
        x = x + d / scale * (1.0 if rng.random() < 0.5 else rng.random())
        xs.append(x)
    return np.concatenate(xs)


def _scene_near(rng: np.random.Generator, model, x0: np.ndarray, m: int) -> Scene:
    """m spheres around points of the body at x0, from touching it to 120 mm away, some breathing, some drifting."""
    P = model.points(x0, 20)
    obs = []
    for i in range(m):
        c = P[rng.integers(len(P))] + rng.normal(0.0, 1.0, 3) / np.sqrt(3) * rng.uniform(0.0, 120.0)
        obs.append(
            Obstacle(
                center=tuple(c),
                radius=rng.uniform(5.0, 30.0),
                amplitude=rng.uniform(0.0, 4.0),
                omega=rng.uniform(0.1, 2.0),
                to=tuple(c + rng.normal(0.0, 20.0, 3)),
                duration=rng.uniform(1.0, 5.0),
                name=f"o{i}",
            )
        )
    return Scene(obstacles=tuple(obs), safety_distance=5.0)


def test_step_reach_bounds_the_body_motion_of_every_step_within_the_limits(model, full):
    """No change dx with |A dx| <= step_limit moves the body (`BodyMetric.motion_bound`) more than step_reach."""
    rng = np.random.default_rng(3)
    reach = step_reach(model, full.step_limit)
    bound = BodyMetric(model.robot, 50.0).motion_bound
    A = model.robot.cable_matrix()[0]
    worst = 0.0
    for _ in range(2000):
        d = rng.normal(size=full.nx) * rng.uniform(0.0, 3.0, full.nx)
        d /= np.max(np.abs(A @ d) / full.step_limit)
        worst = max(worst, float(bound(d)))
    assert 0.5 * reach < worst <= reach


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(1, SLOTS), t0=st.floats(0.0, 20.0))
def test_the_gap_bounds_every_row_of_every_plan_within_reach(model, full, seed, m, t0):
    """For random scenes, start configurations and reachable plans, every obstacle row of the full NLP (the
    narrow phase, at the plan's configurations) is at least the obstacle's gap; hence an obstacle that some
    plan comes within its sphere of is always selected."""
    rng = np.random.default_rng(seed)
    x0 = XS + rng.normal(0.0, [0.3, 0.3, 0.3, 0.3, 20.0])
    scene = _scene_near(rng, model, x0, m)
    O = full.obstacles_from_scene(scene, t0)  # every obstacle in its own slot (no broad phase without x0)
    c, rho, _ = packing.unpack(O)
    gaps = full.broad.gaps(x0, c[:, :m], rho[:, :m])
    idx, relevant = full.broad.select(x0, c[:, :m], rho[:, :m], SLOTS)
    assert relevant == len(idx) == int(np.sum(gaps <= 0.0))
    for _ in range(5):
        rows = full.distances(_reachable(rng, full, x0), O)[:, :m]  # (N, m, points)
        nearest = rows.min(axis=(0, 2))
        assert np.all(nearest >= gaps - 1e-6), (nearest, gaps)
        assert set(np.flatnonzero(nearest <= 0.0)) <= set(idx)


def test_the_gap_is_the_numpy_lower_bound(model, full):
    """gap_i = min over steps k and points j of |p_j(x0) - c_ik| - rho_ik - k reach, computed independently."""
    rng = np.random.default_rng(7)
    x0 = XS + 0.2 * (XG - XS)
    scene = _scene_near(rng, model, x0, 5)
    c, rho, _ = packing.unpack(full.obstacles_from_scene(scene, 1.3))
    P = model.points(x0, OPTS.points)
    reach = step_reach(model, full.step_limit)
    expect = [
        min(np.linalg.norm(P - c[k, i], axis=1).min() - rho[k, i] - (k + 1) * reach for k in range(full.N))
        for i in range(5)
    ]
    np.testing.assert_allclose(
        BroadPhase(model, OPTS.points, full.step_limit, full.N).gaps(x0, c[:, :5], rho[:, :5]), expect
    )


def test_more_obstacles_than_slots_keep_the_nearest_and_are_counted(model, full):
    """select: when more obstacles can matter than there are slots, the ones with the smallest gaps."""
    rng = np.random.default_rng(11)
    x0 = XS.copy()
    scene = _scene_near(rng, model, x0, SLOTS)
    c, rho, _ = packing.unpack(full.obstacles_from_scene(scene, 0.0))
    gaps = full.broad.gaps(x0, c, rho)
    idx, relevant = full.broad.select(x0, c, rho, 2)
    assert len(idx) == 2 and relevant == int(np.sum(gaps <= 0.0)) > 2
    assert set(idx) == set(np.argsort(gaps)[:2]) and list(idx) == sorted(idx)


def _far_scene(model) -> Scene:
    """One breathing ball in the robot's way and eleven spheres beyond anything the horizon can reach (this
    robot's bending can move a body point hundreds of mm per step)."""
    ball = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=0.5, phase=-0.43, name="ball")
    far = tuple(
        Obstacle(center=(5000.0 * np.cos(a), 5000.0 * np.sin(a), 300.0), radius=20.0, name=f"far{i}")
        for i, a in enumerate(np.linspace(0.0, 2 * np.pi, 11, endpoint=False))
    )
    return Scene(obstacles=(*far[:5], ball, *far[5:]), safety_distance=5.0)


def test_a_qp_with_fewer_slots_plans_what_the_full_qp_plans(model):
    """A replanner with 2 slots, fed by the broad phase, solves a 12-obstacle scene to the plan of one with 12."""
    scene = _far_scene(model)
    small = Replanner(model, OPTS, max_obstacles=2, safety_distance=5.0)
    big = Replanner(model, OPTS, max_obstacles=12, safety_distance=5.0)
    x0 = XS + 0.25 * (XG - XS)
    ref = x0 + np.clip(0.12 * np.arange(1, OPTS.horizon + 1), 0, 1)[:, None] * (XG - x0)
    Os = small.obstacles_from_scene(scene, 0.5, x0)
    c, _, active = packing.unpack(Os)
    assert active[0].tolist() == [1.0, 0.0]  # the ball alone, then padding
    np.testing.assert_allclose(c[0, 0], scene.obstacles[5].center, atol=60.0)
    a = small.solve(x0, ref, Os)
    b = big.solve(x0, ref, big.obstacles_from_scene(scene, 0.5))
    assert a.is_success() and b.is_success()
    np.testing.assert_allclose(a.configs, b.configs, atol=1e-6)
    assert small.broad_overflows == 0


def test_the_loop_builds_the_qp_for_qp_obstacles_and_runs_safely(model):
    """With qp_obstacles = 2 a 12-obstacle scene gets a 2-slot QP; the run reaches the goal with no collision
    and no D_sf breach (the loop's dense checks cover all twelve)."""
    scene = _far_scene(model)
    opts = dataclasses.replace(OPTS, qp_obstacles=2)
    loop = ClosedLoop.build(
        model, scene, model.tip_position(XG), XS, options=opts, loop_options=LoopOptions(duration=20.0), goal_config=XG
    )
    assert loop.replanner.max_obstacles == 2
    run = loop.run()
    assert run.status is RunStatus.REACHED, run.summary_line()
    assert run.collisions == 0 and run.safety_violations == 0
    assert loop.replanner.broad_overflows == 0


def test_reselect_puts_an_entered_omitted_obstacle_into_a_slot(model, full):
    """An omitted obstacle whose sphere holds a point of the solution is reported (its row) and goes into a slot
    first; with none entered there is nothing to do."""
    N = full.N
    P = np.zeros((N, 3, 3))
    P[:, :, 2] = [100.0, 200.0, 300.0]
    centers = np.zeros((N, 3, 3))
    centers[:, :, 2] = [100.0, 200.0, 600.0]
    centers[:, :, 0] = [50.0, 30.0, 0.0]
    rho = np.tile([[10.0, 40.0, 5.0]], (N, 1))  # obstacle 1 holds the point at z = 200 by 10 mm
    sel = BroadPhase(model, OPTS.points, full.step_limit, N)
    s = Selection.of(centers, rho, np.array([0]), 1)
    worst, nxt = sel.reselect(s, P, 1)
    assert worst == pytest.approx(-10.0) and nxt is not None and nxt.chosen.tolist() == [1]
    worst, nxt = sel.reselect(Selection.of(centers, rho, np.array([1]), 1), P, 1)
    assert worst == pytest.approx(40.0) and nxt is None


def test_an_overflowing_qp_returns_no_plan_inside_an_omitted_obstacle(model, full):
    """Scenes where more obstacles can matter than the QP's 2 slots: a feasible plan keeps every obstacle row of
    the full NLP (all obstacles) satisfied."""
    small = Replanner(model, OPTS, max_obstacles=2, safety_distance=5.0)
    rng = np.random.default_rng(5)
    plans = 0
    for _ in range(6):
        x0 = XS + rng.normal(0.0, [0.2, 0.2, 0.2, 0.2, 10.0])
        scene = _scene_near(rng, model, x0, SLOTS)
        ref = x0 + np.linspace(0.1, 1.0, OPTS.horizon)[:, None] * (XG - x0)
        res = small.solve(x0, ref, small.obstacles_from_scene(scene, 0.0, x0))
        small.reset()
        if res.feasible:
            plans += 1
            rows = full.distances(res.configs.ravel(), full.obstacles_from_scene(scene, 0.0))
            assert rows.min() >= -1e-6, res.solver_status
    assert small.broad_overflows == 6 and plans >= 1


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(SLOTS + 1, 4 * SLOTS), t0=st.floats(0.0, 20.0))
def test_with_more_obstacles_than_slots_the_narrow_phase_loses_none(model, full, seed, m, t0):
    """Random scenes of more obstacles than the QP's slots and random plans within reach (issue 29): every obstacle
    whose narrow-phase rows (every backbone point of every step against its inflated swept sphere, in numpy) the
    plan enters is one the broad phase calls relevant, and is in the QP's slots or found by the check at the
    solution (`BroadPhase.reselect`: its worst row below zero, and the entered ones first in the next slots)."""
    rng = np.random.default_rng(seed)
    x0 = XS + rng.normal(0.0, [0.3, 0.3, 0.3, 0.3, 20.0])
    scene = _scene_near(rng, model, x0, m)
    centers, radii = scene.swept_spheres(*full.step_windows(t0))
    rho = full._rho(radii)
    _, sel = full.broad.pack(x0, centers, rho, SLOTS)
    relevant = np.flatnonzero(full.broad.gaps(x0, centers, rho) <= 0.0)
    assert (sel is None) == (len(relevant) <= SLOTS)
    for _ in range(5):
        P = model.points(_reachable(rng, full, x0).reshape(full.N, full.nx), OPTS.points)  # (N, points, 3)
        rows = np.linalg.norm(P[:, None] - centers[:, :, None], axis=-1) - rho[:, :, None]  # (N, m, points)
        entered = set(np.flatnonzero(rows.min(axis=(0, 2)) < -ROW_TOLERANCE).tolist())
        assert entered <= set(relevant.tolist())
        if sel is None:
            continue  # every relevant obstacle has a slot
        missed = entered - set(relevant[sel.chosen].tolist())
        worst, nxt = full.broad.reselect(sel, P, SLOTS)
        if not missed:
            assert nxt is None and worst >= -ROW_TOLERANCE
            continue
        assert nxt is not None and worst == pytest.approx(rows.min(axis=(0, 2))[list(missed)].min(), abs=1e-9)
        if len(missed) <= SLOTS:
            assert missed <= set(relevant[nxt.chosen].tolist())
