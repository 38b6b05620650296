"""Planning for the rod's body (crtraj.model.cosserat.RodModel, crtraj.planning.body, ``crtraj plan --model rod``).

The robot is problems/robots/cdsr1_side.toml: one 300 mm NiTi segment mounted sideways, whose rod sags up to
17 mm below PCC's body. A small rod model (a 7 x 7 surrogate grid, a degree-6 polynomial) keeps the builds to
a second; its measured error is what the planner adds to D_sf. The independent check of a plan is
`crtraj.app.lab.verify_cosserat`: fresh rod solves at every waypoint (the robot file's actuation mode,
gravity) and numpy distances to the obstacles, no surrogate."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.lab import verify_cosserat
from crtraj.app.plan import plan_problem
from crtraj.core.errors import InputError
from crtraj.io.problem import Problem, load_robot
from crtraj.io.results import read_result
from crtraj.model.cosserat import RodDrive, RodModel, RodModelOptions, load_rod_model, sample_within_limits
from crtraj.model.cosserat._surrogate import SurrogateOptions
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.planning.body import body_mismatch, planning_model, planning_scene
from crtraj.planning.validity import kernel_key
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PROBLEM = ROOT / "problems" / "side_shelf.toml"
ROBOT = load_robot(ROOT / "problems" / "robots" / "cdsr1_side.toml")
SMALL = RodModelOptions(degree=6, samples=2000, holdout=40, seed=2, surrogate=SurrogateOptions(grid=7, holdout=10))


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("rod_model_cache")


@pytest.fixture(scope="module")
def rod(cache: Path) -> RodModel:
    return load_rod_model(ROBOT, SMALL, cache_dir=cache)


def test_the_rod_model_equals_fresh_rod_solves_within_its_stated_bound(rod: RodModel) -> None:
    """At every rod node of new random configurations (not the held-out ones) the model's body is within the
    stated bound of a fresh solve from the straight rod; and the bound is not vacuous (PCC misses by far more)."""
    xs = sample_within_limits(ROBOT, 12, np.random.default_rng(77))
    mech = Mechanics.from_robot(ROBOT)
    steps = mech.steps
    arcs = ROBOT.total_length * np.arange(steps + 1) / steps
    f = rod.points_at_arcs(arcs)
    pcc = Model(ROBOT)
    worst = worst_pcc = 0.0
    for x in xs:
        shape = RodDrive(ROBOT, mech, pretension=1.0).shape_config(x)
        assert shape.is_success()
        worst = max(worst, float(np.linalg.norm(np.asarray(f(x)).T - shape.points, axis=1).max()))
        worst_pcc = max(worst_pcc, float(np.linalg.norm(pcc.points(x, steps + 1) - shape.points, axis=1).max()))
    assert worst <= rod.planning_margin, (worst, rod.error.text())
    assert worst_pcc > 10.0 * rod.planning_margin  # the sag is real and the model removes it


def test_every_body_function_is_the_same_rod_body(rod: RodModel) -> None:
    """tip, backbone, points(n), segment_point_function and the tip Jacobian describe one body (the last against
    central differences)."""
    x = np.array([0.7, -0.4, -20.0])
    tip = rod.tip_position(x)
    assert np.allclose(rod.points(x)[-1], tip, atol=1e-9)
    dense = rod.points(x, 31)
    assert np.allclose(dense[-1], tip, atol=1e-9)
    seg = rod.segment_point_function()
    for k, frac in ((10, 1.0 / 3.0), (15, 0.5), (30, 1.0)):
        assert np.allclose(np.asarray(seg(x, frac)).ravel(), dense[k], atol=1e-9)
    assert not np.allclose(tip, Model(ROBOT).tip_position(x), atol=1.0)  # not PCC's
    h, J = 1e-6, rod.jacobian(x)
    fd = np.stack([(rod.tip_position(x + h * e) - rod.tip_position(x - h * e)) / (2 * h) for e in np.eye(3)], 1)
    assert np.allclose(J, fd, atol=1e-5)


def test_the_rod_model_is_cached_and_keys_its_own_compiled_kernel(rod: RodModel, cache: Path) -> None:
    """A second load reads the same coefficients and error; the compiled checker's key differs from PCC's."""
    again = load_rod_model(ROBOT, SMALL, cache_dir=cache)
    assert np.array_equal(again.correction.coef, rod.correction.coef) and again.error == rod.error
    assert kernel_key(rod, 15).spec != kernel_key(Model(ROBOT), 15).spec
    assert "body" not in kernel_key(Model(ROBOT), 15).spec  # PCC's libraries keep their keys


def test_the_planning_margin_grows_dsf_and_pcc_is_unchanged(rod: RodModel) -> None:
    """The planner keeps D_sf + the rod model's bound; PCC's scene is the problem's own object."""
    scene = Problem.load(PROBLEM).options(Scene, "scene")
    assert planning_scene(scene, rod).safety_distance == pytest.approx(scene.safety_distance + rod.planning_margin)
    assert planning_scene(scene, Model(ROBOT)) is scene
    assert rod.planning_margin == pytest.approx(1.5 * rod.error.body_max)


def test_rod_on_a_robot_without_mechanics_is_one_line() -> None:
    """--model rod on a robot file without [robot.mechanics] names the missing table; an unknown kind its choices."""
    bare = load_robot(ROOT / "problems" / "robots" / "cdsr1.toml")
    with pytest.raises(InputError, match=r"--model rod: robot 'cdsr1' has no \[robot.mechanics\] table"):
        planning_model(bare, "rod")
    with pytest.raises(InputError, match="choose from pcc, rod"):
        planning_model(bare, "cosserat")
    assert type(planning_model(bare, "pcc")) is Model


def test_the_sagging_shelf_pcc_plan_breaches_dsf_on_the_rod_and_the_rod_plan_keeps_it(rod: RodModel) -> None:
    """problems/side_shelf.toml planned both ways, each checked by fresh rod solves at every waypoint: PCC's plan
    holds D_sf for PCC but the rod sags into the shelf; the rod plan keeps D_sf on the rod itself."""
    problem = Problem.load(PROBLEM)
    robot = problem.robot
    verdicts = {}
    for name, kw in (("pcc", {"body": "pcc"}), ("rod", {"model": rod})):
        run = plan_problem(problem, **kw)
        assert run.result.is_success(), (name, run.result.message)
        doc = run.document()
        assert doc["options"]["body"]["kind"] == doc["options"]["planner"]["model"] == name
        assert doc["scene"]["safety_distance"] == problem.options(Scene, "scene").safety_distance
        v = verify_cosserat(read_result(doc), robot)
        assert v.failed == 0 and v.actuation == "cable_length" and v.gravity
        verdicts[name] = (v.pcc.clearance, v.rod.clearance)
    pcc_by_pcc, pcc_by_rod = verdicts["pcc"]
    assert pcc_by_pcc >= 0.0 and pcc_by_rod < -1.0, verdicts  # PCC keeps D_sf only in its own eyes
    assert verdicts["rod"][1] >= 0.0, verdicts  # the rod plan keeps D_sf on the rod
    assert doc["options"]["body"]["planning_margin_mm"] == pytest.approx(rod.planning_margin)
    # the rod plan records its mechanics: its own robot file may stream it, one with other mechanics may not
    assert body_mismatch(doc["options"]["body"], robot) is None
    heavier = replace(robot, mechanics={**robot.mechanics, "disc_mass": 0.4})
    assert "robot.mechanics.disc_mass" in body_mismatch(doc["options"]["body"], heavier)


def test_the_replan_loop_plans_for_the_rod_body() -> None:
    """ClosedLoop.from_problem(body="rod"): the loop's model (reference planner, horizon NLP, step verification)
    is the rod model and its scene keeps D_sf plus the rod model's margin; its start tip is the rod's."""
    from crtraj.control.loop import ClosedLoop

    problem = Problem.load(PROBLEM)
    loop = ClosedLoop.from_problem(problem, body="rod")
    assert isinstance(loop.model, RodModel)
    assert loop.extra_options["body"]["kind"] == "rod"  # recorded in the run document's options
    d_sf = problem.options(Scene, "scene").safety_distance
    assert loop.scene.safety_distance == pytest.approx(d_sf + loop.model.planning_margin)
    x0 = loop.x_start
    task = problem.require_task()
    rod_tip = RodDrive(ROBOT, Mechanics.from_robot(ROBOT)).shape_config(x0).tip
    assert np.linalg.norm(rod_tip - np.asarray(task.start)) < task.goal_tolerance + loop.model.error.tip_bound
    assert np.linalg.norm(Model(ROBOT).tip_position(x0) - np.asarray(task.start)) > 5.0  # PCC's tip is elsewhere


def test_a_corrupt_rod_model_entry_is_rebuilt_not_used(rod: RodModel, cache: Path, caplog) -> None:
    """A cache entry whose JSON is damaged is refused with one warning and rebuilt to the same coefficients."""
    (entry,) = cache.glob(f"rod_model-{rod.identity()['rod_model']}.json")
    entry.write_text(entry.read_text()[:-40])
    with caplog.at_level("WARNING", logger="crtraj"):
        again = load_rod_model(ROBOT, SMALL, cache_dir=cache)
    assert "is unusable" in caplog.text and "rebuilding it" in caplog.text
    assert np.allclose(again.correction.coef, rod.correction.coef, rtol=0.0, atol=1e-9)
    assert load_rod_model(ROBOT, SMALL, cache_dir=cache).error == again.error  # and stored again


def test_the_compiled_checker_and_numpy_evaluate_the_same_rod_body(rod: RodModel) -> None:
    """The checker's generated C (backbone points and the tip), the interpreted SX function and a plain numpy
    evaluation of the correction (PCC's points plus mean + modes x polynomials, interpolated along the arc) agree
    to 1e-9 mm."""
    from crtraj.core.build_cache import BuildCache
    from crtraj.planning.validity import RodKernel, ValidityKernel

    kernel = RodKernel.load(rod, 15, BuildCache())
    if kernel is None:
        pytest.skip("no C compiler")
    X = sample_within_limits(ROBOT, 64, np.random.default_rng(5))
    interpreted = rod.points(X, 15)
    assert np.abs(kernel.points(X) - interpreted).max() <= 1e-9
    c = rod.correction
    arcs = Model(ROBOT).arc_positions(15)
    by_numpy = Model(ROBOT).points(X, 15) + np.einsum(
        "qj,njc->nqc", c.weights(arcs), c.values(ROBOT.bending(X).reshape(len(X), -1))
    )
    assert np.abs(by_numpy - interpreted).max() <= 1e-9
    tips, jac = kernel.tip_jacobian(X)  # the tip's own polynomials (the modes folded in): the same tip
    assert np.abs(tips - by_numpy[:, -1]).max() <= 1e-9
    # the hand-written tip Jacobian (derivative coefficients, chain rule through the coupling) against CasADi's
    # symbolic one of the same expression, and a central difference of the compiled tip
    symbolic = np.array([np.asarray(rod.jac_tip(x)) for x in X])
    assert np.abs(jac - symbolic).max() <= 1e-9 * max(1.0, np.abs(symbolic).max())
    # the tips alone sum the same products in the same order: bit for bit; the push-out's Jacobian is PCC's
    assert np.array_equal(kernel.tip_positions(X), tips)
    pcc_kernel = ValidityKernel.load(Model(ROBOT), 15, BuildCache())
    assert np.array_equal(kernel.pcc_tip_jacobian(X), pcc_kernel.tip_jacobian(X)[1])
    assert np.abs(kernel.pcc_tip_jacobian(X) - jac).max() > 1e-3  # and not the rod's
    h = 1e-6
    for j in range(ROBOT.nx):
        e = np.zeros(ROBOT.nx)
        e[j] = h
        fd = (kernel.tip_jacobian(X + e)[0] - kernel.tip_jacobian(X - e)[0]) / (2 * h)
        assert np.abs(fd - jac[:, :, j]).max() <= 1e-5 * max(1.0, np.abs(jac).max())
    assert c.basis.shape[0] == min(SMALL.modes, 3 * len(c.arcs))  # the modes, not one polynomial per number


def test_the_view_draws_the_rod_body_of_a_rod_result() -> None:
    """`crtraj view` of a --model rod plan draws the rod model's body (the plan's own model, not PCC's); a result
    that records a PCC body is drawn with PCC."""
    from crtraj.viz.view import Visualizer, result_model

    run = plan_problem(Problem.load(PROBLEM), body="rod")
    doc = run.document()
    vis = Visualizer.for_result(doc)
    try:
        assert isinstance(vis.model, RodModel) and vis.model.identity() == run.model.identity()
    finally:
        vis.close()
    xs = read_result(doc).x
    x = xs[len(xs) // 2]
    assert np.allclose(vis.model.points(x), run.model.points(x), atol=1e-12)
    assert np.linalg.norm(vis.model.points(x) - Model(ROBOT).points(x), axis=1).max() > 5.0  # the sag is drawn
    doc["options"]["body"] = {"kind": "pcc"}
    assert type(result_model(read_result(doc))) is Model


def test_the_numpy_tip_is_the_interpreted_rod_tip(rod: RodModel) -> None:
    """`RodModel.tip_position` (PCC's tip plus the tip polynomials by table look-ups, numpy) equals the model's
    interpreted SX tip function at random configurations, one at a time and in a batch; its monomials equal
    plain powers (`monomials`) on 4 variables of degree 10 (cdsr2's two segments)."""
    from crtraj.model.cosserat import power_products
    from crtraj.model.cosserat._rod_model import exponents, monomials

    X = sample_within_limits(ROBOT, 16, np.random.default_rng(8))
    interpreted = np.array([np.asarray(rod.tip(x)).ravel() for x in X])
    assert np.abs(rod.tip_position(X) - interpreted).max() <= 1e-9
    assert rod.tip_position(X[3]).shape == (3,)
    assert np.abs(rod.tip_position(X[3]) - interpreted[3]).max() <= 1e-9
    assert np.abs(rod.tip_position(X) - Model(ROBOT).tip_position(X)).max() > 1.0  # the sag, not PCC's tip
    w = np.random.default_rng(9).uniform(-1.2, 1.2, (5, 4))
    exps = exponents(4, 10)
    plain = monomials(w, exps)
    assert np.abs(power_products(w, exps) - plain).max() <= 1e-13 * np.abs(plain).max()
