"""Obstacle shapes and their distances (crtraj.world.geometry) against independent computations.

- closed forms against brute force: dense samples on each surface (placed in the world by SciPy's
  rotations, not the module's), the distance to the nearest sample within the sampling's covering
  radius, and the sign from an independent inside test;
- gradients against central finite differences away from each shape's non-smooth set;
- the sweep bound never above the signed distance at dense times (a hypothesis property test over
  random shapes, poses, keyframe motions, breathing and intervals), and exact where it should be;
- motions against their definitions (keyframes hit, slerp's constant speed, SciPy's natural spline);
- the sphere obstacles' straight-line profiles against `Scene.states`;
- the CasADi distances against numpy (exact ones to round-off, the smooth box below and within its bound);
- every bad input raises one `InputError` line naming the field.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from crtraj.core.errors import InputError
from crtraj.world.geometry import (
    BOX_SMOOTH_ERROR,
    Box,
    Breathing,
    Capsule,
    Cylinder,
    DistanceField,
    Fixed,
    HalfSpace,
    Keyframes,
    MovingShape,
    Pose,
    Sphere,
    StraightLine,
    casadi_distance,
)
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene


# ----------------------------------------------------------------- surface samples (shape's frame)
def _grid(a: float, b: float, n: int) -> np.ndarray:
    return np.linspace(a, b, n)


def _sphere_cap(r: float, n: int, z_sign: float = 0.0, z_off: float = 0.0) -> tuple[np.ndarray, float]:
    """Lat-long samples of a sphere (z_sign 0) or of its upper/lower half (z_sign +-1), centre (0, 0, z_off),
    and a covering radius: every surface point is within r (d_theta + d_phi) / 2 of a sample (arc >= chord)."""
    theta = _grid(0.0, math.pi, 2 * n + 1) if z_sign == 0 else _grid(0.0, math.pi / 2, n + 1)
    phi = _grid(0.0, 2 * math.pi, 4 * n + 1)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    z = np.cos(th) * (1.0 if z_sign == 0 else z_sign)
    pts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), z], axis=-1).reshape(-1, 3) * r
    pts[:, 2] += z_off
    return pts, r * (theta[1] - theta[0] + phi[1] - phi[0]) / 2


def _side(r: float, z0: float, z1: float, n: int) -> tuple[np.ndarray, float]:
    """The side of a cylinder of radius r, z in [z0, z1]; covering radius from the z and arc spacing."""
    z = _grid(z0, z1, n + 1)
    phi = _grid(0.0, 2 * math.pi, 4 * n + 1)
    zz, ph = np.meshgrid(z, phi, indexing="ij")
    pts = np.stack([r * np.cos(ph), r * np.sin(ph), zz], axis=-1).reshape(-1, 3)
    return pts, math.hypot((z[1] - z[0]) / 2, r * (phi[1] - phi[0]) / 2)


def _disk(r: float, z: float, n: int) -> tuple[np.ndarray, float]:
    rho = _grid(0.0, r, n + 1)
    phi = _grid(0.0, 2 * math.pi, 4 * n + 1)
    rr, ph = np.meshgrid(rho, phi, indexing="ij")
    pts = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.full_like(rr, z)], axis=-1).reshape(-1, 3)
    return pts, (rho[1] - rho[0]) / 2 + r * (phi[1] - phi[0]) / 2


def _rect(h: np.ndarray, axis: int, sign: float, n: int) -> tuple[np.ndarray, float]:
    """One face of a box of half extents h: the face normal to `axis` on its `sign` side."""
    a, b = [i for i in range(3) if i != axis]
    u, v = np.meshgrid(_grid(-h[a], h[a], n + 1), _grid(-h[b], h[b], n + 1), indexing="ij")
    pts = np.zeros((u.size, 3))
    pts[:, a], pts[:, b], pts[:, axis] = u.ravel(), v.ravel(), sign * h[axis]
    return pts, math.hypot(h[a] / n, h[b] / n)


def surface(shape, n: int = 60) -> tuple[np.ndarray, float]:
    """Dense samples (M, 3) of the surface of `shape` in its own frame at scale 1, and their covering radius."""
    if isinstance(shape, Sphere):
        parts = [_sphere_cap(shape.radius, n)]
    elif isinstance(shape, Box):
        h = np.asarray(shape.half_extents)
        parts = [_rect(h, ax, s, n) for ax in range(3) for s in (-1.0, 1.0)]
    elif isinstance(shape, Capsule):
        half = shape.length / 2
        parts = [
            _side(shape.radius, -half, half, n),
            _sphere_cap(shape.radius, n, 1.0, half),
            _sphere_cap(shape.radius, n, -1.0, -half),
        ]
    else:
        half = shape.length / 2
        parts = [_side(shape.radius, -half, half, n), _disk(shape.radius, half, n), _disk(shape.radius, -half, n)]
    return np.concatenate([p for p, _ in parts]), max(e for _, e in parts)


def inside(shape, y: np.ndarray) -> np.ndarray:
    """Independent membership of points y (N, 3) in the shape's frame at scale 1."""
    if isinstance(shape, Sphere):
        return np.sum(y * y, axis=1) < shape.radius**2
    if isinstance(shape, Box):
        return np.all(np.abs(y) < np.asarray(shape.half_extents), axis=1)
    rho2 = y[:, 0] ** 2 + y[:, 1] ** 2
    half = shape.length / 2
    if isinstance(shape, Cylinder):
        return (rho2 < shape.radius**2) & (np.abs(y[:, 2]) < half)
    dz = np.maximum(np.abs(y[:, 2]) - half, 0.0)
    return rho2 + dz**2 < shape.radius**2


def scipy_rot(q) -> Rotation:
    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w])


def random_quat(rng) -> tuple[float, ...]:
    q = rng.normal(size=4)
    return tuple(q / np.linalg.norm(q))


BOUNDED = [
    Sphere(12.0),
    Box((10.0, 25.0, 6.0)),
    Capsule(7.0, 30.0),
    Cylinder(9.0, 22.0),
]


@pytest.mark.parametrize("base", BOUNDED, ids=lambda s: s.kind)
def test_closed_forms_match_brute_force_surface_sampling(base):
    rng = np.random.default_rng(1)
    pose = Pose((5.0, -20.0, 40.0), random_quat(rng))
    shape = replace(base, pose=pose)
    scale = 1.3
    samples, cover = surface(shape)
    rot = scipy_rot(pose.rotation)
    world = rot.apply(samples * scale) + np.asarray(pose.position)
    r = shape.local_radius * scale
    x = np.asarray(pose.position) + rng.uniform(-1.6 * r, 1.6 * r, size=(400, 3))
    # scale by breathing at t = 0: 1 + a sin(phase) = 1.3
    m = MovingShape(shape, breathing=Breathing(0.3, 1.0, math.pi / 2))
    d = m.distance(x, 0.0)
    nearest = np.min(np.linalg.norm(x[:, None, :] - world[None, :, :], axis=2), axis=1)
    assert np.all(np.abs(d) <= nearest + 1e-9)  # no surface sample is nearer than the exact distance
    assert np.all(nearest <= np.abs(d) + cover * scale + 1e-9)  # the nearest sample is within the covering radius
    inner = inside(shape, rot.inv().apply(x - np.asarray(pose.position)) / scale)
    assert np.all((d < 0) == inner)
    assert inner.any() and (~inner).any()


def test_halfspace_matches_brute_force_plane_sampling():
    rng = np.random.default_rng(2)
    pose = Pose((3.0, 4.0, -7.0), random_quat(rng))
    n = np.array([1.0, 2.0, 2.0]) / 3.0
    shape = HalfSpace(tuple(n), offset=5.0, pose=pose)
    scale = 1.3  # breathing scales the offset: the plane n . y = 6.5
    x = np.asarray(pose.position) + rng.uniform(-50, 50, size=(300, 3))
    # the plane n . y = offset, sampled on a patch that holds every projection with room to spare
    e1 = np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    u, v = np.meshgrid(_grid(-200, 200, 401), _grid(-200, 200, 401), indexing="ij")
    local = 5.0 * scale * n + u.reshape(-1, 1) * e1 + v.reshape(-1, 1) * e2
    world = scipy_rot(pose.rotation).apply(local) + np.asarray(pose.position)
    d = MovingShape(shape, breathing=Breathing(0.3, 1.0, math.pi / 2)).distance(x, 0.0)
    nearest = np.array([np.min(np.linalg.norm(world - p, axis=1)) for p in x])
    assert np.all(np.abs(d) <= nearest + 1e-9)
    assert np.all(nearest <= np.abs(d) + math.hypot(0.5, 0.5) + 1e-9)
    y = scipy_rot(pose.rotation).inv().apply(x - np.asarray(pose.position))
    assert np.all((d < 0) == (y @ n < 5.0 * scale))


def _smooth_here(shape, y: np.ndarray, margin: float) -> np.ndarray:
    """Points y (shape's frame) at least `margin` from the surface and the shape's non-smooth set."""
    d, _ = shape.local_distance(y)
    ok = np.abs(d) > margin
    if isinstance(shape, HalfSpace):
        return np.ones(len(y), dtype=bool)
    if isinstance(shape, Sphere):
        return ok & (np.linalg.norm(y, axis=1) > margin)
    if isinstance(shape, Box):
        q = np.sort(np.abs(y) - np.asarray(shape.half_extents), axis=1)
        return ok & ((d > 0) | (q[:, 2] - q[:, 1] > margin))
    if isinstance(shape, Capsule):
        return ok & (np.linalg.norm(y[:, :2], axis=1) > margin)
    rho = np.linalg.norm(y[:, :2], axis=1)
    q = np.stack([rho - shape.radius, np.abs(y[:, 2]) - shape.length / 2], axis=1)
    return ok & (rho > margin) & ((d > 0) | (np.abs(q[:, 0] - q[:, 1]) > margin))


@pytest.mark.parametrize("base", [*BOUNDED, HalfSpace((0.0, 0.6, 0.8), 2.0)], ids=lambda s: s.kind)
def test_gradients_match_finite_differences(base):
    rng = np.random.default_rng(3)
    pose = Pose((1.0, 2.0, 3.0), random_quat(rng))
    m = MovingShape(replace(base, pose=pose), breathing=Breathing(0.2, 2.0, 0.3))
    x = np.asarray(pose.position) + rng.uniform(-40, 40, size=(2000, 3))
    o, r, s = m.frame(0.7)
    keep = _smooth_here(m.shape, (x - o) @ r / s, 1e-3)
    x = x[keep]
    assert len(x) > 500
    _, g = m.distance_and_gradient(x, 0.7)
    eps = 1e-6
    fd = np.stack([(m.distance(x + eps * e, 0.7) - m.distance(x - eps * e, 0.7)) / (2 * eps) for e in np.eye(3)], 1)
    np.testing.assert_allclose(g, fd, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-12)


def test_gradient_on_the_non_smooth_set_is_a_stated_unit_vector():
    # box centre: the nearest face is the thinnest (axis 2 here), + side; capsule axis: +x; sphere centre: +z
    _, g = Box((10.0, 20.0, 5.0)).local_distance(np.zeros((1, 3)))
    np.testing.assert_array_equal(g, [[0.0, 0.0, 1.0]])
    _, g = Capsule(3.0, 10.0).local_distance(np.array([[0.0, 0.0, 2.0]]))
    np.testing.assert_array_equal(g, [[1.0, 0.0, 0.0]])
    _, g = Sphere(3.0).local_distance(np.zeros((1, 3)))
    np.testing.assert_array_equal(g, [[0.0, 0.0, 1.0]])
    d, g = Cylinder(3.0, 10.0).local_distance(np.zeros((1, 3)))
    assert d[0] == -3.0 and np.array_equal(g, [[1.0, 0.0, 0.0]])


# ----------------------------------------------------------------------------------- the sweep bound
def random_shape(rng, kind: int):
    pose = Pose(tuple(rng.uniform(-30, 30, 3)), random_quat(rng))
    if kind == 0:
        return Sphere(float(rng.uniform(1, 30)), pose=pose)
    if kind == 1:
        return Box(tuple(rng.uniform(0.5, 30, 3)), pose=pose)
    if kind == 2:
        return Capsule(float(rng.uniform(1, 20)), float(rng.uniform(0.5, 60)), pose=pose)
    if kind == 3:
        return Cylinder(float(rng.uniform(1, 20)), float(rng.uniform(0.5, 60)), pose=pose)
    n = rng.normal(size=3)
    return HalfSpace(tuple(n / np.linalg.norm(n)), float(rng.uniform(-20, 20)), pose)


def random_motion(rng, kind: str):
    if kind == "fixed":
        return Fixed()
    if kind == "straight":
        return StraightLine(
            tuple(rng.uniform(-50, 50, 3)),
            tuple(rng.uniform(-50, 50, 3)),
            float(rng.uniform(0.2, 2.0)),
            str(rng.choice(["linear", "sin", "cos"])),
        )
    k = int(rng.integers(2, 6))
    times = float(rng.uniform(-0.5, 1.0)) + np.cumsum(rng.uniform(0.1, 1.5, k))
    positions = rng.uniform(-60, 60, (k, 3))
    rotations = [random_quat(rng) for _ in range(k)]
    return Keyframes(tuple(times), positions, rotations, kind)


def ahead_of_surface(m: MovingShape, tm: float, rng, k: int = 60) -> np.ndarray:
    """Points a little ahead of moving surface points at time tm: where the distance falls fastest, so
    the bound is nearly tight (a bound that misses a term of the surface speed fails here)."""
    if isinstance(m.shape, HalfSpace):
        n = np.asarray(m.shape.normal)
        e = np.linalg.svd(n[None, :])[2][1:]  # two unit vectors in the plane
        y = m.shape.offset * n + rng.uniform(-150, 150, (k, 2)) @ e
    else:
        y, _ = surface(m.shape, 8)
        y = y[rng.choice(len(y), k)]

    def world(t: float) -> np.ndarray:
        o, r, s = m.frame(t)
        return o + s * y @ r.T

    eps = 1e-6
    vel = (world(tm + eps) - world(tm - eps)) / (2 * eps)
    speed = np.linalg.norm(vel, axis=1, keepdims=True)
    ahead = np.where(speed > 0, vel / np.where(speed > 0, speed, 1.0), 0.0)
    return world(tm) + rng.uniform(0.0, 2.0, (k, 1)) * ahead


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    kind=st.integers(0, 4),
    motion=st.sampled_from(["fixed", "linear", "cubic", "straight"]),
    breathe=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
    t0=st.floats(-1.0, 6.0),
    span=st.one_of(st.floats(0.0, 0.05), st.floats(0.0, 3.0)),
)
def test_sweep_bound_is_never_above_the_distance_at_dense_times(kind, motion, breathe, seed, t0, span):
    check_sweep(kind, motion, breathe, seed, t0, span)


@pytest.mark.parametrize("kind", range(5), ids=["sphere", "box", "capsule", "cylinder", "halfspace"])
@pytest.mark.parametrize("motion", ["fixed", "linear", "cubic", "straight"])
def test_sweep_bound_on_seeded_random_cases(kind, motion):
    # The same check on 20 uniformly random cases per shape and motion, for a reproducible spread that
    # hypothesis's search (which favours small seeds and zero spans) does not promise.
    rng = np.random.default_rng(100 * kind + len(motion))
    for seed in rng.integers(0, 2**32, 20):
        t0, span = float(rng.uniform(-1, 6)), float(rng.choice([0.05, 0.5, 3.0]) * rng.uniform())
        check_sweep(kind, motion, bool(rng.integers(2)), int(seed), t0, span)


def check_sweep(kind: int, motion: str, breathe: bool, seed: int, t0: float, span: float) -> None:
    """The lower bound over [t0, t0 + span] is at most the distance at 201 times, for random and
    nearly-worst points of a random moving shape."""
    rng = np.random.default_rng(seed)
    shape = random_shape(rng, kind)
    breathing = (
        Breathing(float(rng.uniform(-0.6, 0.6)), float(rng.uniform(0, 10)), float(rng.uniform(0, 6)))
        if breathe
        else None
    )
    m = MovingShape(shape, random_motion(rng, motion), breathing)
    t1 = t0 + span
    x = np.concatenate([rng.uniform(-120, 120, (40, 3)), ahead_of_surface(m, 0.5 * (t0 + t1), rng)])
    lb = m.lower_bound(x, t0, t1)
    dense = np.min(np.stack([m.distance(x, t) for t in np.linspace(t0, t1, 201)]), axis=0)
    assert np.all(lb <= dense + 1e-9), f"bound above the distance by {np.max(lb - dense):.3g} mm"


def test_sweep_bound_is_exact_for_a_sphere_approaching_at_constant_speed():
    # centre x: 0 -> 100 mm over [0, 1] s, radius 10; the point at x = 200 is nearest at t = 1: 90 mm.
    m = MovingShape(Sphere(10.0), Keyframes((0.0, 1.0), ((0, 0, 0), (100, 0, 0))))
    assert m.lower_bound([[200.0, 0.0, 0.0]], 0.0, 1.0)[0] == pytest.approx(90.0, abs=1e-12)
    assert m.surface_speed(0.0, 1.0) == pytest.approx(100.0)
    # and after the last keyframe nothing moves: the bound is the distance
    assert m.lower_bound([[200.0, 0.0, 0.0]], 1.0, 9.0)[0] == pytest.approx(90.0, abs=1e-12)


def test_sweep_speed_counts_rotation_about_the_motion_origin_and_growth():
    # a box 50 mm from the motion's origin turning at pi rad/s, breathing: v + w (|c| + s_max r) + s_rate r
    box = Box((3.0, 4.0, 12.0), pose=Pose((30.0, 40.0, 0.0)))
    motion = Keyframes((0.0, 1.0), ((0, 0, 0), (0, 0, 0)), ((1, 0, 0, 0), (0, 0, 0, 1)))
    m = MovingShape(box, motion, Breathing(0.1, 2.0, 0.0))
    r = 13.0
    assert m.surface_speed(0.0, 1.0) == pytest.approx(math.pi * (50.0 + 1.1 * r) + 0.2 * r)


def test_sweep_bound_is_nearly_tight_for_a_grown_capsule_turning_about_its_centre():
    # Scale 1.6 (breathing held at its crest), 2 rad/s about x: the side near the tips moves along its
    # normal at up to 2 * 1.6 * 30 = 96 mm/s, the bound's L = 2 * 1.6 * 31 = 99.2 mm/s (a bound that
    # forgot the scale, 62 mm/s, would be above the distance here).
    half_turn = (math.cos(1.0), math.sin(1.0), 0.0, 0.0)
    m = MovingShape(
        Capsule(1.0, 60.0),
        Keyframes((0.0, 1.0), ((0, 0, 0), (0, 0, 0)), ((1, 0, 0, 0), half_turn)),
        Breathing(0.6, 0.0, math.pi / 2),
    )
    assert m.surface_speed(0.4, 0.45) == pytest.approx(2.0 * 1.6 * 31.0)
    x = ahead_of_surface(m, 0.425, np.random.default_rng(5), 400)
    lb = m.lower_bound(x, 0.4, 0.45)
    dense = np.min(np.stack([m.distance(x, t) for t in np.linspace(0.4, 0.45, 201)]), axis=0)
    assert np.all(lb <= dense + 1e-9)
    assert np.min(dense - lb) < 0.1 * 0.025 * m.surface_speed(0.4, 0.45)


# ----------------------------------------------------------------------------------------- motions
def test_keyframes_hit_their_poses_and_slerp_turns_at_constant_speed():
    rng = np.random.default_rng(6)
    times = (0.5, 1.0, 2.5, 3.0)
    pos = rng.uniform(-50, 50, (4, 3))
    quats = [random_quat(rng) for _ in range(4)]
    for interp in ("linear", "cubic"):
        k = Keyframes(times, pos, quats, interp)
        for t, p, q in zip(times, pos, quats, strict=True):
            p_t, r_t = k.pose(t)
            np.testing.assert_allclose(p_t, p, atol=1e-9)
            np.testing.assert_allclose(r_t, scipy_rot(q).as_matrix(), atol=1e-9)
        # before the first and after the last keyframe the pose holds
        np.testing.assert_allclose(k.pose(-3.0)[0], pos[0], atol=1e-12)
        np.testing.assert_allclose(k.pose(9.0)[1], scipy_rot(quats[-1]).as_matrix(), atol=1e-9)
    k = Keyframes(times, pos, quats)
    np.testing.assert_allclose(k.pose(1.75)[0], 0.5 * (pos[1] + pos[2]), atol=1e-12)
    # slerp: the rotation from keyframe 1 grows linearly in time, the short way (SciPy's relative angle)
    total = (scipy_rot(quats[1]).inv() * scipy_rot(quats[2])).magnitude()
    for u in (0.1, 0.5, 0.9):
        r_t = Rotation.from_matrix(k.pose(1.0 + 1.5 * u)[1])
        assert (scipy_rot(quats[1]).inv() * r_t).magnitude() == pytest.approx(u * total, abs=1e-9)


def test_cubic_keyframes_are_scipys_natural_spline():
    rng = np.random.default_rng(7)
    times = np.cumsum(rng.uniform(0.2, 1.0, 5))
    pos = rng.uniform(-50, 50, (5, 3))
    k = Keyframes(tuple(times), pos, interpolation="cubic")
    ref = CubicSpline(times, pos, bc_type="natural")
    for t in np.linspace(times[0], times[-1], 57):
        np.testing.assert_allclose(k.pose(t)[0], ref(t), atol=1e-9)


@pytest.mark.parametrize("interp", ["linear", "cubic"])
def test_keyframe_speed_bounds_hold_at_dense_times(interp):
    rng = np.random.default_rng(8)
    k = Keyframes((0.0, 0.4, 1.5, 2.0, 3.5), rng.uniform(-60, 60, (5, 3)), [random_quat(rng) for _ in range(5)], interp)
    short = [(a, a + float(rng.uniform(0.05, 0.4))) for a in rng.uniform(-0.2, 3.4, 12)]
    for t0, t1 in [(0.1, 0.3), (0.2, 1.9), (-1.0, 0.5), (1.4, 4.0), *short]:
        v, w = k.speed_bound(t0, t1)
        ts = np.linspace(t0, t1, 1001)
        p = np.array([k.pose(t)[0] for t in ts])
        r = Rotation.from_matrix(np.array([k.pose(t)[1] for t in ts]))
        dt = ts[1] - ts[0]
        assert np.max(np.linalg.norm(np.diff(p, axis=0), axis=1)) / dt <= v + 1e-9
        assert np.max((r[:-1].inv() * r[1:]).magnitude()) / dt <= w + 1e-9
        # and tight: within 1 % of the largest measured speeds; the cubic's bound is the norm of the
        # per-axis maxima, which may be up to sqrt(3) above the largest speed
        tight = 0.99 if interp == "linear" else 1.0 / math.sqrt(3.0)
        assert np.max(np.linalg.norm(np.diff(p, axis=0), axis=1)) / dt >= tight * v
        assert np.max((r[:-1].inv() * r[1:]).magnitude()) / dt >= 0.99 * w


def test_sphere_obstacles_are_one_case_of_moving_shapes():
    # The straight-line profiles and additive breathing of `Obstacle`, read through `Scene.states`.
    rng = np.random.default_rng(9)
    for profile in ("linear", "sin", "cos"):
        ob = Obstacle(
            center=tuple(rng.uniform(-50, 50, 3)),
            radius=20.0,
            amplitude=5.0,
            omega=3.0,
            phase=0.4,
            to=tuple(rng.uniform(-50, 50, 3)),
            duration=1.3,
            profile=profile,
        )
        m, scene = MovingShape.from_obstacle(ob), Scene((ob,))
        x = rng.uniform(-100, 100, (50, 3))
        for t in np.linspace(-0.5, 4.0, 23):
            c, r = scene.states(t)
            np.testing.assert_allclose(m.distance(x, t), np.linalg.norm(x - c[0], axis=1) - r[0], atol=1e-9)
        assert m.motion.speed_bound(0.0, 10.0)[0] == pytest.approx(ob.center_speed_max)
        assert m.breathing.rate_max * ob.radius == pytest.approx(ob.radius_rate_max)


def test_moving_shapes_implement_the_distance_interface():
    assert isinstance(MovingShape(Box((1.0, 2.0, 3.0))), DistanceField)
    assert not isinstance(Box((1.0, 2.0, 3.0)), DistanceField)


# ------------------------------------------------------------------------------------------ CasADi
def _cas_eval(shape, x: np.ndarray, o, r, s, smooth: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Distances and gradients from a CasADi function of the point, origin, rotation and scale (all symbols)."""
    xs, os_, rs, ss = ca.SX.sym("x", 3), ca.SX.sym("o", 3), ca.SX.sym("r", 3, 3), ca.SX.sym("s")
    d = casadi_distance(shape, xs, os_, rs, ss, smooth=smooth)
    f = ca.Function("f", [xs, os_, rs, ss], [d, ca.gradient(d, xs)]).map(len(x))
    dv, gv = f(x.T, np.tile(o[:, None], len(x)), np.tile(r, len(x)), np.full(len(x), s))
    return np.asarray(dv).ravel(), np.asarray(gv).T


@pytest.mark.parametrize("shape", [Sphere(12.0), Capsule(5.0, 30.0), HalfSpace((0.0, 0.6, 0.8), 3.0)], ids=str)
def test_casadi_exact_distances_match_numpy(shape):
    rng = np.random.default_rng(10)
    m = MovingShape(replace(shape, pose=Pose((4.0, -3.0, 9.0), random_quat(rng))), breathing=Breathing(0.3, 1.0, 0.5))
    x = rng.uniform(-60, 60, (500, 3))
    o, r, s = m.frame(0.2)
    d, g = m.distance_and_gradient(x, 0.2)
    dc, gc = _cas_eval(m.shape, x, o, r, s)
    np.testing.assert_allclose(dc, d, atol=1e-9)
    np.testing.assert_allclose(gc, g, atol=1e-9)
    # without a frame: the shape's own pose
    xs = ca.SX.sym("x", 3)
    f = ca.Function("f", [xs], [casadi_distance(m.shape, xs)])
    np.testing.assert_allclose(float(f(x[0])), m.shape.local_distance((x[:1] - o) @ r)[0][0], atol=1e-9)


@pytest.mark.parametrize("shape", [Box((10.0, 25.0, 6.0)), Cylinder(9.0, 22.0)], ids=str)
@pytest.mark.parametrize("smooth", [0.2, 1.0])
def test_casadi_smooth_box_and_cylinder_are_lower_bounds_within_their_error(shape, smooth):
    rng = np.random.default_rng(11)
    m = MovingShape(replace(shape, pose=Pose((4.0, -3.0, 9.0), random_quat(rng))))
    o, r, s = m.frame(0.0)
    # far, near, inside, and on the symmetry planes and the edges (where the exact one is not smooth)
    x = np.concatenate([rng.uniform(-60, 60, (2000, 3)), o + rng.normal(scale=3.0, size=(500, 3))])
    edges = o + np.array([[10.0, 25.0, z] for z in np.linspace(-8, 8, 41)]) @ r.T
    x = np.concatenate([x, edges])
    d = m.distance(x, 0.0)
    dc, gc = _cas_eval(m.shape, x, o, r, s, smooth=smooth)
    assert np.all(dc <= d + 1e-9)
    gap = d - dc
    assert np.max(gap) <= BOX_SMOOTH_ERROR * smooth
    assert np.max(gap) >= 0.3 * smooth  # the stated error is of the right size, not vacuous
    assert np.all(np.isfinite(gc))


# --------------------------------------------------------------------------------------- bad input
BAD = {
    "box zero extent": (lambda: Box((1.0, 0.0, 2.0)), "box.half_extents[1]: must be > 0 mm"),
    "box negative extent": (lambda: Box((1.0, 2.0, -3.0), name="table"), "box 'table'.half_extents[2]: must be > 0"),
    "sphere NaN radius": (lambda: Sphere(float("nan")), "sphere.radius: must be finite"),
    "capsule zero length": (lambda: Capsule(2.0, 0.0), "capsule.length: must be > 0"),
    "cylinder negative radius": (lambda: Cylinder(-1.0, 3.0), "cylinder.radius: must be > 0"),
    "box two extents": (lambda: Box((1.0, 2.0)), "box.half_extents: expected 3 numbers"),
    "rotation not unit": (lambda: Pose(rotation=(1.0, 0.1, 0.0, 0.0)), "pose.rotation: must be a unit quaternion"),
    "rotation NaN": (lambda: Pose(rotation=(float("nan"), 0.0, 0.0, 0.0)), "pose.rotation[0]: must be finite"),
    "position NaN": (lambda: Pose(position=(0.0, float("nan"), 0.0)), "pose.position[1]: must be finite"),
    "normal zero": (lambda: HalfSpace((0.0, 0.0, 0.0)), "halfspace.normal: must be a unit vector"),
    "times out of order": (
        lambda: Keyframes((0.0, 2.0, 1.0), ((0, 0, 0),) * 3),
        "keyframes.times: must be strictly increasing, got 1 s after 2 s at index 2",
    ),
    "times repeated": (lambda: Keyframes((0.0, 0.0), ((0, 0, 0),) * 2), "keyframes.times: must be strictly increasing"),
    "keyframe rotation not unit": (
        lambda: Keyframes((0.0, 1.0), ((0, 0, 0),) * 2, ((1, 0, 0, 0), (2, 0, 0, 0))),
        "keyframes.rotations[1]: must be a unit quaternion",
    ),
    "positions wrong count": (lambda: Keyframes((0.0, 1.0), ((0, 0, 0),)), "keyframes.positions: expected shape"),
    "interpolation unknown": (
        lambda: Keyframes((0.0, 1.0), ((0, 0, 0),) * 2, interpolation="spline"),
        "keyframes.interpolation: must be one of linear, cubic",
    ),
    "breathing too deep": (lambda: Breathing(1.0, 1.0), "breathing.amplitude: must be in (-1, 1)"),
    "interval reversed": (lambda: MovingShape(Sphere(1.0)).lower_bound([[0, 0, 0]], 2.0, 1.0), "t1: must be >= t0"),
    "points wrong shape": (lambda: MovingShape(Sphere(1.0)).distance([[0, 0]], 0.0), "points: expected shape"),
    "points NaN": (lambda: MovingShape(Sphere(1.0)).distance([[0, 0, float("nan")]], 0.0), "points: contains NaN"),
    "not a shape": (lambda: MovingShape("box"), "shape: expected one of sphere, box"),
    "smooth zero": (
        lambda: casadi_distance(Box((1.0, 1.0, 1.0)), ca.SX.sym("x", 3), smooth=0.0),
        "smooth: must be > 0",
    ),
    "obstacle radius 0": (
        lambda: MovingShape.from_obstacle(Obstacle((0, 0, 0), 0.0)),
        "obstacle.radius: a shape needs a mean radius > 0 mm",
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_raises_one_line_naming_the_field(case):
    make, expected = BAD[case]
    with pytest.raises(InputError) as err:
        make()
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(expected.split(":")[0])
    assert expected in msg, msg


def test_casadi_smooth_box_has_bounded_curvature_where_the_exact_one_has_kinks():
    # Along lines through the centre, a face, an edge and a corner region, the second difference of
    # the smooth distance stays below a few / k while the exact one shows kinks (about 1 / step).
    box, k, step = Box((10.0, 25.0, 6.0)), 0.5, 1e-3
    xs = ca.SX.sym("x", 3)
    f = ca.Function("f", [xs], [casadi_distance(box, xs, smooth=k)])
    for start, direction in [((-20, 0, 0), (1, 0, 0)), ((-20, 0, 0), (1, 1, 0.3)), ((-20, -30, -10), (1, 1.5, 0.6))]:
        u = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
        pts = np.asarray(start, dtype=float) + np.arange(0.0, 60.0, step)[:, None] * u
        smooth = np.asarray(f.map(len(pts))(pts.T)).ravel()
        exact = box.local_distance(pts)[0]
        assert np.max(np.abs(np.diff(smooth, 2))) / step**2 < 10.0 / k
        assert np.max(np.abs(np.diff(exact, 2))) / step**2 > 100.0 / k


def test_cubic_speed_bound_finds_the_fastest_instant_inside_a_piece():
    # Along one axis the speed is |a quadratic| on each piece; its peak often lies inside a piece,
    # where neither end of a short interval around it sees it.
    rng = np.random.default_rng(12)
    times = np.cumsum(rng.uniform(0.3, 1.0, 8))
    pos = np.zeros((8, 3))
    pos[:, 0] = rng.uniform(-60, 60, 8)
    k = Keyframes(tuple(times), pos, interpolation="cubic")
    ts = np.linspace(times[0], times[-1], 20001)
    speed = np.abs(np.gradient(np.array([k.pose(t)[0][0] for t in ts]), ts))
    peaks = [i for i in range(1, len(ts) - 1) if speed[i] >= speed[i - 1] and speed[i] >= speed[i + 1]]
    peaks = [i for i in peaks if np.min(np.abs(times - ts[i])) > 0.05]
    assert peaks, "no peak inside a piece"
    for i in peaks:
        v, _ = k.speed_bound(ts[i] - 0.04, ts[i] + 0.04)
        assert speed[i] <= v + 1e-6
        assert speed[i] >= 0.999 * v


def test_the_concept_pages_python_runs():
    """The ```python block of docs/concepts/shapes.md runs as it is."""
    page = Path(__file__).resolve().parent.parent / "docs" / "concepts" / "shapes.md"
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)
    assert len(blocks) == 1
    root = page.parent.parent.parent
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.run([sys.executable, "-c", blocks[0]], cwd=root, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["[", "50.", "200.]"]
