"""Cosserat-rod statics (crtraj.model.cosserat._statics) against closed forms, and the PCC comparison tool."""

from __future__ import annotations

import dataclasses
import io
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import require_tool

from crtraj.app.lab import compare_models, sample_configs
from crtraj.core.build_cache import BuildCache
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import load_robot
from crtraj.model.cosserat._cables import CableDrivenRod
from crtraj.model.cosserat._drive import RodDrive
from crtraj.model.cosserat._map import pcc_nodes, segment_moments, tensions_for_bending
from crtraj.model.cosserat._statics import NO_LOAD, CosseratRod, RodLoad
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot, Segment

ROOT = Path(__file__).resolve().parent.parent
CDSR2 = ROOT / "problems" / "robots" / "cdsr2.toml"
L = 100.0  # mm, the one-segment test rod
RC = 2.5  # mm, its cable radius


@pytest.fixture(scope="module")
def mech() -> Mechanics:
    return Mechanics(steps=20)


@pytest.fixture(scope="module")
def one(mech: Mechanics) -> CosseratRod:
    """One 100 mm segment, cable 1 at angle 0 (+x)."""
    return CosseratRod(Robot("one", RC, (Segment(L),)), mech)


@pytest.fixture(scope="module")
def cdsr2() -> Robot:
    return load_robot(CDSR2)


def _arc_tip(kappa: float, stretch: float, length: float) -> np.ndarray:
    """Tip of the extensible rod with constant strains u = kappa e_y (rad per mm of undeformed length)
    and v = stretch e_3: it turns through kappa * length on a circle of radius stretch / kappa, toward +x."""
    a = kappa * length
    return (stretch / kappa) * np.array([1.0 - math.cos(a), 0.0, math.sin(a)])


def test_one_tendon_gives_the_exact_circular_arc(one: CosseratRod, mech: Mechanics) -> None:
    """One tendon along a straight path: an arc of curvature tau r / EI, compressed by tau / EA."""
    tau = 20.0
    sol = one.solve([tau, 0.0, 0.0], NO_LOAD)
    assert sol.is_success()
    kappa = tau * RC / mech.bending_stiffness
    stretch = 1.0 - tau / (mech.youngs_modulus * mech.area)
    expected = _arc_tip(kappa, stretch, L)
    assert np.linalg.norm(sol.tip - expected) <= 1e-6 * np.linalg.norm(expected)
    # every node lies on that circle (centre (stretch / kappa, 0, 0))
    radius = np.linalg.norm(sol.points - np.array([stretch / kappa, 0.0, 0.0]), axis=1)
    np.testing.assert_allclose(radius, stretch / kappa, rtol=1e-6)
    np.testing.assert_allclose(sol.points[:, 1], 0.0, atol=1e-9)


def test_tendon_at_ninety_degrees_bends_toward_y(mech: Mechanics) -> None:
    """The bending direction follows the tendon's angle: cable 1 at pi/2 bends the rod toward +y."""
    rod = CosseratRod(Robot("one_y", RC, (Segment(L, cable_phase=math.pi / 2),)), mech)
    tau = 10.0
    sol = rod.solve([tau, 0.0, 0.0], NO_LOAD)
    kappa = tau * RC / mech.bending_stiffness
    ex = _arc_tip(kappa, 1.0 - tau / (mech.youngs_modulus * mech.area), L)
    np.testing.assert_allclose(sol.tip, [0.0, ex[0], ex[2]], rtol=1e-6, atol=1e-9)


def test_zero_tension_is_straight(one: CosseratRod) -> None:
    """No tension, no load: the straight rod of the undeformed length."""
    sol = one.solve([0.0, 0.0, 0.0], NO_LOAD)
    np.testing.assert_allclose(sol.points[:, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(sol.points[:, 2], np.linspace(0.0, L, 21), atol=1e-12)


def test_equal_tensions_compress_axially(one: CosseratRod, mech: Mechanics) -> None:
    """Equal tensions in the three tendons: straight, shortened by 3 T L / EA."""
    tau = 15.0
    sol = one.solve([tau, tau, tau], NO_LOAD)
    ea = mech.youngs_modulus * mech.area
    np.testing.assert_allclose(sol.tip[:2], 0.0, atol=1e-10)
    assert sol.tip[2] == pytest.approx(L * (1.0 - 3.0 * tau / ea), rel=1e-12)
    np.testing.assert_allclose(sol.base_force, [0.0, 0.0, -3.0 * tau], atol=1e-9)


@pytest.mark.parametrize("force", [1e-3, 1e-2])
def test_small_tip_load_matches_beam_theory(one: CosseratRod, mech: Mechanics, force: float) -> None:
    """A cantilever under a small tip load: F L^3 / 3EI + F L / GA, up to the geometric nonlinearity
    (relative order (F L^2 / EI)^2)."""
    ei = mech.bending_stiffness
    ga = mech.shear_modulus * mech.area
    sol = one.solve([0.0, 0.0, 0.0], RodLoad(tip_force=(force, 0.0, 0.0), distributed=(0.0, 0.0, 0.0)))
    linear = force * L**3 / (3.0 * ei) + force * L / ga
    assert abs(sol.tip[0] / linear - 1.0) < (force * L**2 / ei) ** 2
    # the base reacts the load: internal force F, moment L x F about the base
    np.testing.assert_allclose(sol.base_force, [force, 0.0, 0.0], atol=1e-9)  # the solve tolerance
    assert sol.base_moment[1] == pytest.approx(force * L, rel=1e-3)


def test_halving_the_step_changes_the_tip_by_less_than_1e_4_mm(cdsr2: Robot) -> None:
    """Step convergence on the two-segment robot with gravity: 10 vs 20 steps per segment."""
    base = Mechanics.from_robot(cdsr2)
    tau = np.array([6.0, 0.0, 1.0, 0.0, 4.0, 0.0])
    tips = [CosseratRod(cdsr2, base.with_(steps=n)).solve(tau, RodLoad()).tip for n in (10, 20)]
    assert np.all(np.isfinite(tips))
    gap = np.linalg.norm(tips[0] - tips[1])
    assert 0.0 < gap < 1e-4


def test_warm_start_needs_fewer_iterations(one: CosseratRod) -> None:
    """Solving again near the last solution takes fewer Newton iterations than from the straight rod."""
    cold = one.solve([30.0, 5.0, 0.0], NO_LOAD, warm=False)
    warm = one.solve([30.0, 5.0, 0.0], NO_LOAD)
    assert cold.is_success() and warm.is_success()
    assert warm.iterations < cold.iterations
    np.testing.assert_allclose(warm.points, cold.points, atol=1e-8)


def test_solve_path_unpolished_stays_within_the_tolerance_of_cold_solves(mech: Mechanics) -> None:
    """A path of nearby tensions solved by `solve_path` without polish (each solve stops once its residual is
    within the 1e-6 N tolerance): every shape converged, its residual within the tolerance, its points within
    1e-3 mm of an independent cold full-Newton solve; bad paths are one-line input errors."""
    rod = CosseratRod(Robot("one", RC, (Segment(L),)), mech.with_(tolerance=1e-6))
    ref = CosseratRod(Robot("one", RC, (Segment(L),)), mech, compiled=False)
    s = np.linspace(0.0, 1.0, 40)[:, None]
    path = np.hstack([20.0 * s, 5.0 * s**2, 3.0 * (1.0 - s)])
    sols = rod.solve_path(path, NO_LOAD, polish=1.0)
    assert all(sol.is_success() and sol.residual <= 1e-6 for sol in sols)
    for tau, sol in zip(path[::7], sols[::7], strict=True):
        np.testing.assert_allclose(sol.points, ref.solve(tau, NO_LOAD, warm=False).points, atol=1e-3)
    with pytest.raises(InputError, match="a tendon cannot push"):
        rod.solve_path([[1.0, 0.0, 0.0], [1.0, -1.0, 0.0]])
    with pytest.raises(InputError, match=r"tensions: expected shape \(N, 3\)"):
        rod.solve_path([1.0, 0.0, 0.0])


def test_a_tension_that_breaks_the_solve_is_reported_not_shaped(one: CosseratRod) -> None:
    """1000 N on one tendon (40 rad of bending in 100 mm): a failed status and no shape."""
    sol = one.solve([1000.0, 0.0, 0.0], NO_LOAD, warm=False)
    assert not sol.is_success()
    assert np.all(np.isnan(sol.points))


def test_a_shape_too_coarse_for_the_steps_is_reported(one: CosseratRod) -> None:
    """100 N bends the rod 4.1 rad over 20 steps (> 0.2 rad a step): under_resolved, no shape."""
    sol = one.solve([100.0, 0.0, 0.0], NO_LOAD, warm=False)
    assert sol.status == "under_resolved"
    assert np.all(np.isnan(sol.points))


def test_bad_tensions_are_one_line_input_errors(one: CosseratRod) -> None:
    """A negative tension, the wrong count or NaN name the tension."""
    with pytest.raises(InputError, match=r"tensions\[1\]: a tendon cannot push"):
        one.solve([1.0, -1.0, 0.0])
    with pytest.raises(InputError, match="tensions"):
        one.solve([1.0, 0.0])
    with pytest.raises(InputError, match="tensions"):
        one.solve([1.0, float("nan"), 0.0])


@pytest.mark.parametrize(
    ("table", "field"),
    [
        ({"youngs_modulus": -1.0}, "robot.mechanics.youngs_modulus: must be > 0"),
        ({"shear_modulus": 0.0}, "robot.mechanics.shear_modulus: must be > 0"),
        ({"gravity": [0.0, -9.81]}, "robot.mechanics.gravity"),
        ({"steps": 0}, "robot.mechanics.steps"),
        ({"tendon_stiffness": -5.0}, "robot.mechanics.tendon_stiffness: must be > 0"),
        ({"stiffness": 1.0}, "robot.mechanics.stiffness"),
        ({"actuation": "force"}, "robot.mechanics.actuation: must be one of cable_length, tension; got 'force'"),
    ],
)
def test_bad_mechanics_tables_name_the_field(table: dict, field: str) -> None:
    """Each bad [robot.mechanics] value is one InputError naming its key."""
    with pytest.raises(InputError, match=field.replace(".", r"\.")):
        Mechanics.from_table(Table(table, "robot.mechanics"))


def test_negative_modulus_in_python_is_refused() -> None:
    """A Mechanics built in Python is checked like the file."""
    with pytest.raises(InputError, match="youngs_modulus: must be > 0"):
        Mechanics(youngs_modulus=-60_000.0)


def test_robot_file_carries_mechanics_outside_its_dict(cdsr2: Robot) -> None:
    """cdsr2.toml's [robot.mechanics] parses; the robot's dict (written into results) does not change."""
    mech = Mechanics.from_robot(cdsr2)
    assert mech.youngs_modulus == 60_000.0 and mech.gravity == (0.0, 0.0, -9.80665)
    assert "mechanics" not in cdsr2.to_dict()
    bare = dataclasses.replace(cdsr2, mechanics=None)
    with pytest.raises(InputError, match=r"robot\.mechanics: missing"):
        Mechanics.from_robot(bare)


def test_weight_per_length_adds_backbone_and_discs() -> None:
    """(rho A + m_disc / spacing) g, in N/mm, from the file's units."""
    m = Mechanics(backbone_radius=0.5, backbone_density=8000.0, disc_mass=0.5, disc_spacing=5.0, gravity=(0, 0, -10))
    per_mm = 8000.0 * 1e-9 * math.pi * 0.25 + 0.5e-3 / 5.0
    np.testing.assert_allclose(m.weight_per_length(), [0.0, 0.0, -10.0 * per_mm], rtol=1e-14)


def test_bending_map_reproduces_the_segment_moments(cdsr2: Robot) -> None:
    """Tensions of the map: non-negative, the smallest per segment zero, and their moments r tau (-sin a,
    cos a) summed over the tendons passing each segment equal EI times its curvature."""
    mech = Mechanics.from_robot(cdsr2)
    ub = np.array([[0.3, -0.2], [-0.5, 0.4]])
    tau = tensions_for_bending(cdsr2, mech, ub)
    assert np.all(tau >= 0.0)
    np.testing.assert_allclose(tau.reshape(2, 3).min(axis=1), 0.0, atol=1e-12)
    for k in range(2):
        total = np.zeros(2)
        for j in range(k, 2):
            a = cdsr2.cable_angles(j)
            total += cdsr2.cable_radius * (tau[3 * j : 3 * j + 3] @ np.stack([-np.sin(a), np.cos(a)], axis=1))
        kappa = np.array([-ub[k, 1], ub[k, 0]]) / cdsr2.segments[k].length
        np.testing.assert_allclose(total, mech.bending_stiffness * kappa, rtol=1e-12)
    np.testing.assert_allclose(
        segment_moments(cdsr2, mech, ub)[1], mech.bending_stiffness * np.array([-0.4, -0.5]) / 200
    )
    many = np.stack([ub, -ub, np.zeros_like(ub)])  # many at once: each row as alone
    np.testing.assert_array_equal(
        tensions_for_bending(cdsr2, mech, many), [tensions_for_bending(cdsr2, mech, u) for u in many]
    )


def test_without_gravity_the_rod_follows_pcc_and_gravity_pulls_it_away(cdsr2: Robot) -> None:
    """Weightless, the rod held by the mapped tensions is within 1 mm of the PCC backbone (only the
    axial compression and tendon geometry differ); the discrepancy grows strictly with the mass."""
    configs = sample_configs(cdsr2, 3, np.random.default_rng(1))
    base = Mechanics.from_robot(cdsr2)
    body = []
    for disc_mass in (0.0, 0.1, 0.3, 1.0):
        cmp = compare_models(cdsr2, base.with_(disc_mass=disc_mass), configs)
        assert cmp.failures == 0
        assert np.all(cmp.body_free < 1.0)
        body.append(cmp.body_gravity)
    body = np.array(body)
    assert np.all(np.diff(body, axis=0) > 0.0)
    weightless = compare_models(cdsr2, base.with_(backbone_density=0.0, disc_mass=0.0), configs)
    np.testing.assert_allclose(weightless.body_gravity, weightless.body_free, atol=1e-9)


def _with_actuation(robot: Robot, mode: str) -> Robot:
    """`robot` with ``[robot.mechanics] actuation = mode``."""
    return dataclasses.replace(robot, mechanics={**dict(robot.mechanics or {}), "actuation": mode})


def _independent_rod(robot: Robot, mech: Mechanics, x: np.ndarray, mode: str) -> np.ndarray:
    """The rod's backbone (mm, base at the origin) at configuration x with gravity, solved cold by the
    interpreted rootfinders: under the tensions that hold x's bending on a weightless rod (1 N pretension),
    or under the commanded cable lengths of `RodDrive.lengths` (its length map is checked against PCC in
    test_rod_plant)."""
    if mode == "tension":
        tau = tensions_for_bending(robot, mech, robot.bending(x), 1.0)
        sol = CosseratRod(robot, mech, compiled=False).solve(tau, RodLoad(), warm=False)
        assert sol.is_success()
        return sol.points
    ell = RodDrive(robot, mech.with_(actuation="cable_length"), pretension=1.0).lengths(robot.cables(x))
    cab = CableDrivenRod(robot, mech, compiled=False).solve(ell, RodLoad())
    assert cab.is_success()
    return cab.rod.points


@pytest.mark.parametrize("mode", ["cable_length", "tension"])
def test_the_robot_files_actuation_mode_decides_the_rod(cdsr2: Robot, mode: str) -> None:
    """`RodDrive` and `compare_models` solve the rod in the robot file's actuation mode: the shapes equal
    independent cold solves of that mode's statics, the mode is reported, and the two modes' shapes under
    gravity are millimetres apart (so a consumer that ignored the mode would fail this test)."""
    robot = _with_actuation(cdsr2, mode)
    mech = Mechanics.from_robot(robot)
    assert mech.actuation == mode and Mechanics.from_robot(cdsr2).actuation == "cable_length"  # the default
    drive = RodDrive(robot)
    assert drive.actuation == mode and mode in drive.describe()
    configs = sample_configs(cdsr2, 2, np.random.default_rng(6))
    configs[:, -1] = 0.0  # the comparison puts the base at the origin
    cmp = compare_models(robot, mech, configs)
    assert cmp.actuation == mode and cmp.failures == 0
    other = "tension" if mode == "cable_length" else "cable_length"
    for i, x in enumerate(configs):
        mine = _independent_rod(cdsr2, mech, x, mode)
        np.testing.assert_allclose(drive.shape_config(x).points, mine, atol=1e-6)
        pcc = pcc_nodes(Model(cdsr2), x, mech.steps)
        assert cmp.tip_gravity[i] == pytest.approx(np.linalg.norm(mine[-1] - pcc[-1]), abs=1e-6)
        assert cmp.body_gravity[i] == pytest.approx(np.max(np.linalg.norm(mine - pcc, axis=1)), abs=1e-6)
        assert np.linalg.norm(_independent_rod(cdsr2, mech, x, other)[-1] - mine[-1]) > 1.0


def test_sample_configs_are_within_limits_and_seeded(cdsr2: Robot) -> None:
    """Seeded, within the robot's limits."""
    a = sample_configs(cdsr2, 5, np.random.default_rng(3))
    b = sample_configs(cdsr2, 5, np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (5, cdsr2.nx) and np.all(cdsr2.limit_violation(a) <= 0.0)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "crtraj.cli", *args], capture_output=True, text=True, cwd=ROOT)


def test_cli_compare_reports_and_plots(tmp_path: Path) -> None:
    """`crtraj model compare` prints both cases' spreads and the robot file's actuation mode, and writes the PNG."""
    plot = tmp_path / "cmp.png"
    out = _cli("model", "compare", str(CDSR2), "--samples", "2", "--seed", "4", "--plot", str(plot))
    assert out.returncode == 0, out.stderr
    assert "no gravity: tip RMS" in out.stdout and "gravity:    tip RMS" in out.stdout
    assert "(actuation cable_length)" in out.stdout  # cdsr2.toml names no mode: the position servos' default
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    tension = tmp_path / "tension.toml"
    tension.write_text(CDSR2.read_text().replace("[robot.mechanics]", '[robot.mechanics]\nactuation = "tension"'))
    out = _cli("model", "compare", str(tension), "--samples", "1")
    assert out.returncode == 0, out.stderr
    assert "(actuation tension)" in out.stdout


def test_cli_compare_bad_inputs_are_one_line_and_touch_nothing(tmp_path: Path) -> None:
    """--samples 0, the robot file as --plot, a robot without [robot.mechanics]: exit 2, one line."""
    robot = tmp_path / "r.toml"
    robot.write_text(CDSR2.read_text())
    before = robot.read_bytes()
    bare = tmp_path / "bare.toml"
    bare.write_text(CDSR2.read_text().split("[robot.mechanics]")[0])
    force = tmp_path / "force.toml"
    force.write_text(CDSR2.read_text().replace("[robot.mechanics]", '[robot.mechanics]\nactuation = "force"'))
    cases = [
        ([], str(force), "robot.mechanics.actuation: must be one of cable_length, tension; got 'force'"),
        (["--samples", "0"], str(robot), "--samples: must be in"),
        (["--plot", str(robot)], str(robot), "--plot:"),
        ([], str(bare), "robot.mechanics: missing"),
    ]
    for extra, path, message in cases:
        out = _cli("model", "compare", path, *extra)
        assert out.returncode == 2
        assert out.stderr.count("\n") == 1 and message in out.stderr
    assert robot.read_bytes() == before


@pytest.fixture(scope="module")
def cabled(mech: Mechanics) -> CableDrivenRod:
    return CableDrivenRod(Robot("one", RC, (Segment(L),)), mech)


def test_one_shortened_tendon_takes_the_closed_form_tension(cabled: CableDrivenRod, mech: Mechanics) -> None:
    """Tendon 1 shortened by d, the others paid out: they go slack, and tendon 1's path on the arc,
    L (1 - tau / EA - tau r^2 / EI), equals its stretched length l (1 + tau / EA_t)."""
    ea, ei, kt = mech.youngs_modulus * mech.area, mech.bending_stiffness, mech.tendon_stiffness
    for ell in (99.9, 99.0):
        sol = cabled.solve([ell, L + 5.0, L + 5.0])
        assert sol.is_success()
        tau = (L - ell) / (L / ea + L * RC**2 / ei + ell / kt)
        np.testing.assert_allclose(sol.tensions, [tau, 0.0, 0.0], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(sol.slack, [False, True, True])
        assert np.all(sol.paths[1:] < L + 5.0)
        expected = _arc_tip(tau * RC / ei, 1.0 - tau / ea, L)
        assert np.linalg.norm(sol.rod.tip - expected) <= 1e-6 * L


def test_paid_out_tendons_are_all_slack(cabled: CableDrivenRod) -> None:
    """Every tendon longer than the rod: no tension, the straight rod."""
    sol = cabled.solve([L + 1.0, L + 2.0, L + 1.0])
    np.testing.assert_array_equal(sol.tensions, 0.0)
    assert np.all(sol.slack)
    np.testing.assert_allclose(sol.rod.tip, [0.0, 0.0, L], atol=1e-12)


def test_equally_shortened_tendons_share_the_load(cabled: CableDrivenRod, mech: Mechanics) -> None:
    """All three shortened by d: equal tensions with L (1 - 3 tau / EA) = (L - d)(1 + tau / EA_t)."""
    d = 0.1
    ea, kt = mech.youngs_modulus * mech.area, mech.tendon_stiffness
    tau = d / (3.0 * L / ea + (L - d) / kt)
    sol = cabled.solve([L - d] * 3)
    np.testing.assert_allclose(sol.tensions, tau, rtol=1e-9)
    assert sol.rod.tip[2] == pytest.approx(L * (1.0 - 3.0 * tau / ea), rel=1e-12)


def test_bad_lengths_are_one_line_input_errors(cabled: CableDrivenRod) -> None:
    """A non-positive or missing length names it."""
    with pytest.raises(InputError, match=r"lengths\[2\]: must be > 0"):
        cabled.solve([L, L, 0.0])
    with pytest.raises(InputError, match="lengths"):
        cabled.solve([L, L])


def test_compiled_path_finds_the_interpreted_root_and_its_jacobian_is_exact(cdsr2: Robot) -> None:
    """The generated C (chord Newton, warm-started along a sequence) gives the interpreted rootfinder's shapes,
    and its Jacobian matches central differences of its own residual."""
    require_tool("cc", "gcc", "clang", hint="the compiled Cosserat path")
    mech = Mechanics.from_robot(cdsr2)
    fast, slow = CosseratRod(cdsr2, mech), CosseratRod(cdsr2, mech, compiled=False)
    assert fast.compiled and not slow.compiled
    rng = np.random.default_rng(3)
    tau = np.array([6.0, 0.0, 1.0, 0.0, 4.0, 0.0])
    for step in range(12):  # a ramp (the secant predictor), then random steps, then a jump
        tau = tau + (0.3 if step < 4 else rng.uniform(-0.5, 0.5, 6) if step < 11 else 3.0)
        tau = np.maximum(tau, 0.0)
        a, b = fast.solve(tau, RodLoad()), slow.solve(tau, RodLoad(), warm=False)
        assert a.is_success() and b.is_success()
        np.testing.assert_allclose(a.points, b.points, atol=1e-7)
        assert a.residual <= mech.tolerance
    p = np.concatenate([tau, mech.weight_per_length(), np.zeros(6)])
    w = np.concatenate([a.base_force, a.base_moment]) + 0.01
    _, jac = fast._compiled.resjac(w, p)
    h = 1e-5
    fd = np.column_stack(
        [
            (fast._compiled.residual(w + h * e, p)[0] - fast._compiled.residual(w - h * e, p)[0]) / (2 * h)
            for e in np.eye(6)
        ]
    )
    # central differences err by about h^2 |r'''| (1e-6 here): far below any wrong entry's size
    np.testing.assert_allclose(np.asarray(jac), fd, rtol=1e-4, atol=1e-5 * np.abs(fd).max())


def test_compiled_cable_mode_finds_the_interpreted_root_and_its_jacobian_is_exact(cdsr2: Robot) -> None:
    """The cable-length mode in generated C (chord Newton on wrench and tensions) gives the interpreted
    rootfinder's shape (to 1e-7 mm), tensions (to 1e-7 N) and slack set along a sequence of commanded
    lengths with gravity (small steps, a slack tendon, a jump back), and its Jacobian dF/dz, with a mixed
    active set, matches central differences of its own residual."""
    require_tool("cc", "gcc", "clang", hint="the compiled Cosserat path")
    mech = Mechanics.from_robot(cdsr2)
    fast, slow = CableDrivenRod(cdsr2, mech), CableDrivenRod(cdsr2, mech, compiled=False)
    assert fast.compiled and not slow.compiled
    drive = RodDrive(cdsr2, mech, pretension=1.0)
    rng = np.random.default_rng(4)
    x = cdsr2.straight(0.0)
    slack_seen = False
    for step in range(10):
        x = x + np.concatenate([rng.uniform(-0.15, 0.15, x.size - 1), [0.0]])
        ell = drive.lengths(cdsr2.cables(x))
        if step in (5, 6):  # pay tendon 2 of segment 1 out by 2 mm: it goes slack
            ell[1] += 2.0
        a, b = fast.solve(ell, RodLoad()), slow.solve(ell, RodLoad())
        assert a.is_success() and b.is_success()
        np.testing.assert_array_equal(a.slack, b.slack)
        slack_seen |= bool(a.slack.any())
        np.testing.assert_allclose(a.rod.points, b.rod.points, atol=1e-7)
        np.testing.assert_allclose(a.tensions, b.tensions, atol=1e-7)
        assert a.rod.residual <= mech.tolerance
    assert slack_seen
    nt = fast.n_tendons
    taut = np.array([1.0, 0.0, 1.0, 1.0, 1.0, 0.0])
    q = np.concatenate([ell, taut, mech.weight_per_length(), np.zeros(6)])
    z = np.concatenate([a.rod.base_force, a.rod.base_moment, a.tensions]) + 0.01
    _, jac = fast._compiled.jacobian(z, q)
    h = 1e-5
    fd = np.column_stack(
        [
            (fast._compiled.residual(z + h * e, q)[0] - fast._compiled.residual(z - h * e, q)[0]) / (2 * h)
            for e in np.eye(6 + nt)
        ]
    )
    # central differences err by about h^2 |F'''|: far below any wrong entry's size
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-5 * np.abs(fd).max())
    np.testing.assert_array_equal(jac[6 + 1], np.eye(6 + nt)[6 + 1])  # a slack row: c = tau_i, nothing else


def test_cable_mode_without_a_compiler_falls_back_to_the_interpreter(mech: Mechanics, tmp_path: Path) -> None:
    """No C compiler: one notice line, the interpreted rootfinder, and still the closed-form tensions of
    three equally shortened tendons (test_equally_shortened_tendons_share_the_load)."""
    out = io.StringIO()
    rod = CableDrivenRod(
        Robot("one", RC, (Segment(L),)), mech, build_cache=BuildCache(tmp_path, compiler=None, notice=out)
    )
    assert not rod.compiled
    assert out.getvalue().count("\n") == 1 and "interpreted" in out.getvalue()
    d = 0.1
    tau = d / (3.0 * L / (mech.youngs_modulus * mech.area) + (L - d) / mech.tendon_stiffness)
    np.testing.assert_allclose(rod.solve([L - d] * 3).tensions, tau, rtol=1e-9)
