"""The nearest surface point of every shape (`nearest_surface_points`) and the view's closest-approach line that is
drawn to it (`crtraj.viz.timeline.closest_approach`), against brute-force surface sampling."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from conftest import PROBLEMS
from scipy.spatial import cKDTree
from test_geometry import BOUNDED, random_quat, surface

from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.viz.timeline import CLEARANCE_POINTS, closest_approach
from crtraj.world.geometry import (
    Box,
    Breathing,
    HalfSpace,
    Keyframes,
    Mesh,
    MovingShape,
    PointCloud,
    Pose,
    exact_distance,
    nearest_surface_points,
    point_triangle_distance,
)

MOTION = Keyframes((0.0, 2.0), ((0.0, 0.0, 0.0), (30.0, -10.0, 5.0)), ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)))


def world_samples(ms: MovingShape, local: np.ndarray, t: float) -> np.ndarray:
    """Samples of the shape's surface (its frame, scale 1) placed in the world at time t."""
    o, r, s = ms.frame(t)
    return o + (s * local) @ r.T


def check_against_samples(x, d, q, world, cover):
    """|x - q| is |d|; no surface sample is nearer than |d|; the nearest sample is within the samples' covering
    radius of it; q is on the sampled surface (within the covering radius of a sample). Nearest samples by a
    KD-tree over all of them (exact nearest neighbours)."""
    np.testing.assert_allclose(np.linalg.norm(x - q, axis=1), np.abs(d), atol=1e-9)
    tree = cKDTree(world)
    nearest = tree.query(x)[0]
    assert np.all(np.abs(d) <= nearest + 1e-9)
    assert np.all(nearest <= np.abs(d) + cover + 1e-9)
    assert np.all(tree.query(q)[0] <= cover + 1e-9)


@pytest.mark.parametrize("base", BOUNDED, ids=lambda s: s.kind)
def test_primitives_nearest_point_is_on_the_surface_and_nearest(base):
    """Sphere, box, capsule, cylinder, posed, moving on keyframes and breathing (scale 1.2 at t = 0.7 s)."""
    rng = np.random.default_rng(2)
    shape = replace(base, pose=Pose((5.0, -20.0, 40.0), random_quat(rng)))
    ms = MovingShape(shape, MOTION, Breathing(0.2, 1.0, math.pi / 2 - 0.7))
    t = 0.7
    local, cover = surface(shape)
    o, _, s = ms.frame(t)
    world = world_samples(ms, local, t)
    r = shape.local_radius * s
    x = o + rng.uniform(-1.6 * r, 1.6 * r, size=(300, 3))
    d, q = nearest_surface_points(ms, x, t)
    check_against_samples(x, d, q, world, cover * s)
    assert (d < 0).any() and (d > 0).any()  # points inside step out to the nearest face too


def test_halfspace_nearest_point_is_the_foot_of_the_perpendicular():
    """A turned plane: q lies on it, x - q is along its normal, and a dense patch of the plane has no nearer point."""
    rng = np.random.default_rng(3)
    rot = random_quat(rng)
    ms = MovingShape(HalfSpace((0.0, 0.0, 1.0), 4.0, Pose((1.0, 2.0, 3.0), rot)), MOTION)
    t = 1.1
    o, r, _ = ms.frame(t)
    n = r @ np.array([0.0, 0.0, 1.0])
    x = o + rng.uniform(-30.0, 30.0, size=(50, 3))
    d, q = nearest_surface_points(ms, x, t)
    np.testing.assert_allclose((q - o) @ n, 4.0, atol=1e-9)
    np.testing.assert_allclose(np.cross(x - q, n), 0.0, atol=1e-9)
    u, v = np.meshgrid(np.linspace(-60.0, 60.0, 241), np.linspace(-60.0, 60.0, 241))
    patch = np.stack([u.ravel(), v.ravel(), np.full(u.size, 4.0)], axis=1)
    check_against_samples(x, d, q, world_samples(ms, patch, t), math.hypot(0.25, 0.25))


def triangle_samples(tri: np.ndarray, n: int) -> tuple[np.ndarray, float]:
    """Barycentric grid samples of every triangle (n steps per edge) and their covering radius (longest
    sub-edge)."""
    ij = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)], dtype=float) / n
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    pts = a[:, None] + ij[None, :, :1] * (b - a)[:, None] + ij[None, :, 1:] * (c - a)[:, None]
    edges = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2).max()
    return pts.reshape(-1, 3), edges / n


def test_mesh_nearest_point_is_on_a_triangle_and_nearest():
    """A posed, moving icosphere mesh (80 triangles, sampled every 4 mm by the planner): the point returned lies on a
    triangle (the verifier's point-triangle distance 0) and no dense sample of the triangles is nearer; the distance is
    the true one, not the planner's sample-based bound."""
    ico = trimesh.creation.icosphere(subdivisions=1, radius=20.0)
    tri = np.asarray(ico.triangles)
    rng = np.random.default_rng(4)
    ms = MovingShape(Mesh(tri, 4.0, Pose((0.0, 10.0, 5.0), random_quat(rng))), MOTION)
    t = 0.4
    o, r, _ = ms.frame(t)
    x = o + rng.uniform(-35.0, 35.0, size=(200, 3))
    d, q = nearest_surface_points(ms, x, t)
    local, cover = triangle_samples(tri, 40)
    check_against_samples(x, d, q, world_samples(ms, local, t), cover)
    on = point_triangle_distance((q - o) @ r, tri).min(axis=1)
    assert np.all(on <= 1e-9)
    np.testing.assert_allclose(np.abs(d), exact_distance(ms, x, t), atol=1e-9)
    assert np.any(np.abs(d) - ms.distance(x, t) > 0.1)  # the planner's bound is below it by up to its cover


def test_point_cloud_nearest_point_is_on_the_nearest_ball():
    """Balls of 2 mm about points 10 mm apart: the point returned is on the sampled surface of the union."""
    pts = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 12.0, 3.0], [5.0, 5.0, 15.0]])
    ms = MovingShape(PointCloud(pts, 2.0, Pose((3.0, 0.0, 0.0), random_quat(np.random.default_rng(5)))), MOTION)
    t = 1.5
    o, _, _ = ms.frame(t)
    x = o + np.random.default_rng(6).uniform(-15.0, 25.0, size=(200, 3))
    d, q = nearest_surface_points(ms, x, t)
    th, ph = np.meshgrid(np.linspace(0.0, math.pi, 121), np.linspace(0.0, 2.0 * math.pi, 241), indexing="ij")
    sphere = 2.0 * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1).reshape(-1, 3)
    local = (pts[:, None, :] + sphere[None]).reshape(-1, 3)
    cover = 2.0 * (math.pi / 120 + 2.0 * math.pi / 240) / 2.0
    check_against_samples(x, d, q, world_samples(ms, local, t), cover)


def test_closest_approach_line_ends_on_the_nearest_surface():
    """The view's closest approach among a sphere and a turned box: the clearance of each is the brute-force minimum
    over the same backbone points (the verifier's exact distance, minus body radius and D_sf); the nearest column
    is the smaller; the line's obstacle end lies on that obstacle's surface and the line is as long as the
    clearance plus D_sf."""
    model = Model(load_robot(PROBLEMS / "robots" / "cdsr2.toml"))
    x = np.array([[0.3, 0.1, -0.2, 0.1, 0.0], [0.0, 0.4, 0.1, -0.3, -20.0], [-0.2, -0.1, 0.3, 0.2, 10.0]])
    box = MovingShape(Box((20.0, 30.0, 15.0), Pose((60.0, 0.0, 300.0), (0.9238795, 0.0, 0.3826834, 0.0))), MOTION)
    centers = np.tile(np.array([[-40.0, 30.0, 250.0]]), (3, 1, 1))
    radii = np.full((3, 1), 15.0)
    t = np.array([0.0, 0.5, 1.0])
    safety = 5.0
    clear, near, body, obst = closest_approach(model, x, centers, radii, safety, (box,), t)
    P = model.points(x, CLEARANCE_POINTS)
    body_r = model.robot.body_radius
    for i in range(3):
        sphere = np.linalg.norm(P[i] - centers[i, 0], axis=1).min() - radii[i, 0] - body_r - safety
        boxd = exact_distance(box, P[i], t[i]).min() - body_r - safety
        np.testing.assert_allclose(clear[i], [sphere, boxd], atol=1e-9)
        assert near[i] == int(np.argmin([sphere, boxd]))
        on = exact_distance(box, obst[i : i + 1], t[i])[0] if near[i] == 1 else (
            np.linalg.norm(obst[i] - centers[i, 0]) - radii[i, 0]
        )  # fmt: skip
        assert abs(on) <= 1e-9
        np.testing.assert_allclose(np.linalg.norm(obst[i] - body[i]), clear[i, near[i]] + safety, atol=1e-9)
    assert set(near) == {0, 1}  # both kinds of obstacle are the nearest somewhere
