"""The planning speed-ups of stop 34 against the paths they replace, on random inputs: the verdict-only edge check
(a motion stops at its first unsafe interval) gives the full check's verdicts with no more samples; the edge
check that counts first intervals in C returns the numpy-counted call's numbers bit for bit and refuses values
that are not finite; the compiled path clearance (with its exact broad phase) equals the numpy samples through
the compiled clearance bit for bit; the compiled B-spline equals `BSplineCurve`; the body-motion bound equals
its former formula; the batched IK dedup keeps what one-at-a-time keeping keeps; a tree filled at once equals
one filled node by node; the closed loop's verification of a move in one call equals its numpy form."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from conftest import require_tool
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_broad_phase import motions, random_scene

from crtraj.core.splines import BSplineCurve
from crtraj.model.kinematics import Model
from crtraj.planning.ik import IKRun
from crtraj.planning.planners._tree import SearchTree
from crtraj.planning.validity import Kernels, MotionValidator, held_clearance
from crtraj.world.scene import Scene


@pytest.fixture(scope="module")
def kernels(build_cache):
    require_tool("cc", "gcc", hint="Debian: apt-get install gcc")
    return Kernels(build_cache)


def numpy_path_clearance(v: MotionValidator, X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Per-motion minima of `MotionValidator.path_clearance` the way it computed them before (numpy samples, one
    compiled clearance call for all of them, every obstacle in every sample)."""
    S, e, tau, _, _, _ = v._samples(X[:-1], X[1:], T[:-1], T[1:])
    ts = T[:-1][e] + tau * (T[1:] - T[:-1])[e]
    c = v.clearance(S, ts, ts)
    per_edge = np.full(len(X) - 1, np.inf)
    np.minimum.at(per_edge, e, c)
    return per_edge


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 60), moving=st.booleans(), origin=st.floats(0, 5))
def test_verdict_mode_keeps_every_verdict(model: Model, kernels: Kernels, seed, n, moving, origin):
    """edges_valid and first_valid (verdict mode: a motion stops at its first unsafe interval) certify exactly
    the motions the full check (and the numpy loop) certifies, with at most its samples."""
    rng = np.random.default_rng(seed)
    scene = replace(random_scene(rng, n, moving), time_origin=origin)
    v = MotionValidator(model, scene, kernels=kernels)
    loop = MotionValidator(model, scene, kernels=kernels)
    loop.compiled_loop = False
    XA, XB, TA, TB = motions(v, rng, 40)
    s0 = v.n_samples
    full, _ = v.check_edges(XA, XB, TA, TB, prefix=False)
    s1 = v.n_samples
    ok = v.edges_valid(XA, XB, TA, TB)
    s2 = v.n_samples
    ref, _ = loop.check_edges(XA, XB, TA, TB, prefix=False)
    np.testing.assert_array_equal(ok, full >= 1.0)
    np.testing.assert_array_equal(ok, ref >= 1.0)
    assert s2 - s1 <= s1 - s0
    first = np.flatnonzero(ref >= 1.0)
    assert v.first_valid(XA, XB, TA, TB) == (int(first[0]) if len(first) else -1)


def test_verdict_mode_checks_fewer_samples_among_obstacles(model: Model, kernels: Kernels):
    """Among many spheres most long random motions collide somewhere: stopping each at its first unsafe
    interval saves samples (the point of the mode)."""
    rng = np.random.default_rng(5)
    v = MotionValidator(model, random_scene(rng, 40, moving=False), kernels=kernels)
    XA, XB = v.sample(rng, 200), v.sample(rng, 200)
    s0 = v.n_samples
    full, _ = v.check_edges(XA, XB, prefix=False)
    s1 = v.n_samples
    ok = v.edges_valid(XA, XB)
    np.testing.assert_array_equal(ok, full >= 1.0)
    assert (~ok).sum() > 20 and v.n_samples - s1 < 0.9 * (s1 - s0)


def test_first_intervals_counted_in_c_give_the_same_numbers(model: Model, kernels: Kernels):
    """`ValidityKernel.check_edges` given a coarse interval (first intervals max(1, ceil(bound / coarse))
    counted in C) returns the call with numpy-counted intervals bit for bit, for both modes; a bound that is
    not finite is refused (None) before anything is checked."""
    rng = np.random.default_rng(2)
    v = MotionValidator(model, random_scene(rng, 9, moving=False), kernels=kernels)
    k = v.state.kernel
    XA, XB, _, _ = motions(v, rng, 60)
    dX = XB - XA
    bound = v.motion_bound(dX)
    n0 = np.maximum(1, np.ceil(bound / v.coarse)).astype(int)
    slots = v.state.static_slots
    for prefix in (True, False):
        ref = k.check_edges(XA, dX, bound, n0, slots, v.inflate, 1.5, prefix, 3)
        out = k.check_edges(XA, dX, bound, v.coarse, slots, v.inflate, 1.5, prefix, 3)
        assert out is not None
        for a, b in zip(out, ref, strict=True):
            np.testing.assert_array_equal(a, b)
    bad = bound.copy()
    bad[7] = np.nan
    assert k.check_edges(XA, dX, bad, v.coarse, slots, v.inflate, 1.5, False, 3) is None


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 80), moving=st.booleans(), origin=st.floats(0, 5))
def test_compiled_path_clearance_is_the_numpy_one(model: Model, kernels: Kernels, seed, n, moving, origin):
    """The one-call path clearance, which skips per motion the obstacles that cannot set its minimum, gives the
    per-motion minima of the numpy samples through the compiled clearance bit for bit (waits and slow motions
    included), and the smallest of them."""
    rng = np.random.default_rng(seed)
    scene = replace(random_scene(rng, n, moving), time_origin=origin)
    v = MotionValidator(model, scene, kernels=kernels)
    X = v.sample(rng, 12)
    X[5] = X[4]  # a wait
    T = np.concatenate([[rng.uniform(0, 2)], rng.uniform(0.0, 3.0, 11)]).cumsum()
    ref = numpy_path_clearance(v, X, T)
    low, per = v.path_clearance(X, T)
    np.testing.assert_array_equal(per, ref)
    assert low == ref.min()


def test_path_clearance_refuses_times_that_are_not_finite(model: Model, kernels: Kernels):
    """A time that is not finite goes to the numpy path, which names it (the compiled call computes nothing)."""
    from crtraj.core.errors import InputError

    rng = np.random.default_rng(4)
    v = MotionValidator(model, random_scene(rng, 5, moving=True), kernels=kernels)
    X = v.sample(rng, 4)
    with pytest.raises(InputError, match=r"^t: contains NaN or infinity"):
        v.path_clearance(X, np.array([0.0, 1.0, np.inf, 3.0]))


def test_compiled_bspline_is_bsplinecurve(model: Model, kernels: Kernels):
    """`ValidityKernel.bspline` equals `BSplineCurve.__call__` bit for bit: clamped and repeated interior knots,
    degrees 1 to 4, parameters inside, on the knots and beyond the ends."""
    k = MotionValidator(model, Scene(), kernels=kernels).state.kernel
    rng = np.random.default_rng(8)
    for deg in (1, 2, 3, 4):
        for _ in range(20):
            nc = int(rng.integers(deg + 1, 30))
            inner = np.sort(rng.uniform(0.0, 1.0, nc - deg - 1))
            if len(inner) > 2:
                inner[1] = inner[2]  # a repeated knot (an empty span)
            knots = np.concatenate([np.zeros(deg + 1), inner, np.ones(deg + 1)])
            C = rng.normal(size=(nc, int(rng.integers(1, 8)))) * 100
            spl = BSplineCurve(knots, C, deg)
            x = np.concatenate([rng.uniform(-0.2, 1.2, 300), knots, [0.0, 1.0]])
            np.testing.assert_array_equal(k.bspline(spl.knots, spl.coeffs, deg, x), spl(x))


def test_motion_bound_keeps_its_numbers(model: Model):
    """The body-motion bound (squares summed once, add.reduce) equals its former formula bit for bit, for one
    change and for batches."""
    v = MotionValidator(model, Scene(), compiled=False)
    M, m = v.metric_matrix, 2 * model.robot.n_segments
    rng = np.random.default_rng(1)
    for shape in ((5,), (1, 5), (7, 5), (300, 5), (4, 6, 5)):
        dx = rng.normal(size=shape) * rng.uniform(1e-3, 1e3)
        dy = dx @ M.T
        yx, yy = dy[..., 0:m:2], dy[..., 1:m:2]
        old = np.sqrt(yx * yx + yy * yy).sum(axis=-1) + np.abs(dy[..., -1])
        np.testing.assert_array_equal(v.motion_bound(dx), old)


def test_batched_dedup_keeps_what_one_at_a_time_keeps(model: Model):
    """`IKRun.add_all` keeps the configurations `add` one at a time keeps (dedup by body motion), in order."""
    v = MotionValidator(model, Scene(), compiled=False)
    rng = np.random.default_rng(6)

    class Sol:  # what add/add_all read of an IKSolution
        def __init__(self, x: np.ndarray) -> None:
            self.x = x

    for trial in range(30):
        base = v.sample(rng, 3)
        X = base[rng.integers(0, 3, 12)] + rng.normal(scale=rng.uniform(0.001, 0.05), size=(12, model.nx))
        runs = [IKRun(np.zeros(3), X, v, (0.0, 0.0), 1e-3, 0.0, 4, 5.0) for _ in range(2)]
        pre = v.sample(rng, trial % 3)
        for r in runs:
            for x in pre:
                r.keep(x)
        for x in X:
            runs[0].add(Sol(x))
        runs[1].add_all([Sol(x) for x in X])
        assert len(runs[0].kept) == len(runs[1].kept) and len(runs[1].sols) == 12
        np.testing.assert_array_equal(np.array(runs[0].kept), np.array(runs[1].kept))


def test_tree_filled_at_once_is_the_tree_filled_node_by_node():
    """`SearchTree.add_many` gives the nodes, keys and nearest answers of `add` one at a time, across growth."""
    rng = np.random.default_rng(0)
    a, b = SearchTree(3, 5, capacity=4), SearchTree(3, 5, capacity=4)
    keys, X = rng.normal(size=(40, 3)), rng.normal(size=(40, 5))
    t, cost, par = rng.uniform(size=40), rng.uniform(size=40), np.arange(-1, 39)
    for i in range(40):
        a.add(keys[i], X[i], float(t[i]), float(cost[i]), int(par[i]))
    b.add_many(keys[:1], X[:1], t[:1], cost[:1], par[:1])
    b.add_many(keys[1:], X[1:], t[1:], cost[1:], par[1:])
    for name in ("keys", "x", "t", "cost", "parent"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for q in rng.normal(size=(10, 3)):
        assert a.nearest(q) == b.nearest(q)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 40), moving=st.booleans(), origin=st.floats(0, 5))
def test_path_clearance_of_frames_shares_their_samples_exactly(model: Model, kernels: Kernels, seed, n, moving, origin):
    """Frames every 10 ms along a path (a retimed motion): a motion's last sample is the next one's first, bit for
    bit, and the compiled call takes it once for both; the minima and the sample count stay those of the numpy
    samples (every sample, every obstacle), bit for bit."""
    rng = np.random.default_rng(seed)
    scene = replace(random_scene(rng, n, moving), time_origin=origin)
    v = MotionValidator(model, scene, kernels=kernels)
    ends = v.sample(rng, 4)
    f = np.linspace(0.0, 1.0, 60)[:, None]
    X = np.concatenate([a + f * (b - a) for a, b in itertools.pairwise(ends)])
    X[10:14] = X[10]  # a wait
    X += 1e-3 * np.sin(np.arange(len(X)))[:, None]  # off the straight lines, across zero in places
    T = 0.25 + 0.01 * np.arange(len(X))
    # the precondition of the sharing holds for most frames here (else this test would not exercise it)
    shared = np.all(X[:-1] + 1.0 * (X[1:] - X[:-1]) == X[1:], axis=1)
    assert shared.mean() > 0.5
    ref = numpy_path_clearance(v, X, T)
    S, _, _, _, _, _ = v._samples(X[:-1], X[1:], T[:-1], T[1:])
    s0 = v.n_samples
    low, per = v.path_clearance(X, T)
    np.testing.assert_array_equal(per, ref)
    assert low == ref.min()
    assert v.n_samples - s0 == len(S)


def _servo_motion(v: MotionValidator, rng: np.random.Generator, n: int, scale: float) -> tuple[np.ndarray, ...]:
    """A step's sampled move as the loop verifies it: n configurations a small random walk apart, every 10 ms."""
    X = v.project_limits(v.sample(rng, 1) + np.cumsum(rng.normal(scale=scale, size=(n, v.robot.nx)), axis=0))
    T = rng.uniform(0.0, 3.0) + 0.01 * np.arange(n)
    return X, T


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 12), k=st.integers(1, 30), moving=st.booleans())
def test_held_clearance_in_one_call_is_the_numpy_one(model: Model, kernels: Kernels, seed, n, k, moving):
    """The loop's verification of a sampled move in one compiled call (its bounds from the kernel's motion bound)
    equals the numpy buffers through the validator's clearance within 1e-9 mm, with and without the hold after
    it, and counts the same samples."""
    rng = np.random.default_rng(seed)
    v = MotionValidator(model, replace(random_scene(rng, k, moving), time_origin=rng.uniform(0, 5)), kernels=kernels)
    X, T = _servo_motion(v, rng, n, rng.choice([1e-3, 0.02, 0.2]))
    for after in (None, (T[-1], T[-1] + 0.5)):
        s0 = v.n_samples
        a = held_clearance(v, X, T, after)
        s1 = v.n_samples
        b = held_clearance(v, X, T, after, compiled=False)
        assert abs(a - b) <= 1e-9
        assert s1 - s0 == v.n_samples - s1 == n + (after is not None)


def test_held_clearance_keeps_the_margin_between_samples(model: Model, kernels: Kernels):
    """Moves whose samples are all clear but whose configurations between them may not be: the one-call check
    subtracts the half bound and flags them (negative) as numpy does; without the margin (the weaker check) the
    samples alone would pass. A time that is not finite goes to numpy, which names it."""
    from crtraj.core.errors import InputError

    rng = np.random.default_rng(11)
    v = MotionValidator(model, random_scene(rng, 12, moving=True), kernels=kernels)
    assert v.kernel is not None
    flagged = 0
    for _ in range(300):
        X, T = _servo_motion(v, rng, 4, 0.15)
        held = held_clearance(v, X, T)
        weak = float(np.min(v.clearance(X, T, T)))
        assert abs(held - held_clearance(v, X, T, compiled=False)) <= 1e-9
        assert held <= weak + 1e-12
        flagged += held < 0.0 <= weak
    assert flagged >= 3
    with pytest.raises(InputError, match="NaN or infinity"):
        held_clearance(v, X, np.array([0.0, 0.01, np.inf, 0.03]))
