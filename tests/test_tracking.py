"""Tracking controller: LQR design, servo model, closed loop, limits, options."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import control
import numpy as np
import pytest
import scipy.linalg
from conftest import assert_same_multiset
from scipy.integrate import solve_ivp

from crtraj.control.tracking._controller import TrackingController
from crtraj.control.tracking._options import TrackingOptions
from crtraj.control.tracking._servo import ServoModel
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot, Segment

ROBOT_FILE = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot(ROBOT_FILE)


@pytest.fixture(scope="module")
def model(robot: Robot) -> Model:
    return Model(robot)


@pytest.fixture(scope="module")
def ctl(model: Model) -> TrackingController:
    return TrackingController(model)


def _hand_built_matrices(robot: Robot, o: TrackingOptions) -> tuple[np.ndarray, ...]:
    """A, B, Q, R of the design written out from the closed-form servo decay (no python-control)."""
    n, nx = robot.n_segments, robot.nx
    tau = np.append(np.full(2 * n, o.servo_tau), o.servo_tau_z)
    phi = np.exp(-o.dt / tau)
    A = np.zeros((2 * nx, 2 * nx))
    A[:nx, :nx] = np.diag(phi)
    A[:nx, nx:] = np.diag(1.0 - phi)
    A[nx:, nx:] = np.eye(nx)
    B = np.vstack([np.diag(1.0 - phi), np.eye(nx)])
    err = np.append(np.full(2 * n, o.bending_error_scale), o.z_error_scale)
    step = np.append(np.full(2 * n, o.max_cable_rate * o.dt / robot.cable_radius), o.max_z_rate * o.dt)
    Q = np.diag(np.concatenate([err**-2.0, np.zeros(nx)]))
    R = o.effort_weight * np.diag(step**-2.0)
    return A, B, Q, R


OPTION_CASES = [
    TrackingOptions(),
    TrackingOptions(dt=0.005, servo_tau=0.2, servo_tau_z=0.02),
    TrackingOptions(dt=0.1, effort_weight=50.0, bending_error_scale=0.05),
    TrackingOptions(dt=0.02, servo_tau=1e-3, servo_tau_z=1e-3, max_cable_rate=1.0, z_error_scale=5.0),
]


# ----------------------------------------------------------------------- design
@pytest.mark.parametrize("opts", OPTION_CASES)
def test_lqr_gain_stabilises_error_dynamics(model: Model, robot: Robot, opts: TrackingOptions) -> None:
    c = TrackingController(model, opts)
    A, B, _, _ = _hand_built_matrices(robot, opts)
    # the controller's (python-control) model equals the closed-form one
    d = c.design()
    np.testing.assert_allclose(d.A, A, atol=1e-12)
    np.testing.assert_allclose(d.B, B, atol=1e-12)
    lam = np.linalg.eigvals(A - B @ c.gain)
    assert np.max(np.abs(lam)) < 0.999
    # as multisets: sorting cannot pair a conjugate pair whose real parts differ in the last bit
    assert_same_multiset(lam, c.closed_loop_eigenvalues(), atol=1e-10)
    # the paper's K_P is symmetric positive definite
    kp = c.proportional_gain
    np.testing.assert_allclose(kp, kp.T, atol=1e-12)
    assert np.min(np.linalg.eigvalsh(kp)) > 0.0


@pytest.mark.parametrize("opts", OPTION_CASES)
def test_gain_matches_riccati_solution(model: Model, robot: Robot, opts: TrackingOptions) -> None:
    c = TrackingController(model, opts)
    A, B, Q, R = _hand_built_matrices(robot, opts)
    K = c.gain
    scale = max(1.0, float(np.max(np.abs(K))))
    # scipy's DARE
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K_are = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    assert np.max(np.abs(K - K_are)) <= 1e-8 * scale
    # control.dlqr called directly on the same matrices
    K_dlqr, _, _ = control.dlqr(A, B, Q, R)
    assert np.max(np.abs(K - K_dlqr)) <= 1e-8 * scale
    # hand-built Riccati value iteration
    Pi = Q.copy()
    for _ in range(20000):
        G = np.linalg.solve(R + B.T @ Pi @ B, B.T @ Pi @ A)
        P_next = Q + A.T @ Pi @ A - A.T @ Pi @ B @ G
        done = np.max(np.abs(P_next - Pi)) <= 1e-13 * max(1.0, float(np.max(np.abs(P_next))))
        Pi = P_next
        if done:
            break
    K_iter = np.linalg.solve(R + B.T @ Pi @ B, B.T @ Pi @ A)
    assert np.max(np.abs(K - K_iter)) <= 1e-8 * scale


def test_design_per_dt_is_cached_and_different(ctl: TrackingController) -> None:
    d1 = ctl.design(0.01)
    assert ctl.design(0.01) is d1
    assert not np.allclose(d1.K, ctl.gain)
    np.testing.assert_allclose(d1.phi[-1], math.exp(-0.01 / ctl.options.servo_tau_z), rtol=1e-13)


def test_steps_to_bound_on_a_defective_closed_loop(ctl: TrackingController) -> None:
    # a Jordan block has no eigenvector basis: the bound falls back to matrix powers
    Acl = np.array([[0.5, 1.0], [0.0, 0.5]])
    d = replace(ctl.design(), A=Acl, B=np.zeros((2, 1)), K=np.zeros((1, 2)))
    e0 = np.array([1.0, 1.0])
    k = d.steps_to(e0, 1e-6)
    norms = [np.linalg.norm(np.linalg.matrix_power(Acl, j), 2) * np.linalg.norm(e0) for j in range(k + 40)]
    assert norms[k - 1] > 1e-6
    assert max(norms[k:]) <= 1e-6


# ------------------------------------------------------------------------ servo
def test_servo_lag_discretisation_matches_closed_form(robot: Robot, ctl: TrackingController) -> None:
    servo = ServoModel(robot, 0.05, 0.12)
    for dt in (1e-3, 0.02, 0.3):
        expect = np.append(np.full(robot.nq - 1, math.exp(-dt / 0.05)), math.exp(-dt / 0.12))
        np.testing.assert_allclose(servo.decay(dt), expect, rtol=1e-15)
    # design decay from control.c2d equals exp(-dt/tau) per configuration coordinate
    o = ctl.options
    tau = np.append(np.full(robot.nx - 1, o.servo_tau), o.servo_tau_z)
    np.testing.assert_allclose(ctl.design().phi, np.exp(-o.dt / tau), rtol=1e-12)
    # repeated periods equal the continuous step response
    rng = np.random.default_rng(3)
    q0, qc = rng.normal(200, 3, robot.nq), rng.normal(200, 3, robot.nq)
    q = q0.copy()
    dt = 0.02
    for k in range(1, 11):
        q = servo.advance(q, qc, dt)
        np.testing.assert_allclose(q, qc + (q0 - qc) * np.exp(-k * dt / servo.tau), rtol=0, atol=1e-12)
    # and the ODE tau dq/dt = qc - q integrated numerically
    times = np.linspace(0.0, 0.05, 11)
    sol = solve_ivp(lambda t, y: (qc - y) / servo.tau, (0.0, 0.05), q0, t_eval=times, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(servo.trajectory(q0, qc, times), sol.y.T, atol=1e-8)
    np.testing.assert_allclose(servo.trajectory(q0, qc, [dt])[0], servo.advance(q0, qc, dt), atol=1e-13)


def test_servo_config_inverts_cable_map(robot: Robot, model: Model) -> None:
    servo = ServoModel(robot, 0.05, 0.1)
    x = np.random.default_rng(0).uniform(-0.5, 0.5, (7, robot.nx))
    np.testing.assert_allclose(servo.config(model.cables(x)), x, atol=1e-12)


# ------------------------------------------------------------------- closed loop
def _errors(ctl: TrackingController, run, ref: np.ndarray) -> np.ndarray:
    """Design error states (ref - x_k, ref - x_cmd_{k-1}) along a run."""
    x_cmd = np.vstack([run.x[:1], ctl.servo.config(run.q_command)])
    return np.hstack([ref - run.x, ref - x_cmd])


def test_linear_regime_follows_prediction_and_converges_in_bound(ctl: TrackingController) -> None:
    x0 = np.array([0.2, -0.1, 0.05, 0.1, -10.0])
    ref = x0 + np.array([0.002, -0.003, 0.001, 0.002, 0.05])
    steps = 120
    run = ctl.simulate(x0, ref, steps)
    assert not run.rate_limited.any() and not run.limited.any()
    E = _errors(ctl, run, ref)
    d = ctl.design()
    Acl = d.A - d.B @ d.K
    e = E[0]
    for k in range(steps + 1):
        np.testing.assert_allclose(E[k], e, atol=1e-11)
        e = Acl @ e
    tol = 1e-9
    bound = d.steps_to(E[0], tol)
    assert 0 < bound < steps
    assert np.all(np.linalg.norm(E[bound:], axis=1) <= tol)
    assert ctl.tip_error(run.x[-1], ref) < 1e-6


def test_large_offset_saturates_then_converges_in_predicted_steps(
    ctl: TrackingController, robot: Robot, model: Model
) -> None:
    x0 = robot.straight()
    ref = np.array([0.6, -0.4, -0.3, 0.5, -60.0])
    steps = 200
    run = ctl.simulate(x0, ref, steps)
    dt, o = ctl.options.dt, ctl.options
    rates = np.append(np.full(robot.nq - 1, o.max_cable_rate), o.max_z_rate)
    # no schedule can be faster than the slowest actuator at full rate
    ramp = np.max(np.abs(model.cables(ref) - model.cables(x0)) / (rates * dt))
    E = _errors(ctl, run, ref)
    tol = 1e-6
    assert np.all(np.linalg.norm(E[: math.floor(ramp)], axis=1) > tol)
    # saturation lasts about as long as that ramp
    k_sat = int(np.nonzero(run.rate_limited)[0][-1]) + 1
    assert ramp - 2 <= k_sat <= ramp + 5
    # from the end of saturation the linear bound holds
    bound = k_sat + ctl.design().steps_to(E[k_sat], tol)
    assert bound < steps
    assert np.all(np.linalg.norm(E[bound:], axis=1) <= tol)
    assert run.final_tip_error < 1e-6


def test_rate_and_actuation_limits_hold_on_every_step(model: Model, robot: Robot) -> None:
    rng = np.random.default_rng(11)
    lo, hi = robot.config_box()
    for mode in ("configuration", "tip"):
        o = TrackingOptions(mode=mode, max_cable_rate=4.0, max_z_rate=30.0)
        c = TrackingController(model, o)
        rates = np.append(np.full(robot.nq - 1, o.max_cable_rate), o.max_z_rate)
        x = np.array([0.3, 0.2, -0.1, 0.4, -50.0])
        q_cmd = c.initial_command(x)
        q_act = q_cmd.copy()
        ref = x.copy()
        n_rate = 0
        for k in range(300):
            if k % 25 == 0:  # jumps, some far outside the actuation limits
                ref = rng.uniform(1.4 * lo, 1.4 * hi)
            ref = ref + rng.normal(0.0, [0.02, 0.02, 0.02, 0.02, 2.0])
            xm = c.servo.config(q_act)
            cmd = c.step(xm, q_cmd, ref)
            assert np.all(np.abs(cmd.q - q_cmd) <= rates * o.dt * (1 + 1e-12))
            assert robot.limit_violation(c.servo.config(cmd.q))[0] <= 1e-9
            np.testing.assert_allclose(c.servo.config(cmd.q), cmd.x, atol=1e-10)
            n_rate += cmd.rate_limited
            q_cmd = cmd.q
            q_act = c.servo.advance(q_act, q_cmd, o.dt)
        assert n_rate > 50  # the limiter was exercised


def test_reference_outside_limits_stops_at_the_boundary(ctl: TrackingController, robot: Robot) -> None:
    lo_z = robot.z_range[0]
    run = ctl.simulate(robot.straight(), np.array([0.0, 0.0, 0.0, 0.0, lo_z - 60.0]), 300)
    assert np.all(run.x[:, -1] >= lo_z - 1e-9)
    assert abs(run.x[-1, -1] - lo_z) < 1e-6
    assert run.limited.any()
    # bending far beyond theta_max: the set-point ends on the boundary, never past it
    run = ctl.simulate(robot.straight(), np.array([5.0, 0.0, 0.0, 0.0, 0.0]), 300)
    v = robot.limit_violation(ctl.servo.config(run.q_command))
    assert np.all(v <= 1e-9)
    assert v[-1] > -1e-6


def test_feedforward_removes_ramp_lag(ctl: TrackingController) -> None:
    d = ctl.design()
    dt = ctl.options.dt
    rate = np.array([0.01, -0.005, 0.008, 0.0, 2.0])  # rad/s, mm/s: well below the rate limits
    n = 150
    ref = np.array([0.1, 0.1, -0.1, 0.0, -20.0]) + dt * np.arange(n)[:, None] * rate
    E = {}
    for ff in (False, True):
        run = ctl.simulate(ref[0], ref, feedforward=ff)
        assert not run.rate_limited.any()
        E[ff] = _errors(ctl, run, ref[np.minimum(np.arange(n + 1), n - 1)])
    # without feed-forward: the steady lag of e = (A - BK) e + (dr, dr)
    dr = np.concatenate([rate * dt, rate * dt])
    e_ss = np.linalg.solve(np.eye(10) - (d.A - d.B @ d.K), dr)
    np.testing.assert_allclose(E[False][100], e_ss, atol=1e-10)
    assert np.max(np.abs(e_ss[:5])) > 1e-2
    # with it (eq. 15 plus the servo-lag lead) the ramp is tracked exactly
    np.testing.assert_allclose(E[True][100][:5], 0.0, atol=1e-10)


def test_tip_mode_corrects_model_error(model: Model, robot: Robot) -> None:
    # the real robot's segments are 3% longer/shorter than the model's
    segs = (replace(robot.segments[0], length=206.0), replace(robot.segments[1], length=194.0))
    plant = Model(replace(robot, segments=segs))
    ref = np.array([0.5, -0.3, -0.2, 0.6, -40.0])
    x0 = np.array([0.45, -0.25, -0.15, 0.55, -38.0])
    intended = model.tip_position(ref)
    conf = TrackingController(model).simulate(x0, ref, 250, plant=plant)
    np.testing.assert_allclose(conf.final_tip_error, np.linalg.norm(plant.tip_position(ref) - intended), rtol=1e-6)
    assert conf.final_tip_error > 1.0
    # the paper's damping leaves a residual of order lambda^2 / sigma_min(J)^2 (here < 1 um)
    tip = TrackingController(model, TrackingOptions(mode="tip")).simulate(x0, ref, 250, plant=plant)
    assert tip.final_tip_error < 2e-3
    np.testing.assert_allclose(tip.tip[-1], intended, atol=2e-3)
    exact = TrackingController(model, TrackingOptions(mode="tip", damping=0.0)).simulate(x0, ref, 250, plant=plant)
    assert exact.final_tip_error < 1e-8


def test_tip_mode_with_exact_model_reaches_reference_configuration(model: Model) -> None:
    c = TrackingController(model, TrackingOptions(mode="tip", damping=0.0))
    ref = np.array([0.3, 0.1, -0.2, 0.2, -10.0])
    run = c.simulate(ref + np.array([0.01, -0.02, 0.01, 0.0, 1.0]), ref, 200)
    np.testing.assert_allclose(run.x[-1], ref, atol=1e-8)
    # without damping the configuration error it acts on is x_ref - x up to the
    # tip map's curvature: the difference shrinks with the square of the offset
    delta = np.array([0.01, 0.02, -0.01, 0.03, 2.0])
    gaps = []
    for s in (1.0, 0.1, 0.01):
        xm = ref - s * delta
        cmd = c.step(xm, c.initial_command(xm), ref)
        gaps.append(np.linalg.norm(cmd.error - s * delta))
    assert gaps[0] > 1e-6
    assert gaps[1] / gaps[0] < 0.02 and gaps[2] / gaps[1] < 0.02


# ---------------------------------------------------------------- tip error
def test_tip_error_helper(ctl: TrackingController, model: Model) -> None:
    rng = np.random.default_rng(5)
    X = rng.uniform(-0.4, 0.4, (6, 5))
    R = rng.uniform(-0.4, 0.4, (6, 5))
    expect = np.linalg.norm(model.tip_position(X) - model.tip_position(R), axis=1)
    np.testing.assert_allclose(ctl.tip_error(X, R), expect, atol=1e-12)
    assert isinstance(ctl.tip_error(X[0], R[0]), float)
    assert ctl.tip_error(X[0], tip_reference=model.tip_position(X[0]) + np.array([3.0, 4.0, 0.0])) == pytest.approx(5.0)
    with pytest.raises(InputError, match="exactly one"):
        ctl.tip_error(X[0])


def test_step_rejects_bad_inputs(ctl: TrackingController) -> None:
    x = np.zeros(5)
    q = ctl.initial_command(x)
    with pytest.raises(InputError, match=r"^x_measured: expected 5 numbers"):
        ctl.step(np.zeros(4), q, x)
    with pytest.raises(InputError, match=r"^q_command: expected 7 numbers"):
        ctl.step(x, q[:5], x)
    with pytest.raises(InputError, match=r"^x_reference: contains NaN"):
        ctl.step(x, q, np.full(5, np.nan))
    with pytest.raises(InputError, match=r"^dt: must be > 0"):
        ctl.step(x, q, x, dt=0.0)
    with pytest.raises(InputError, match=r"^tip_measured/tip_reference: only used with tracking.mode"):
        ctl.step(x, q, x, tip_measured=np.zeros(3))
    with pytest.raises(InputError, match=r"^steps: 3 does not match the 2 reference"):
        ctl.simulate(x, np.zeros((2, 5)), 3)


# --------------------------------------------------------------------- options
def _problem(robot: Robot, tracking: dict) -> Problem:
    return Problem.from_dict({"robot": robot.to_dict(), "tracking": tracking})


def test_options_from_problem_file(robot: Robot) -> None:
    o = _problem(robot, {"dt": 0.01, "mode": "tip", "max_z_rate": 20, "damping": 0.0}).options(
        TrackingOptions, "tracking"
    )
    assert (o.dt, o.mode, o.max_z_rate, o.damping, o.servo_tau) == (0.01, "tip", 20.0, 0.0, 0.05)
    assert _problem(robot, {}).options(TrackingOptions, "tracking") == TrackingOptions()
    assert TrackingOptions.from_table(Table(o.to_dict(), "tracking")) == o


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"dtt": 0.02}, r"^tracking\.dtt: unknown key"),
        ({"dt": -0.02}, r"^tracking\.dt: must be > 0"),
        ({"dt": "fast"}, r"^tracking\.dt: expected a number"),
        ({"servo_tau": 0}, r"^tracking\.servo_tau: must be > 0"),
        ({"max_cable_rate": float("nan")}, r"^tracking\.max_cable_rate: must be finite"),
        ({"max_z_rate": float("inf")}, r"^tracking\.max_z_rate: must be finite"),
        ({"damping": -0.1}, r"^tracking\.damping: must be >= 0"),
        ({"mode": "joint"}, r"^tracking\.mode: must be one of configuration, tip"),
        ({"effort_weight": True}, r"^tracking\.effort_weight: expected a number"),
    ],
)
def test_options_reject_bad_input(robot: Robot, section: dict, message: str) -> None:
    with pytest.raises(InputError, match=message) as info:
        _problem(robot, section).options(TrackingOptions, "tracking")
    assert "\n" not in str(info.value)


def test_options_validate_when_built_in_python() -> None:
    with pytest.raises(InputError, match=r"^tracking\.z_error_scale: must be > 0"):
        TrackingOptions(z_error_scale=0.0)
    with pytest.raises(InputError, match=r"^tracking\.mode"):
        TrackingOptions(mode="TIP")


def test_one_segment_robot(robot: Robot) -> None:
    r1 = Robot("one", 2.0, (Segment(150.0),), z_range=(-50.0, 50.0))
    c = TrackingController(Model(r1))
    assert c.gain.shape == (3, 6)
    run = c.simulate(r1.straight(), np.array([0.2, -0.1, 10.0]), 200)
    assert run.final_tip_error < 1e-6
