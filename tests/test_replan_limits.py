"""Actuator speed and acceleration limits in the replanner: the horizon NLP, the tracking set-points, and a
whole `crtraj replan` run's recorded actuation as `crtraj stream` sends it (the admitted frames at 100 Hz)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import PAPER, paper_copy

from crtraj.cli import main
from crtraj.control.horizon import Replanner, ReplanOptions
from crtraj.control.tracking import TrackingController
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import admit
from crtraj.io.problem import Problem
from crtraj.io.results import read_result
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def acts(robot) -> Actuators:
    return Actuators.from_robot(robot)


def _values(robot, acts: Actuators, x: np.ndarray) -> np.ndarray:
    """Actuator values (rad, mm) of configurations x (N, nx), through the cable lengths and `Actuators.command`
    (not through the rate limits' Jacobian)."""
    A, q0 = robot.cable_matrix()
    return acts.command(q0 + np.asarray(x) @ np.asarray(A).T)


def test_horizon_solution_keeps_the_actuator_speed_and_acceleration_limits(model, robot, acts):
    opts = ReplanOptions(horizon=8, points=12, solver="sqp", max_z_speed=40.0, limit_fraction=0.9)
    free = Replanner(model, opts, max_obstacles=0, safety_distance=5.0)
    rp = Replanner(model, opts, max_obstacles=0, safety_distance=5.0, rate_limits=acts.rate_limits(robot))
    dt, N = opts.dt, opts.horizon
    x0 = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
    x_prev = x0 + np.array([0.0, 0.0, 0.0, 0.0, -1.2])  # z was rising at 12 mm/s
    xg = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])  # the reference asks z to fall fast
    Xr = x0 + np.clip(0.15 * np.arange(1, N + 1), 0, 1)[:, None] * (xg - x0)
    obstacles = rp.obstacles_from_scene(Scene(obstacles=(), safety_distance=5.0), 0.0)
    vmax, amax = 0.9 * acts.vmax, 0.9 * acts.amax

    def rates(configs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = _values(robot, acts, np.vstack([x_prev, x0, configs]))
        vel = np.diff(v, axis=0) / dt
        return vel[1:], np.diff(vel, axis=0) / dt  # steps 1..N; accelerations at steps 1..N (k = 1 uses x_prev)

    res0 = free.solve(x0, Xr, obstacles, x_prev=x_prev, warm=False)
    assert res0.is_success(), res0.solver_status
    _, acc0 = rates(res0.configs)
    assert np.max(np.abs(acc0) / amax) > 1.5  # without the limits this reference breaks them: the test can fail
    res = rp.solve(x0, Xr, obstacles, x_prev=x_prev, warm=False)
    assert res.is_success(), res.solver_status
    vel, acc = rates(res.configs)
    assert np.all(np.abs(vel) <= vmax * (1 + 1e-6) + 1e-9)
    assert np.all(np.abs(acc) <= amax * (1 + 1e-6) + 1e-9)
    assert np.max(np.abs(acc) / amax) > 0.99  # the acceleration limit is what shaped the solution
    assert rp.describe()["actuator_limits"] == list(acts.names)


def test_tracking_set_points_and_servo_samples_keep_the_limits(model, robot, acts):
    limits = acts.rate_limits(robot).scaled(0.5)
    ctl = TrackingController(model, rate_limits=limits)
    h = ctl.options.dt
    x0 = np.array([0.3, 0.0, -0.2, 0.1, 20.0])
    ref = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
    run = ctl.simulate(x0, ref, 600)
    sp = np.vstack([_values(robot, acts, ctl.servo.config(ctl.initial_command(x0))[None]), acts.command(run.q_command)])
    vel = np.diff(sp, axis=0) / h
    acc = np.diff(vel, axis=0, prepend=np.zeros((1, vel.shape[1]))) / h
    assert np.all(np.abs(vel) <= limits.vmax * (1 + 1e-9))
    assert np.all(np.abs(acc) <= limits.amax * (1 + 1e-9))
    assert np.max(np.abs(acc[:, -1])) >= 0.999 * limits.amax[-1]  # the z stage did use its acceleration
    # the servos' actual motion, sampled every 5 periods, keeps the same limits (positive averaging kernel)
    actual = acts.command(run.q)[::5]
    v5 = np.diff(actual, axis=0) / (5 * h)
    a5 = np.diff(v5, axis=0) / (5 * h)
    assert np.all(np.abs(v5) <= limits.vmax * (1 + 1e-9))
    assert np.all(np.abs(a5) <= limits.amax * (1 + 1e-9))
    assert run.final_tip_error < 0.5
    free = TrackingController(model).simulate(x0, ref, 600)
    a_free = np.diff(np.diff(acts.command(free.q_command), axis=0), axis=0) / h**2
    assert np.max(np.abs(a_free) / limits.amax) > 2.0  # without the limits the same move breaks them


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """Simulation 2 as shipped but without its 4 ms step deadline: with it, which steps fall back depends on how
    fast this machine is at the time, and the limits below are properties of one reproducible run."""
    folder = tmp_path_factory.mktemp("limits")
    problem = paper_copy(folder)
    out = folder / "replan"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["replan", str(problem), "--out", str(out), "--no-html"])
    return rc, buf.getvalue(), json.loads((out / "run.json").read_text()), np.load(out / "run.npz")


def _streamed(res: dict) -> tuple[np.ndarray, np.ndarray, Actuators]:
    """Velocity and acceleration fractions per streamed frame: the frames admission verified and the streamer
    sends (`AdmittedMotion.values`), with the limits gate's formula (finite differences at 100 Hz from rest)."""
    acts = Actuators.from_robot(Problem.load(PAPER).robot)
    values = admit(read_result(res).motion_record(), acts, rate=100.0).values
    vel = np.diff(values, axis=0, prepend=values[:1]) / 0.01
    acc = np.diff(vel, axis=0, prepend=np.zeros((1, acts.n))) / 0.01
    return np.abs(vel) / acts.vmax, np.abs(acc) / acts.amax, acts


def test_paper_run_reaches_the_goal_safely_and_reports_its_limit_fractions(paper_run):
    rc, text, res, npz = paper_run
    assert rc == 0, text
    s = res["summary"]
    assert res["status"] == "reached" and s["collisions"] == 0 and s["safety_violations"] == 0
    # independent dense check: every verification sample's body against the scene's closed-form spheres
    scene = Scene.from_table(Problem.load(PAPER).section("scene"))
    from crtraj.model.kinematics import Model

    model = Model(Problem.load(PAPER).robot)
    T, X = npz["dense_t"], npz["dense_x"]
    P = model.points(X, 41)
    ang = np.array([[o.omega, o.phase] for o in scene.obstacles])
    R = np.array([o.radius for o in scene.obstacles]) + np.array([o.amplitude for o in scene.obstacles]) * np.sin(
        T[:, None] * ang[:, 0] + ang[:, 1]
    )
    C = np.array([o.center for o in scene.obstacles])
    d = np.linalg.norm(P[:, :, None, :] - C[None, None], axis=-1).min(axis=1) - R - model.robot.body_radius
    # at least one sample per 20 ms control period of every 0.1 s step (`StepMotion.track`: more where the body
    # moves further than half the check resolution in a period)
    assert len(T) >= 5 * (len(res["waypoints"]) - 1) and d.min() > 0.0
    fv, fa, _ = _streamed(res)
    assert s["max_velocity_fraction"] == pytest.approx(fv.max(), rel=1e-6)
    assert s["max_acceleration_fraction"] == pytest.approx(fa.max(), rel=1e-6)
    line = f"actuators at most {fv.max():.2f} of their velocity limit and {fa.max():.2f} of their acceleration limit"
    assert line in text and f"executed {s['duration_s']:.2f} s" in text


def test_paper_run_streams_within_the_velocity_limits(paper_run):
    fv, _, _ = _streamed(paper_run[2])
    assert fv.max() <= 1.0


def test_paper_run_streams_within_the_acceleration_limits(paper_run):
    _, fa, _ = _streamed(paper_run[2])
    assert fa.max() <= 1.0


def test_streamed_run_stays_on_the_executed_motion_and_keeps_the_samples_bounds(paper_run):
    """The streamed curve (the executed actuation's B-spline) starts and ends at rest exactly on the executed
    motion, passes within a sixth of a second difference of every executed sample, and its frames' speed and
    acceleration stay within the executed samples' own first and second differences (independent bounds,
    computed here from `executed.q`)."""
    res = paper_run[2]
    acts = Actuators.from_robot(Problem.load(PAPER).robot)
    ex = res["executed"]
    h, c = ex["dt"], acts.command(np.asarray(ex["q"]))
    np.testing.assert_allclose(c[0], acts.command(np.asarray(res["waypoints"][0]["q"])), atol=1e-12)
    np.testing.assert_allclose(c[-1], acts.command(np.asarray(res["waypoints"][-1]["q"])), atol=1e-12)
    motion = admit(read_result(res).motion_record(), acts, rate=100.0)
    stamps, v = motion.stamps, motion.values
    np.testing.assert_allclose(v[0], c[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(v[-1], c[-1], rtol=0, atol=1e-9)
    assert stamps[0] == pytest.approx(ex["t0"] - h) and stamps[-1] == pytest.approx(ex["t0"] + len(c) * h)
    # at the executed sample times the curve is (p[k-1] + 4 p[k] + p[k+1]) / 6: off by |second difference| / 6
    pad = np.vstack([c[:1], c, c[-1:]])
    second = np.abs(pad[2:] - 2.0 * pad[1:-1] + pad[:-2])
    k = np.flatnonzero(np.isin(np.round((stamps - ex["t0"]) / h, 9), np.arange(len(c))))
    idx = np.round((stamps[k] - ex["t0"]) / h).astype(int)
    assert len(idx) > 0.9 * len(c)
    assert np.all(np.abs(v[k] - c[idx]) <= second[idx] / 6.0 + 1e-9)
    first = np.max(np.abs(np.diff(np.vstack([c[:1], c, c[-1:]]), axis=0)), axis=0) / h
    d2 = np.abs(np.diff(np.vstack([c[:1], c[:1], c, c[-1:], c[-1:]]), 2, axis=0))
    vel = np.diff(v, axis=0) * 100.0
    acc = np.diff(v, 2, axis=0) * 100.0**2
    assert np.all(np.abs(vel) <= first * (1 + 1e-9) + 1e-9)
    assert np.all(np.abs(acc) <= d2.max(axis=0) / h**2 * (1 + 1e-9) + 1e-9)
    # and those are the loop's own limits (full limits over the interpolation gain): the reserve is real
    assert np.all(d2.max(axis=0) / h**2 <= acts.amax / 2.0 * (1 + 1e-9))


def test_run_document_executed_field_is_validated_and_optional(paper_run):
    """`executed` is read with one-line errors naming the field; a run written before it existed streams its
    waypoints as before."""
    from crtraj.core.errors import InputError

    res = paper_run[2]
    rec = read_result(res).motion_record()
    assert rec.period == res["executed"]["dt"] and len(rec.q) == len(res["executed"]["q"])
    for key, value, match in (
        ("dt", -0.02, r"^executed\.dt: "),
        ("q", [[0.0] * 6], r"^executed\.q: expected shape"),
        ("q", [], r"^executed\.q: expected a non-empty list"),
        ("t0", None, r"^executed\.t0: "),
    ):
        bad = {**res, "executed": {**res["executed"], key: value}}
        with pytest.raises(InputError, match=match):
            read_result(bad)
    old = {k: v for k, v in res.items() if k != "executed"}
    rec_old = read_result(old).motion_record()
    assert rec_old.period is None and len(rec_old.q) == len(res["waypoints"])
