"""The C tracking simulation of one control step (crtraj.control.tracking._compiled) against the numpy one
(`StepMotion.track` with TrackingController.step and ServoModel), limits binding and not."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PROBLEMS, require_tool

from crtraj.control.loop import ClosedLoop
from crtraj.control.tracking._compiled import CompiledTracking
from crtraj.core.build_cache import BuildCache
from crtraj.io.problem import Problem

TOL = 1e-9


@pytest.fixture(scope="module")
def loop_and_c(tmp_path_factory):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    problem = Problem.load(PROBLEMS / "paper_dynamic.toml")
    loop = ClosedLoop.from_problem(problem, seed=0)
    h = loop.options.dt / loop.n_sub
    cache = BuildCache(tmp_path_factory.mktemp("tracking"))
    c = CompiledTracking.load(loop.tracker, h, loop.parts.checks.validator.space.metric_matrix, cache)
    assert c is not None
    return loop, c


def _cases(loop, rng):
    """(q, qc, x0, x1, t, inc): random steps, and steps that drive each limit of the controller."""
    ctl = loop.tracker
    lo, hi = loop.robot.z_range
    theta = loop.robot.segments[0].theta_max
    out = []
    for _ in range(150):
        x0 = np.append(rng.uniform(-0.9, 0.9, 4) * theta, rng.uniform(lo, hi))
        size = rng.choice([0.01, 0.1, 1.0, 5.0])
        x1 = x0 + np.append(rng.normal(0, 0.05, 4) * size, rng.normal(0, 3.0) * size)
        q = ctl.initial_command(x0 + np.append(rng.normal(0, 0.01, 4), rng.normal(0, 0.5)))
        qc = ctl.initial_command(x0 + np.append(rng.normal(0, 0.01, 4), rng.normal(0, 0.5)))
        inc = np.append(rng.normal(0, 0.002, 4), rng.normal(0, 0.05)) * rng.choice([0.0, 1.0, 20.0])
        out.append((q, qc, loop.servo.config(q), x1, float(rng.uniform(0, 30)), inc))
    # against the z stage's ends and the bending limit, and a reversal against the acceleration limit
    for x0, x1 in (
        (np.array([0.0, 0.0, 0.0, 0.0, hi - 0.05]), np.array([0.0, 0.0, 0.0, 0.0, hi + 5.0])),
        (np.array([0.0, 0.0, 0.0, 0.0, lo + 0.05]), np.array([0.0, 0.0, 0.0, 0.0, lo - 5.0])),
        (np.array([0.99 * theta, 0.0, 0.0, 0.0, 0.0]), np.array([1.5 * theta, 0.2, 0.0, 0.0, 0.0])),
    ):
        q = ctl.initial_command(x0)
        out.append((q, q.copy(), x0, x1, 1.0, np.zeros(5)))
    x0 = np.array([0.2, 0.1, -0.1, 0.1, 0.0])
    q = ctl.initial_command(x0)
    out.append((q, q.copy(), x0, x0 - np.array([0.05, 0.05, 0.05, 0.05, 2.0]), 2.0, np.array([0.01] * 4 + [0.3])))
    return out


def test_c_tracking_step_is_the_numpy_step(loop_and_c):
    loop, c = loop_and_c
    rng = np.random.default_rng(7)
    flags = {"rate": 0, "limit": 0, "accel": 0}
    step = loop.tracker.step

    def spy(*a, **k):
        cmd = step(*a, **k)
        flags["rate"] += cmd.rate_scale < 1.0
        flags["limit"] += cmd.limit_scale < 1.0
        flags["accel"] += cmd.accel_scale < 1.0
        return cmd

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(loop.tracker, "step", spy)
        mp.setattr(loop.parts.motion, "compiled", None)  # `track` simulates in numpy
        for q, qc, x0, x1, t, inc in _cases(loop, rng):
            want = loop.parts.motion.track(q, qc, x0, x1, t, inc)
            got = c.step(q, qc, x0, x1, t, inc, loop.n_sub, loop.options.dt, loop.loop_options.check_resolution)
            assert got is not None
            assert len(got[2]) == len(want.times)  # the same samples per period
            for g, w in zip(got, (want.q, want.qc, want.times, want.configs, want.commands), strict=True):
                np.testing.assert_allclose(g, w, rtol=0, atol=TOL)
    # every limit of the controller was active in some period
    assert min(flags.values()) > 0, flags


def test_closed_loop_uses_it_and_stays_safe(loop_and_c):
    """The loop built on a machine with a C compiler simulates its steps in C; the run reaches the goal with
    every dense sample clear, and its motion matches the numpy simulation of the same commands."""
    loop, _ = loop_and_c
    assert loop.parts.motion.compiled is not None
    run = loop.run()
    s = run.summary()
    assert s["reached_goal"] and s["collisions"] == 0 and s["min_clearance_mm"] > 0.0
    # replay the recorded set-points through the numpy servo model: the actuators the run reports
    servo, h = loop.servo, loop.options.dt / loop.n_sub
    commands = run.commands.reshape(len(run.q) - 1, loop.n_sub, -1)
    q = run.q[0]
    for k, step_commands in enumerate(commands):
        for cmd in step_commands:
            q = servo.advance(q, cmd, h)
        np.testing.assert_allclose(q, run.q[k + 1], rtol=0, atol=1e-9)
