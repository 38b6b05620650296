"""Actuator speed and acceleration limits in the replanner: the horizon NLP, the tracking set-points, and a
whole `crtraj replan` run's recorded actuation sampled as `crtraj stream` sends it (100 Hz PCHIP)."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.cli import main
from crtraj.control.horizon import Replanner, ReplanOptions
from crtraj.control.tracking import TrackingController
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.setpoints import SetpointPath
from crtraj.io.problem import Problem
from crtraj.io.results import read_result
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PAPER = ROOT / "problems" / "paper_dynamic.toml"


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
    out = tmp_path_factory.mktemp("limits") / "replan"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["replan", str(PAPER), "--out", str(out), "--no-html"])
    return rc, buf.getvalue(), json.loads((out / "run.json").read_text()), np.load(out / "run.npz")


def _streamed(res: dict) -> tuple[np.ndarray, np.ndarray, Actuators]:
    """Velocity and acceleration fractions per streamed frame, with the streamer's own sampler and the limits
    gate's formula (finite differences at 100 Hz from rest)."""
    acts = Actuators.from_robot(Problem.load(PAPER).robot)
    r = read_result(res)
    _, values = SetpointPath.from_actuation(r.t, r.q, acts).sample(100.0)
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
    assert len(T) > 10 * len(res["waypoints"]) and d.min() > 0.0
    fv, fa, _ = _streamed(res)
    assert s["max_velocity_fraction"] == pytest.approx(fv.max(), rel=1e-6)
    assert s["max_acceleration_fraction"] == pytest.approx(fa.max(), rel=1e-6)
    line = f"actuators at most {fv.max():.2f} of their velocity limit and {fa.max():.2f} of their acceleration limit"
    assert line in text and f"executed {s['duration_s']:.2f} s" in text


def test_paper_run_streams_within_the_velocity_limits(paper_run):
    fv, _, _ = _streamed(paper_run[2])
    assert fv.max() <= 1.0


@pytest.mark.xfail(
    strict=True,
    reason="known gap: PCHIP at 100 Hz amplifies the samples' acceleration (up to 6x at starts, stops and "
    "reversals); with interpolation gain 2 the z stage still reaches ~1.17x its limit on paper_dynamic at reversals",
)
def test_paper_run_streams_within_the_acceleration_limits(paper_run):
    _, fa, _ = _streamed(paper_run[2])
    assert fa.max() <= 1.0
