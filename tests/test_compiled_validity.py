"""The compiled validity kernel against the interpreted CasADi path and independent numpy computations:
clearance, backbone points, tip Jacobians and motion bounds agree to 1e-9 on random batches, padded
slots are inert, plans are identical for the same seed, and the cache is reused or rebuilt as it should."""

from __future__ import annotations

import io
from dataclasses import replace

import numpy as np
import pytest
from conftest import PROBLEMS, require_tool

from crtraj.app import build as build_use_case
from crtraj.cli import main
from crtraj.core.build_cache import BuildCache
from crtraj.core.errors import InputError
from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.context import PlanningContext
from crtraj.planning.options import PlannerOptions
from crtraj.planning.planners import BUILTIN
from crtraj.planning.validity._compiled import ValidityKernel, kernel_key
from crtraj.planning.validity._kernels import Kernels
from crtraj.planning.validity._motion import MotionValidator
from crtraj.world import packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

TOL = 1e-9


@pytest.fixture(scope="module")
def kernel_cache(tmp_path_factory):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    return BuildCache(tmp_path_factory.mktemp("kernels"))


def validators(model, scene, cache, **kw):
    """(compiled, interpreted) validators of one scene; the compiled one with its own cache folder."""
    comp = MotionValidator(model, scene, kernels=Kernels(cache), **kw)
    assert comp.state.kernel is not None
    return comp, MotionValidator(model, scene, compiled=False, **kw)


def random_configs(v, rng, n):
    """Configurations within the limits and, for a tenth of them, beyond (the kernel must not care)."""
    X = v.sample(rng, n)
    X[: n // 10] *= 1.5
    return X


def numpy_chord_clearance(P, centers, radii):
    """Independent: min over chords of P (N, n, 3) and spheres of (distance to the chord segment - radius)."""
    A, B = P[:, :-1], P[:, 1:]
    AB = B - A
    out = np.full(len(P), np.inf)
    for c, r in zip(centers, radii, strict=True):
        AC = c - A
        u = np.clip(np.sum(AC * AB, -1) / np.maximum(np.sum(AB * AB, -1), 1e-300), 0.0, 1.0)
        d = np.linalg.norm(AC - AB * u[..., None], axis=-1).min(axis=1) - r
        out = np.minimum(out, d)
    return out


def test_static_clearance_points_and_jacobians_agree(model, kernel_cache):
    problem = Problem.load(PROBLEMS / "paper_static.toml")
    scene = problem.options(Scene, "scene")
    comp, interp = validators(model, scene, kernel_cache)
    rng = np.random.default_rng(3)
    X = random_configs(comp, rng, 400)
    np.testing.assert_allclose(comp.points(X), interp.points(X), rtol=0, atol=TOL)
    c = comp.clearance(X, margin=0.7)
    np.testing.assert_allclose(c, interp.clearance(X, margin=0.7), rtol=0, atol=TOL)
    assert (c < 0).any() and (c > 0).any()  # the batch crosses the boundary
    centers, radii = scene.states(0.0)
    ref = numpy_chord_clearance(model.points(X, comp.check_points), centers, radii) - comp.inflate - 0.7
    np.testing.assert_allclose(c, ref, rtol=0, atol=1e-8)
    P, J = comp.state.kernel.tip_jacobian(X)
    np.testing.assert_allclose(P, model.tip_position(X), rtol=0, atol=TOL)
    np.testing.assert_allclose(J, model.jacobian(X), rtol=0, atol=TOL)
    # and the Jacobian is the derivative of the tip (central differences)
    h = 1e-6
    for j in range(model.nx):
        E = np.zeros(model.nx)
        E[j] = h
        fd = (comp.state.kernel.tip_jacobian(X[:20] + E)[0] - comp.state.kernel.tip_jacobian(X[:20] - E)[0]) / (2 * h)
        np.testing.assert_allclose(J[:20, :, j], fd, rtol=0, atol=1e-5)
    dX = np.diff(X, axis=0)
    np.testing.assert_allclose(comp.state.kernel.motion_bound(dX), interp.motion_bound(dX), rtol=1e-12, atol=TOL)


def test_static_edge_check_in_c_is_the_numpy_loop(model, kernel_cache):
    """The C refinement loop returns what the numpy loop returns with the same clearances, bit for bit."""
    problem = Problem.load(PROBLEMS / "paper_static.toml")
    scene = problem.options(Scene, "scene")
    comp, interp = validators(model, scene, kernel_cache)
    loop = MotionValidator(model, scene, kernels=Kernels(kernel_cache))
    loop.compiled_loop = False  # the numpy loop (its clearances still from the kernel, static slots)
    rng = np.random.default_rng(5)
    XA, XB = comp.sample(rng, 150), comp.sample(rng, 150)
    XB[:20] = XA[:20] + rng.normal(scale=0.05, size=(20, model.nx))  # short motions too
    XB[20] = XA[20]  # and no motion at all
    for prefix in (True, False):
        n0, n1 = comp.n_samples, loop.n_samples
        fc, lc = comp.check_edges(XA, XB, prefix=prefix)
        fl, ll = loop.check_edges(XA, XB, prefix=prefix)
        np.testing.assert_array_equal(fc, fl)
        np.testing.assert_array_equal(lc, ll)
        assert comp.n_samples - n0 == loop.n_samples - n1 > 0
        assert (fc < 1).any() and (fc == 1).any()  # both outcomes occur
        # and the interpreted checks agree (their clearances differ from the kernel's by rounding only)
        fi, li = interp.check_edges(XA, XB, prefix=prefix)
        np.testing.assert_array_equal(fc, fi)
        np.testing.assert_allclose(lc, li, rtol=0, atol=TOL)


def test_nan_is_never_clear(model, kernel_cache):
    """A configuration the kinematics cannot evaluate (NaN) has no clearance (NaN, never +inf) and no motion
    through it is certified, in the C loop as in the numpy one."""
    scene = Problem.load(PROBLEMS / "paper_static.toml").options(Scene, "scene")
    comp, _ = validators(model, scene, kernel_cache)
    X = comp.sample(np.random.default_rng(2), 4)
    X[1, 0] = np.nan
    c = comp.clearance(X)
    assert np.isnan(c[1]) and np.isfinite(c[[0, 2, 3]]).all()
    assert np.isnan(comp.state.kernel.clearance(X[1:2], comp.state.static_slots)[0])
    # the C edge loop: a motion whose samples are NaN is not certified; neither is one given no interval
    k, slots = comp.state.kernel, comp.state.static_slots
    dX = np.full((2, model.nx), np.nan)
    fail, lower, n = k.check_edges(X[[0, 2]], dX, np.array([30.0, 30.0]), np.array([1, 0]), slots, 0.0, 1.5, True)
    assert fail[0] == 0.0 and fail[1] == 0.0 and n > 0 and lower[1] == -np.inf


def moving_scene(n, rng):
    """n spheres near the robot with linear and breathing motions."""
    obs = []
    for i in range(n):
        c = rng.uniform([-120, -120, 100], [120, 120, 420])
        obs.append(
            Obstacle(
                name=f"o{i}",
                center=tuple(c),
                radius=float(rng.uniform(15, 40)),
                amplitude=float(rng.uniform(0, 8)),
                omega=1.3,
                to=tuple(c + rng.uniform(-60, 60, 3)),
                duration=2.0,
                profile=("linear", "sin", "cos")[i % 3],
            )
        )
    return Scene(obstacles=tuple(obs), safety_distance=5.0)


def test_moving_obstacles_over_windows_agree(model, kernel_cache):
    # (not parametrized: the CI policy test names tests that need a compiler by function)
    for n_obstacles in (1, 3, 7, 15):
        rng = np.random.default_rng(n_obstacles)
        scene = moving_scene(n_obstacles, rng)
        # exact lower bounds need every obstacle in every sample (tests/test_broad_phase.py: with the broad
        # phase, the same verdicts)
        comp, interp = validators(model, scene, kernel_cache, broad_phase=False)
        X = random_configs(comp, rng, 300)
        lo = rng.uniform(0, 3, len(X))
        hi = lo + rng.uniform(0, 0.5, len(X))
        np.testing.assert_allclose(comp.clearance(X, lo, hi), interp.clearance(X, lo, hi), rtol=0, atol=TOL)
        # the windows' swept spheres computed in C are Scene.swept_spheres bit for bit (a time origin too)
        k = comp.state.kernel
        for sc in (scene, replace(scene, time_origin=0.7)):
            slots = packing.pack(*sc.swept_spheres(lo, hi), sc.n_obstacles)
            got = k.clearance_windows(X, sc.motion_table(), sc.time_origin, lo, hi)
            np.testing.assert_array_equal(got, k.clearance(X, slots))
        # edge checks and their certified fractions are the same too
        XA, XB = X[:60], X[60:120]
        fa, la = comp.check_edges(XA, XB, lo[:60], hi[:60])
        fb, lb = interp.check_edges(XA, XB, lo[:60], hi[:60])
        np.testing.assert_array_equal(fa, fb)
        np.testing.assert_allclose(la, lb, rtol=0, atol=TOL)


def test_moving_edge_check_in_c_is_the_numpy_loop(model, kernel_cache):
    """Among moving, breathing obstacles the C refinement loop (swept spheres per time window computed in C)
    returns what the numpy loop returns with the kernel's clearances, bit for bit, in both modes."""
    for n_obstacles in (1, 4, 9):
        rng = np.random.default_rng(40 + n_obstacles)
        scene = replace(moving_scene(n_obstacles, rng), time_origin=0.7)
        # without the broad phase the C loop returns the numpy loop's lower bounds too
        # (tests/test_broad_phase.py: with it, the same verdicts)
        comp = MotionValidator(model, scene, kernels=Kernels(kernel_cache), broad_phase=False)
        loop = MotionValidator(model, scene, kernels=Kernels(kernel_cache))
        loop.compiled_loop = False
        assert comp.state.kernel is not None and not comp.static
        XA, XB = comp.sample(rng, 120), comp.sample(rng, 120)
        XB[:15] = XA[:15] + rng.normal(scale=0.05, size=(15, model.nx))  # short motions
        XB[15:25] = XA[15:25]  # waits: certified piece by piece in time
        TA = rng.uniform(0.0, 3.0, len(XA))
        TB = TA + rng.uniform(0.0, 4.0, len(XA))
        TB[30:35] = TA[30:35]  # no time passes
        for prefix in (True, False):
            n0, n1 = comp.n_samples, loop.n_samples
            fc, lc = comp.check_edges(XA, XB, TA, TB, prefix=prefix)
            fl, ll = loop.check_edges(XA, XB, TA, TB, prefix=prefix)
            np.testing.assert_array_equal(fc, fl)
            np.testing.assert_array_equal(lc, ll)
            assert comp.n_samples - n0 == loop.n_samples - n1 > 0
        assert (fc < 1).any() and (fc == 1).any()  # both outcomes occur
    # a non-finite time is refused by the numpy path's check, with the field named
    with pytest.raises(InputError, match="t0"), np.errstate(invalid="ignore"):
        comp.check_edges(XA[:2], XB[:2], np.array([0.0, np.inf]), np.array([1.0, 2.0]))


def test_padding_slots_are_inert_and_one_library_serves_every_count(model, kernel_cache):
    k = ValidityKernel.load(model, 15, kernel_cache)
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (50, model.nx)) * [1, 1, 1, 1, 50]
    P = model.points(X, 15)
    for m in (0, 1, 3, 7, 31):
        centers = rng.uniform(-150, 150, (m, 3)) + np.array([0.0, 0.0, 250.0])
        radii = rng.uniform(5, 50, m)
        ref = numpy_chord_clearance(P, centers, radii)
        for slots in (m, packing.slot_count(m), 64):
            d = k.clearance(X, packing.pack(centers, radii, slots))
            np.testing.assert_allclose(d, ref, rtol=0, atol=1e-8)
        # per-configuration slots: each row its own spheres (here all the same)
        per = np.tile(packing.pack(centers, radii, packing.slot_count(m)), (len(X), 1))
        np.testing.assert_allclose(k.clearance(X, per), ref, rtol=0, atol=1e-8)
    with pytest.raises(ValueError, match="slots"):
        k.clearance(X, np.zeros(7))


def test_identical_plans_for_the_same_seed(model, kernel_cache):
    for problem_file in ("paper_static.toml", "paper_dynamic.toml"):
        identical_plans(model, kernel_cache, problem_file)


def identical_plans(model, kernel_cache, problem_file):
    """Plans of seeds 0 and 1 with the compiled and the interpreted checks: the same, bit for bit."""
    problem = Problem.load(PROBLEMS / problem_file)
    scene = problem.options(Scene, "scene")
    options = problem.options(PlannerOptions, "planner").with_(algorithm="cspace", time_limit=600.0)
    task = problem.task
    plans = []
    for compiled in (True, False):
        # the compiled planner's kernels come from the test's cache (a context built with injected kernels)
        kernels = Kernels(kernel_cache) if compiled else None
        # the IK projection on the numpy loop on both sides: the compiled one stops each seed on its own
        # (tests/test_compiled_ik.py); this test is about the checks
        opts = options.with_(check={"compiled": compiled}, ik={"compiled": False})
        context = PlanningContext(model, scene, opts, kernels=kernels)
        planner = BUILTIN.create("cspace", context)
        assert (planner.validator.state.kernel is not None) == compiled
        res = [
            planner.plan(task.goal, start_tip=task.start, seed=s, goal_tolerance=task.goal_tolerance) for s in (0, 1)
        ]
        plans.append(res)
    for a, b in zip(*plans, strict=True):
        assert a.status == b.status and a.is_success()
        np.testing.assert_array_equal(a.configs, b.configs)
        np.testing.assert_array_equal(a.t, b.t)


def test_cache_reused_for_the_same_robot_and_rebuilt_when_it_changes(tmp_path, robot):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    text = (PROBLEMS / "robots" / "cdsr2.toml").read_text()
    path = tmp_path / "r.toml"
    path.write_text(text)
    cache = BuildCache(tmp_path / "cache")
    k1 = ValidityKernel.load(Model(load_robot(path)), 6, cache)
    assert cache.builds == 1
    # the same file, read again by another process (a new cache object): reused
    again = BuildCache(tmp_path / "cache")
    assert ValidityKernel.load(Model(load_robot(path)), 6, again).library == k1.library and again.builds == 0
    # a comment or the description does not change the code: reused
    path.write_text("# a note\n" + text.replace('description = "Two', 'description = "2'))
    assert ValidityKernel.load(Model(load_robot(path)), 6, again).library == k1.library and again.builds == 0
    # a longer first segment is another robot: rebuilt, and it computes the new robot's points
    path.write_text(text.replace("length = 200.0               # mm", "length = 230.0               # mm"))
    changed = Model(load_robot(path))
    k2 = ValidityKernel.load(changed, 6, again)
    assert again.builds == 1 and k2.library != k1.library
    X = np.zeros((1, changed.nx))
    assert k2.points(X)[0, -1, 2] == pytest.approx(430.0) and k1.points(X)[0, -1, 2] == pytest.approx(400.0)
    assert kernel_key(changed, 6) != kernel_key(Model(robot), 6)


def test_corrupt_kernel_is_rebuilt_not_loaded(tmp_path, model):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    cache = BuildCache(tmp_path)
    lib = ValidityKernel.load(model, 4, cache).library
    data = bytearray(lib.read_bytes())
    data[len(data) // 2] ^= 0xFF
    # replaced, not rewritten in place: this process has the original mapped (as a damaged disk or another
    # program would leave it: a new file under the same name)
    tmp = tmp_path / "bad.so"
    tmp.write_bytes(bytes(data))
    tmp.replace(lib)
    fresh = BuildCache(tmp_path)
    k = ValidityKernel.load(model, 4, fresh)
    assert fresh.builds == 1 and k.library.parent == lib.parent and k.library.read_bytes() != bytes(data)
    np.testing.assert_allclose(k.points(np.zeros((1, model.nx)))[0], model.points(np.zeros(model.nx), 4), atol=TOL)


def test_without_a_compiler_the_interpreted_path_runs_and_says_so_once(tmp_path, model):
    problem = Problem.load(PROBLEMS / "paper_static.toml")
    scene = problem.options(Scene, "scene")
    out = io.StringIO()
    kernels = Kernels(BuildCache(tmp_path, compiler=None, notice=out))
    v1 = MotionValidator(model, scene, kernels=kernels)
    v2 = MotionValidator(model, replace(scene, safety_distance=6.0), kernels=kernels, check_points=9)
    assert v1.state.kernel is None and v2.state.kernel is None
    X = v1.sample(np.random.default_rng(1), 20)
    ref = MotionValidator(model, scene, compiled=False).clearance(X)
    np.testing.assert_array_equal(v1.clearance(X), ref)
    assert len(out.getvalue().splitlines()) == 1 and list(tmp_path.iterdir()) == []


def test_build_command_builds_lists_and_clears_and_commands_reuse_it(tmp_path, monkeypatch, capsys, model):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    monkeypatch.setenv("CRTRAJ_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(build_use_case, "default_check_points", lambda: [])  # only what the test asks for
    assert main(["build", "--check-points", "5"]) == 0
    assert "5 check points" in capsys.readouterr().out
    (entry,) = BuildCache(tmp_path).entries()
    assert entry.valid
    # a command's validator (its own cache object, as in a new process) loads it and builds nothing
    kernels = Kernels(BuildCache())
    v = MotionValidator(model, Scene(), check_points=5, kernels=kernels)
    assert v.state.kernel.library.parent == entry.path and kernels.build_cache.builds == 0
    assert main(["build", "--list"]) == 0
    listed = capsys.readouterr().out
    assert "1 entries" in listed and entry.path.name in listed and " ok" in listed
    assert main(["build", "--clear"]) == 0 and BuildCache(tmp_path).entries() == []
    capsys.readouterr()
    assert main(["build", "--check-points", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--check-points" in err[0]
    # a cache folder that cannot be made (its parent is a file): one line, exit 2
    (tmp_path / "afile").write_text("x")
    monkeypatch.setenv("CRTRAJ_CACHE_DIR", str(tmp_path / "afile" / "cache"))
    assert main(["build", "--check-points", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "build cache" in err[0]
