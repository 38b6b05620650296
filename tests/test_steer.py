"""Steer step: constraints re-checked densely and independently, reach, failure reporting, DLS, options."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.planning.steer._nlp import config_scale
from crtraj.planning.steer._options import SteerOptions
from crtraj.planning.steer._result import SteerResult, SteerStatus
from crtraj.planning.steer._solver import SteerSolver, dls_step
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
DENSE = 200  # backbone points of the independent check


def sim1_scene() -> Scene:
    return Scene(
        obstacles=(
            Obstacle(center=(0, 90, 330), radius=65, name="upper"),
            Obstacle(center=(-10, -70, 250), radius=55, name="lower"),
        ),
        safety_distance=5.0,
    )


def dense_gap(model: Model, x: np.ndarray, scene: Scene, t: float = 0.0) -> float:
    """Smallest distance (mm) from the dense body surface (200 backbone points + disc
    radius) to any sphere surface: plain numpy, independent of the Scene clearance code."""
    pts = model.points(x, DENSE)
    centers, radii = scene.states(t)
    d = np.sqrt(((pts[:, None, :] - centers[None, :, :]) ** 2).sum(axis=-1))
    return float((d - radii[None, :]).min() - model.robot.body_radius)


def point_gap(model: Model, x: np.ndarray, scene: Scene, t: float = 0.0) -> float:
    """The constrained quantity: collision points' distance to spheres minus R, body and D_sf."""
    return dense_gap_at(model.points(x), scene, t) - model.robot.body_radius - scene.safety_distance


def dense_gap_at(pts: np.ndarray, scene: Scene, t: float) -> float:
    centers, radii = scene.states(t)
    d = np.sqrt(((pts[:, None, :] - centers[None, :, :]) ** 2).sum(axis=-1))
    return float((d - radii[None, :]).min())


def safe_configs(model: Model, scene: Scene, n: int, seed: int, margin: float = 2.0) -> np.ndarray:
    """n random configurations within the limits whose body clears the scene by `margin` (mm)."""
    rng = np.random.default_rng(seed)
    lo, hi = model.robot.config_box()
    out = []
    while len(out) < n:
        X = rng.uniform(0.4 * lo, 0.4 * hi, size=(200, model.nx))
        X[:, -1] = rng.uniform(lo[-1], hi[-1], size=200)
        ok = (model.robot.limit_violation(X) <= 0) & (scene.clearance(model, X, 0.0, n_points=DENSE) > margin)
        out.extend(X[ok])
    return np.array(out[:n])


@pytest.fixture(scope="module")
def ipopt(model):
    return SteerSolver(model, 4, SteerOptions())


@pytest.fixture(scope="module")
def sqp(model):
    return SteerSolver(model, 4, SteerOptions(solver="sqp"))


@pytest.fixture(scope="module")
def far_ipopt(model):
    """Large step bound: the steer used as an IK solve."""
    return SteerSolver(model, 2, SteerOptions(max_step=1000.0))


# ------------------------------------------------------------ reach + safety
def witness_problems(model: Model, scene: Scene, n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(x_prev, target) pairs reachable by construction: target = tip of a safe configuration
    that lies within half the step bound of the safe x_prev."""
    goals = safe_configs(model, scene, 4 * n, seed)
    rng = np.random.default_rng(seed + 1)
    S = config_scale(model.robot)
    pairs = []
    for xg in goals:
        xp = xg + rng.uniform(-25.0, 25.0, size=model.nx) / S
        if model.robot.limit_violation(xp)[0] <= 0 and scene.clearance(model, xp, 0.0) > 0:
            pairs.append((xp, model.tip_position(xg)))
        if len(pairs) == n:
            break
    assert len(pairs) == n
    return pairs


@pytest.mark.parametrize("which", ["ipopt", "sqp"])
def test_reachable_targets_are_reached_safely(model, which, request):
    solver = request.getfixturevalue(which)
    scene = sim1_scene()
    for xp, target in witness_problems(model, scene, 15, seed=11):
        r = solver.solve(xp, target, scene)
        assert r.is_success() and r.reached, r.message
        assert np.linalg.norm(model.tip_position(r.x) - target) <= 0.5
        assert r.tip_error == pytest.approx(np.linalg.norm(model.tip_position(r.x) - target))
        # constraints, re-checked independently
        assert point_gap(model, r.x, scene) >= -1e-5
        assert dense_gap(model, r.x, scene) > 0.0
        assert model.robot.limit_violation(r.x)[0] <= 1e-9
        assert np.max(np.abs(r.x - xp) * config_scale(model.robot)) <= solver.options.max_step + 1e-9
        np.testing.assert_allclose(r.q, model.cables(r.x))
        assert r.min_clearance == pytest.approx(float(sim1_scene().clearance(model, r.x, 0.0)), abs=1e-9)


def test_active_constraints_hold_densely(model, far_ipopt):
    """Targets on the safety shell of an obstacle: the constraints become active, and the
    dense body still stays outside the sphere surface plus the disc radius."""
    scene = sim1_scene()
    rng = np.random.default_rng(5)
    starts = safe_configs(model, scene, 8, seed=21, margin=10.0)
    active = 0
    for xp in starts:
        c, r_ob = scene.states(0.0)
        k = int(rng.integers(2))
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        target = c[k] + (r_ob[k] + 2.0) * direction  # inside the keep-out shell
        res = far_ipopt.solve(xp, target, scene)
        if res.status not in (SteerStatus.REACHED, SteerStatus.PARTIAL):
            continue
        gap = point_gap(model, res.x, scene)
        assert gap >= -1e-5
        assert dense_gap(model, res.x, scene) > 0.0, "the body touches a sphere between collision points"
        active += gap < 1e-3
        assert not res.reached  # the target itself is unsafe: never reachable
    assert active >= 4


def test_sim1_start_and_goal_admit_safe_configurations(model, far_ipopt):
    prob = Problem.load(ROOT / "problems" / "paper_static.toml")
    scene = prob.options(Scene, "scene")
    for target in (prob.task.start, prob.task.goal):
        res = far_ipopt.solve(model.robot.straight(0.0), target, scene)
        assert res.is_success() and res.reached, res.message
        assert dense_gap(model, res.x, scene) > 0.0
        assert point_gap(model, res.x, scene) >= -1e-5


def test_margin_keeps_the_full_safety_distance_densely(model):
    """With margin = the documented chord/sagitta allowance, the dense body keeps D_sf too."""
    prob = Problem.load(ROOT / "problems" / "paper_static.toml")
    scene = prob.options(Scene, "scene")
    solver = SteerSolver(model, 2, SteerOptions(max_step=1000.0, margin=1.0))
    res = solver.solve(model.robot.straight(0.0), prob.task.start, scene)
    assert res.reached, res.message
    assert float(scene.clearance(model, res.x, 0.0, n_points=DENSE)) >= 0.0


# --------------------------------------------------------- unreachable / failures
def test_unreachable_target_inside_an_obstacle(model, far_ipopt):
    scene = sim1_scene()
    xp = safe_configs(model, scene, 1, seed=3, margin=10.0)[0]
    center = np.array(scene.obstacles[1].center)
    toward = model.tip_position(xp) - center
    target = center + 20.0 * toward / np.linalg.norm(toward)  # inside the sphere, off its centre
    res = far_ipopt.solve(xp, target, scene, obstacle_weight=0.0)
    assert res.status is SteerStatus.PARTIAL and not res.is_success() and not res.reached, res.message
    assert res.solver_status == "Solve_Succeeded"
    assert "not reached" in res.message
    # the tip is a collision point, so no safe tip comes closer than the keep-out
    # sphere; the closest safe configuration gets (nearly) that close
    rho = scene.obstacles[1].radius + scene.safety_distance + model.robot.body_radius
    assert rho - 20.0 - 1e-6 <= res.tip_error <= rho - 20.0 + 1.0
    assert point_gap(model, res.x, scene) >= -1e-5
    assert dense_gap(model, res.x, scene) > 0.0


def test_target_out_of_reach(model, ipopt):
    scene = sim1_scene()
    xp = model.robot.straight(0.0)
    res = ipopt.solve(xp, [0.0, 0.0, 2000.0], scene)
    assert not res.reached and "not reached" in res.message
    assert res.safe
    assert res.tip_error > 1000


def test_failed_solve_is_reported_as_failed(model):
    solver = SteerSolver(model, 2, SteerOptions(max_iter=1, max_step=1000.0))
    res = solver.solve(model.robot.straight(0.0), [60.0, 40.0, 250.0], sim1_scene())
    # `reached` is geometric only (one IPOPT iteration may already land near the target);
    # an unconverged solve is never usable and never a success
    assert not res.converged and res.status is SteerStatus.FAILED and not res.is_success()
    assert res.solver_status == "Maximum_Iterations_Exceeded"
    assert "failed" in res.message


def test_start_in_collision_raises(model, ipopt):
    scene = sim1_scene().with_obstacles([Obstacle(center=(0, 10, 200), radius=20)])
    x_bad = np.array([0.0, 0.0, 0.0, 0.0, 0.0])  # straight up the axis, through the sphere
    assert float(scene.clearance(model, x_bad, 0.0)) < 0
    with pytest.raises(InputError, match=r"^x_prev: start configuration is in collision"):
        ipopt.solve(x_bad, [0, 0, 380], scene)
    # the caller may opt out (replanning out of a grown obstacle)
    res = ipopt.solve(x_bad, [0, 0, 380], scene, check_start=False)
    assert isinstance(res, SteerResult)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"x_prev": [np.nan, 0, 0, 0, 0]}, "x_prev"),
        ({"x_prev": [0, 0, 0]}, "x_prev"),
        ({"target": [0, np.inf, 300]}, "target"),
        ({"target": "up"}, "target"),
        ({"x0": [0, 0, 0, 0, np.nan]}, "x0"),
        ({"t": float("nan")}, "t"),
        ({"t_end": -1.0}, "t_end"),
        ({"x_prev": [0, 0, 0, 0, 500.0]}, "x_prev"),
    ],
)
def test_bad_inputs_name_the_field(model, ipopt, kwargs, field):
    args = {"x_prev": model.robot.straight(60.0), "target": [0, 0, 400]}
    args.update(kwargs)
    xp, tg = args.pop("x_prev"), args.pop("target")
    with pytest.raises(InputError) as err:
        ipopt.solve(xp, tg, Scene(), **args)
    assert str(err.value).startswith(field + ":"), str(err.value)


def test_packed_obstacles_need_safety_distance_and_size(model, ipopt):
    scene = sim1_scene()
    packed = scene.pack(0.0, 4)
    xp = model.robot.straight(80.0)
    with pytest.raises(InputError, match=r"^safety_distance:"):
        ipopt.solve(xp, [0, 0, 470], packed)
    with pytest.raises(InputError, match=r"^obstacles:"):
        ipopt.solve(xp, [0, 0, 470], packed[:-1], safety_distance=5.0)
    with pytest.raises(InputError, match="at most 4"):
        SteerSolver(model, 4).solve(xp, [0, 0, 470], scene.with_obstacles(scene.obstacles * 3))


# ------------------------------------------------- paper behaviour and packing
def test_obstacle_term_bends_the_body_away_while_the_tip_tracks(model, ipopt):
    """The paper's null-space behaviour: mu > 0 moves the body away, mu = 0 does not."""
    x = np.array([0.4, 0.0, 0.8, 0.0, 0.0])
    pts = model.points(x)
    scene = Scene(obstacles=(Obstacle(center=tuple(pts[4] + np.array([-40.0, 0.0, 0.0])), radius=25.0),))
    tip = model.tip_position(x)
    targets = [tip, tip + np.array([0.0, 5.0, -5.0])]
    for target in targets:
        plain = ipopt.solve(x, target, scene, obstacle_weight=0.0)
        pushed = ipopt.solve(x, target, scene)
        assert plain.reached and pushed.reached
        assert pushed.min_clearance > plain.min_clearance + 0.5
        assert dense_gap(model, pushed.x, scene) > dense_gap(model, plain.x, scene) + 0.5


def test_padding_slots_are_inert(model):
    scene = sim1_scene()
    xp, target = witness_problems(model, scene, 1, seed=31)[0]
    small = SteerSolver(model, 2, SteerOptions(warm_start=False)).solve(xp, target, scene)
    big = SteerSolver(model, 6, SteerOptions(warm_start=False)).solve(xp, target, scene)
    assert small.reached and big.reached
    np.testing.assert_allclose(small.x, big.x, atol=1e-5)


def test_packed_vector_matches_scene(model, ipopt):
    scene = sim1_scene()
    xp, target = witness_problems(model, scene, 1, seed=41)[0]
    ipopt.reset_warm_start()
    a = ipopt.solve(xp, target, scene)
    ipopt.reset_warm_start()
    b = ipopt.solve(xp, target, scene.pack(0.0, 4), safety_distance=5.0)
    np.testing.assert_allclose(a.x, b.x, atol=1e-9)
    assert a.min_clearance == pytest.approx(b.min_clearance, abs=1e-9)


def test_warm_start_and_solvers_agree(model, ipopt, sqp):
    scene = sim1_scene()
    S = config_scale(model.robot)
    cold = SteerSolver(model, 4, SteerOptions(warm_start=False, predictor=False))
    for xp, target in witness_problems(model, scene, 5, seed=51):
        a, b, c = ipopt.solve(xp, target, scene), cold.solve(xp, target, scene), sqp.solve(xp, target, scene)
        for r in (a, b, c):
            assert r.reached
        # the damping term is weak, so the optimum is flat along the null space:
        # compare configurations in scaled millimetres
        assert np.max(np.abs((a.x - b.x) * S)) < 0.05
        assert np.max(np.abs((a.x - c.x) * S)) < 0.05


def test_moving_obstacle_over_an_interval(model, far_ipopt):
    """With t_end the configuration is safe at every instant of [t, t_end], not just the ends."""
    grow = Obstacle(center=(-10, -70, 250), radius=50, amplitude=15, omega=1.0, phase=-math.pi / 2)
    slide = Obstacle(center=(60, 120, 330), radius=50, to=(0, 90, 330), duration=2.0, profile="cos")
    scene = Scene(obstacles=(grow, slide))
    xp = safe_configs(model, Scene(obstacles=(Obstacle(center=grow.center, radius=65), slide)), 1, seed=61)[0]
    target = [-40.0, 80.0, 370.0]
    res = far_ipopt.solve(xp, target, scene, t=0.0, t_end=4.0)
    assert res.status in (SteerStatus.REACHED, SteerStatus.PARTIAL), res.message
    ts = np.linspace(0.0, 4.0, 401)
    pts = model.points(res.x)
    gaps = [dense_gap_at(pts, scene, float(t)) - model.robot.body_radius - scene.safety_distance for t in ts]
    assert min(gaps) >= -1e-5
    assert res.min_clearance <= min(gaps) + 1e-9


def test_dynamic_scene_uses_the_radius_at_t(model, far_ipopt):
    ob = Obstacle(center=(0, 0, 470), radius=30, amplitude=20, omega=1.0, phase=0.0)
    scene = Scene(obstacles=(ob,))
    xp = model.robot.straight(-200.0)  # tip at z = 200
    target = [0.0, 0.0, 420.0]  # under the obstacle: needs R(t) + 8 <= 470 - 420
    small = far_ipopt.solve(xp, target, scene, t=3 * math.pi / 2)  # R = 10
    large = far_ipopt.solve(xp, target, scene, t=math.pi / 2)  # R = 50
    assert small.reached and not large.reached
    assert large.tip_error == pytest.approx(50 + 8 - 50, abs=0.5)


# --------------------------------------------------------------------- DLS
def test_dls_step_matches_the_closed_form(model):
    x = np.array([0.3, -0.2, 0.5, 0.4, 10.0])
    target = model.tip_position(x) + np.array([5.0, -3.0, 4.0])
    # independent: finite-difference Jacobian, damped normal equations in scaled coordinates
    S = np.array([200.0, 200.0, 200.0, 200.0, 1.0])
    h = 1e-6
    J = np.stack(
        [
            (model.tip_position(x + h * np.eye(5)[i]) - model.tip_position(x - h * np.eye(5)[i])) / (2 * h)
            for i in range(5)
        ],
        axis=1,
    )
    Js = J / S
    e = target - model.tip_position(x)
    dy = np.linalg.solve(Js.T @ Js + 0.3**2 * np.eye(5), Js.T @ e)
    np.testing.assert_allclose(dls_step(model, x, target, 0.3), x + dy / S, atol=1e-7)
    # the step bound shrinks the whole step
    small = dls_step(model, x, target, 0.3, max_step=1.0)
    assert np.max(np.abs((small - x) * S)) == pytest.approx(1.0)
    with pytest.raises(InputError, match=r"^target:"):
        dls_step(model, x, [np.nan, 0, 0], 0.3)


def test_dls_converges_in_free_space(model):
    solver = SteerSolver(model, 1, SteerOptions(solver="dls"))
    x = np.array([0.3, -0.2, 0.5, 0.4, 10.0])
    target = model.tip_position(np.array([0.4, -0.1, 0.3, 0.5, 0.0]))
    res = solver.solve(x, target, None)
    assert res.reached and res.solver_status == "Solve_Succeeded" and res.iterations > 1


def test_dls_has_no_hard_constraints_and_is_rechecked(model):
    """DLS ignores obstacles: put one on the body DLS ends in, and the re-check reports it."""
    x = np.array([0.0, 0.0, 0.0, 0.0, -100.0])
    target = model.tip_position(np.array([0.6, 0.0, 0.6, 0.0, -100.0]))
    dls_solver = SteerSolver(model, 1, SteerOptions(solver="dls", max_step=500.0))
    free = dls_solver.solve(x, target, None)
    assert free.reached
    mid = model.points(free.x)[5]
    scene = Scene(obstacles=(Obstacle(center=tuple(mid + np.array([6.0, 0.0, 0.0])), radius=10.0),))
    assert float(scene.clearance(model, x, 0.0)) > 0
    dls = dls_solver.solve(x, target, scene)
    np.testing.assert_allclose(dls.x, free.x)
    assert dls.converged and not dls.safe and dls.status is SteerStatus.UNSAFE and not dls.is_success()
    assert "clearance" in dls.message
    nlp = SteerSolver(model, 1, SteerOptions(max_step=500.0)).solve(x, target, scene)
    assert nlp.is_success() and nlp.reached and nlp.min_clearance >= -1e-5


# ------------------------------------------------------------------ options
def test_options_round_trip_and_mapping():
    opts = SteerOptions.from_table(
        Table({"solver": "sqp", "damping": 0.3, "obstacle_coefficient": 40.0, "ipopt": {"mu_init": 0.01}}, "steer")
    )
    assert opts.damping_weight == pytest.approx((0.3 * opts.damping_scale) ** 2)
    assert opts.obstacle_weight == pytest.approx((40.0 * opts.obstacle_scale) ** 2)
    again = SteerOptions.from_table(Table(opts.to_dict(), "steer"))
    assert again == opts


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"solver": "newton"}, "steer.solver"),
        ({"damping": -1}, "steer.damping"),
        ({"max_step": 0}, "steer.max_step"),
        ({"qpsol": "gurobi"}, "steer.qpsol"),
        ({"jit": "yes"}, "steer.jit"),
        ({"n_points": 1}, "steer.n_points"),
        ({"ipopt": {"tol": [1]}}, "steer.ipopt.tol"),
        ({"dls_gain": 2.0}, "steer.dls_gain"),
        ({"speed": 2.0}, "steer.speed"),
    ],
)
def test_option_errors_name_the_field(data, field):
    with pytest.raises(InputError) as err:
        SteerOptions.from_table(Table(data, "steer"))
    assert str(err.value).startswith(field + ":"), str(err.value)


def test_solver_rejects_unknown_solver_options(model):
    with pytest.raises(InputError, match=r"^steer\.ipopt:"):
        SteerSolver(model, 1, SteerOptions(ipopt=(("no_such_option", 1.0),)))
    with pytest.raises(InputError, match=r"^steer\.sqp:"):
        SteerSolver(model, 1, SteerOptions(solver="sqp", sqp=(("no_such_option", 1.0),)))


def test_problem_file_steer_sections(model):
    for name, mu in [("paper_static", 20.0), ("paper_dynamic", 40.0), ("paper_prototype", 20.0)]:
        opts = Problem.load(ROOT / "problems" / f"{name}.toml").options(SteerOptions, "steer")
        assert opts.damping == 0.3 and opts.obstacle_coefficient == mu


@pytest.mark.slow
def test_jit_compiles_privately_and_matches_plain(model, sqp, tmp_path, monkeypatch):
    require_tool("gcc", hint="Debian: apt-get install gcc")  # without it jit compares plain with plain
    monkeypatch.chdir(tmp_path)  # CasADi's nlpsol jit writes its C source to the working directory
    jit = SteerSolver(model, 4, SteerOptions(solver="sqp", jit=True))
    assert jit.jit_message == "jit: compiled with gcc -O2"
    # really compiled: gcc's shared objects sit in the solver's private folder ...
    private = jit.jit_directory
    assert private is not None
    assert sorted(p.suffix for p in private.iterdir()).count(".so") >= 1
    assert private.parent != tmp_path
    # ... and nothing was left in the working directory
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    scene = sim1_scene()
    for xp, target in witness_problems(model, scene, 3, seed=71):
        a, b = sqp.solve(xp, target, scene), jit.solve(xp, target, scene)
        assert a.is_success() and b.is_success(), (a.message, b.message)
        # the same NLP, compiled: the same iterates up to round-off
        np.testing.assert_allclose(b.x, a.x, atol=1e-6)
        assert abs(b.iterations - a.iterations) <= 1
        assert point_gap(model, b.x, scene) >= -1e-5
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_jit_without_a_compiler_runs_plain(model, monkeypatch):
    import crtraj.planning.steer._backends as steer_mod

    monkeypatch.setattr(steer_mod.shutil, "which", lambda name: None)
    solver = SteerSolver(model, 1, SteerOptions(solver="sqp", jit=True))
    assert solver.jit_message == "jit requested but gcc was not found: running without jit"
    x = np.array([0.3, -0.2, 0.5, 0.4, 10.0])
    target = model.tip_position(x) + np.array([3.0, 0.0, -2.0])
    res = solver.solve(x, target, None)
    assert res.is_success()
    assert np.linalg.norm(model.tip_position(res.x) - target) <= 1e-3


def test_sqp_failure_falls_back_to_ipopt(model):
    scene = sim1_scene()
    xp, target = witness_problems(model, scene, 1, seed=81)[0]
    strict = SteerSolver(model, 2, SteerOptions(solver="sqp", max_iter=1, fallback=False))
    fails = strict.solve(xp, target, scene)
    assert not fails.is_success() and fails.solver_status == "Maximum_Iterations_Exceeded"
    rescued = SteerSolver(model, 2, SteerOptions(solver="sqp", max_iter=1, fallback=True, ipopt=(("max_iter", 100),)))
    res = rescued.solve(xp, target, scene)
    assert res.solver == "sqp>ipopt" and res.is_success() and res.reached
    assert res.message.startswith("sqp: Maximum_Iterations_Exceeded")
