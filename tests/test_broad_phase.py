"""The compiled edge check's broad phase against the numpy refinement loop (which has none): on random
scenes of static and of moving, breathing spheres it never changes a verdict (the certified fractions are
bit for bit the numpy loop's), its lower bounds stay below the exact ones, it checks as many samples (plus
the one sample per motion of its first-level pass among `EDGE_BROAD` obstacles or more), and certified
motions pass an independent dense check."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import require_tool
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crtraj.core.build_cache import BuildCache
from crtraj.model.kinematics import Model
from crtraj.planning.validity._driver import EDGE_BROAD
from crtraj.planning.validity._kernels import Kernels
from crtraj.planning.validity._motion import BROAD_MIN, MotionValidator
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene


@pytest.fixture(scope="module")
def kernels(tmp_path_factory):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    return Kernels(BuildCache(tmp_path_factory.mktemp("kernels")))


def random_scene(rng: np.random.Generator, n: int, moving: bool) -> Scene:
    """n spheres around the robot (mm), some far away; moving ones slide and breathe."""
    obs = []
    for i in range(n):
        c = rng.uniform([-250, -250, 0], [250, 250, 600])
        radius = float(rng.uniform(8, 45))
        kw = {}
        if moving:
            kw = {
                "amplitude": float(rng.uniform(0, 8)),
                "omega": float(rng.uniform(0.2, 2.0)),
                "to": tuple(c + rng.uniform(-80, 80, 3)),
                "duration": float(rng.uniform(0.5, 4.0)),
                "profile": ("linear", "sin", "cos")[i % 3],
            }
        obs.append(Obstacle(name=f"o{i}", center=tuple(c), radius=radius, **kw))
    return Scene(obstacles=tuple(obs), safety_distance=5.0)


def motions(v: MotionValidator, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """Random motions: long ones, short ones and a few that do not move, with start times and durations (s)."""
    XA, XB = v.sample(rng, n), v.sample(rng, n)
    XB[: n // 4] = XA[: n // 4] + rng.normal(scale=0.05, size=(n // 4, v.robot.nx))
    XB[n // 4] = XA[n // 4]
    TA = rng.uniform(0.0, 3.0, n)
    TB = TA + rng.uniform(0.0, 3.0, n)
    return XA, XB, TA, TB


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(BROAD_MIN, 40), moving=st.booleans(), origin=st.floats(0, 5))
def test_broad_phase_never_changes_a_verdict(model: Model, kernels: Kernels, seed, n, moving, origin):
    """With the broad phase the certified fractions are the numpy loop's bit for bit, lower bounds never exceed
    the exact ones, and the same number of samples is checked (plus the first-level pass's)."""
    rng = np.random.default_rng(seed)
    scene = replace(random_scene(rng, n, moving), time_origin=origin)
    broad = MotionValidator(model, scene, kernels=kernels)
    exact = MotionValidator(model, scene, kernels=kernels, broad_phase=False)
    loop = MotionValidator(model, scene, kernels=kernels)
    loop.compiled_loop = False
    XA, XB, TA, TB = motions(broad, rng, 40)
    for prefix in (True, False):
        s0, s1 = broad.n_samples, loop.n_samples
        fb, lb = broad.check_edges(XA, XB, TA, TB, prefix=prefix)
        fl, ll = loop.check_edges(XA, XB, TA, TB, prefix=prefix)
        fe, le = exact.check_edges(XA, XB, TA, TB, prefix=prefix)
        np.testing.assert_array_equal(fb, fl)
        np.testing.assert_array_equal(fe, fl)
        np.testing.assert_array_equal(le, ll)
        assert np.all((lb <= ll) | (np.isnan(lb) & np.isnan(ll)))
        # the first-level pass: one more sample per motion of two or more first intervals
        n0 = np.maximum(1, np.ceil(broad.motion_bound(XB - XA) / broad.coarse))
        extra = int(np.count_nonzero(n0 >= 2)) if n >= EDGE_BROAD else 0
        assert broad.n_samples - s0 == loop.n_samples - s1 + extra


def test_broad_phase_certifies_safely_among_many_spheres(model: Model, kernels: Kernels):
    """Among 60 spheres, most of them far from the robot, the kernel with its broad phase gives the verdicts
    of the one without, its lower bounds never exceed the exact ones, and what it certifies is clear under
    a dense numpy check (200 backbone points, 400 configurations per motion)."""
    rng = np.random.default_rng(3)
    scene = random_scene(rng, 60, moving=False)
    broad = MotionValidator(model, scene, kernels=kernels)
    exact = MotionValidator(model, scene, kernels=kernels, broad_phase=False)
    XA, XB, _, _ = motions(broad, rng, 60)
    fb, lb = broad.check_edges(XA, XB)
    fe, le = exact.check_edges(XA, XB)
    np.testing.assert_array_equal(fb, fe)
    assert (fb >= 1).any() and (fb < 1).any()
    assert np.all(lb <= le)
    centers, radii = scene.states(0.0)
    for a, b, f in zip(XA, XB, fb, strict=True):
        if f <= 0:
            continue
        S = a + np.linspace(0.0, f, 400)[:, None] * (b - a)
        P = model.points(S, 200)
        d = np.linalg.norm(P[:, :, None, :] - centers[None, None], axis=-1) - radii
        assert d.min() - model.robot.body_radius - scene.safety_distance >= -1e-9
