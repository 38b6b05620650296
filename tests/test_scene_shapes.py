"""Shapes in scenes (issue 39): the problem file's [[scene.shape]], point sets, the chord bound the checker uses,
the brute-force distances the verifiers use, and the checker itself against an independent dense check."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.validity import StateValidityChecker
from crtraj.world.geometry import (
    MAX_POINTS,
    Box,
    Breathing,
    Capsule,
    Cylinder,
    HalfSpace,
    Keyframes,
    Mesh,
    MovingShape,
    PointCloud,
    Pose,
    StraightLine,
    chord_clearance,
    exact_distance,
    exact_min_clearance,
    load_points,
    point_triangle_distance,
    shape_from_table,
)
from crtraj.world.scene import Scene

ROBOT = (Path(__file__).resolve().parents[1] / "problems" / "robots" / "cdsr2.toml").as_posix()
Q30 = [0.9659258, 0.0, 0.0, 0.2588190]  # 30 degrees about z


def _shape(d: dict) -> MovingShape:
    return shape_from_table(Table(d, "scene.shape[0]"))


def _pipe(tmp_path, name="pipe.stl"):
    m = trimesh.creation.annulus(r_min=30.0, r_max=34.0, height=120.0, sections=24)
    path = tmp_path / name
    m.export(path)
    return path, m


# ------------------------------------------------------------------ problem file
def test_every_kind_reads_and_round_trips(tmp_path):
    """Each kind with a pose, a motion and breathing reads from a table and writes back to the same shape."""
    pipe, _ = _pipe(tmp_path)
    cloud = tmp_path / "cloud.npy"
    np.save(cloud, np.random.default_rng(0).normal(size=(50, 3)) * 20.0)
    tables = [
        {"kind": "box", "half_extents": [10, 20, 30], "position": [1, 2, 3], "rotation": Q30},
        {"kind": "capsule", "radius": 5, "length": 40, "motion": {"to": [0, 50, 0], "duration": 2, "profile": "cos"}},
        {"kind": "cylinder", "radius": 5, "length": 40, "breathing": {"amplitude": 0.1, "omega": 2.0}},
        {"kind": "halfspace", "normal": [0, 0, 1], "offset": -5},
        {
            "kind": "box",
            "half_extents": [5, 5, 5],
            "position": [60, 0, 0],
            "keyframes": {"times": [0, 2], "positions": [[0, 0, 0], [0, 0, 10]], "rotations": [[1, 0, 0, 0], Q30]},
        },
        {"kind": "mesh", "file": str(pipe), "spacing": 3.0},
        {"kind": "points", "file": str(cloud), "radius": 2.0},
    ]
    pts = np.random.default_rng(1).normal(size=(40, 3)) * 80.0
    for i, d in enumerate(tables):
        ms = _shape({"name": f"s{i}", **d})
        scene = Scene(shapes=(ms,))
        again = Scene.from_table(Table(scene.to_dict(), "scene")).shapes[0]
        for t in (0.0, 0.7, 1.9):
            np.testing.assert_allclose(again.distance(pts, t), ms.distance(pts, t), atol=1e-9)


def test_problem_file_paths_are_relative_to_the_file(tmp_path):
    """A mesh file named in a problem file is found next to it, whatever the working directory."""
    _pipe(tmp_path)
    robot = ROBOT
    (tmp_path / "p.toml").write_text(
        f'robot = "{robot}"\n[task]\nstart = [0, 0, 390]\ngoal = [0, 50, 380]\n'
        '[[scene.shape]]\nname = "pipe"\nkind = "mesh"\nfile = "pipe.stl"\n'
    )
    prob = Problem.load(tmp_path / "p.toml")
    scene = prob.options(Scene, "scene")
    assert scene.n_shapes == 1 and scene.shapes[0].shape.kind == "mesh"


@pytest.mark.parametrize(
    ("table", "field"),
    [
        ({"kind": "box", "half_extents": [10, 0, 5]}, "half_extents[1]"),
        ({"kind": "box", "half_extents": [10, 10, 5], "rotation": [1, 0, 0, 0.1]}, "rotation"),
        ({"kind": "cone", "radius": 1}, "scene.shape[0].kind"),
        ({"kind": "capsule", "radius": -1, "length": 3}, "radius"),
        (
            {"kind": "box", "half_extents": [1, 1, 1], "keyframes": {"times": [0, 2, 1], "positions": [[0] * 3] * 3}},
            "keyframes.times",
        ),
        ({"kind": "box", "half_extents": [1, 1, 1], "colour": "red"}, "colour"),
        ({"kind": "cylinder", "radius": 1, "length": 1, "breathing": {"amplitude": 1.0}}, "breathing.amplitude"),
    ],
)
def test_bad_shapes_are_one_line_naming_the_field(table, field):
    """A zero extent, a quaternion that is not unit, an unknown kind or key, keyframes out of order: one line."""
    with pytest.raises(InputError) as err:
        _shape(table)
    msg = str(err.value)
    assert "\n" not in msg and field in msg and msg.startswith("scene.shape[0]")


def test_bad_data_files_are_one_line(tmp_path):
    """An empty cloud, a file that is not a mesh, and a cloud beyond the point limit are refused in one line."""
    empty = tmp_path / "empty.csv"
    empty.write_text("x,y,z\n")
    junk = tmp_path / "junk.stl"
    junk.write_bytes(b"this is not an stl file at all")
    big = tmp_path / "big.npy"
    np.lib.format.open_memmap(big, mode="w+", dtype=np.float64, shape=(MAX_POINTS + 1, 3)).flush()
    cases = [
        ({"kind": "points", "file": str(empty), "radius": 1}, "holds no points"),
        ({"kind": "mesh", "file": str(junk)}, "junk.stl"),
        ({"kind": "points", "file": str(big), "radius": 1}, "more than"),
        ({"kind": "mesh", "file": str(tmp_path / "none.obj")}, "no such file"),
    ]
    for table, words in cases:
        with pytest.raises(InputError) as err:
            _shape(table)
        assert "\n" not in str(err.value) and words in str(err.value) and "scene.shape[0].file" in str(err.value)


# ------------------------------------------------------------------ point sets
def test_point_cloud_distance_is_the_brute_force_one(tmp_path):
    """The KD-tree distance of a cloud equals numpy's brute force, from a .csv file."""
    rng = np.random.default_rng(2)
    pts = rng.uniform(-50, 50, size=(300, 3))
    path = tmp_path / "c.csv"
    np.savetxt(path, pts, delimiter=",", header="x,y,z")
    cloud = PointCloud(load_points(path), 1.5, Pose((5, 0, 0), Q30))
    q = rng.uniform(-80, 80, size=(200, 3))
    y = (q - np.array([5, 0, 0])) @ cloud.pose.matrix
    brute = np.linalg.norm(y[:, None] - pts[None], axis=-1).min(axis=1) - 1.5
    np.testing.assert_allclose(MovingShape(cloud).distance(q, 0.0), brute, atol=1e-9)


def test_mesh_distance_is_below_the_exact_one_by_at_most_its_cover(tmp_path):
    """The mesh's sampled distance d satisfies d <= exact <= d + cover (exact: point-to-triangle brute force)."""
    _, m = _pipe(tmp_path)
    mesh = Mesh(np.asarray(m.triangles), spacing=3.0)
    q = np.random.default_rng(3).uniform(-60, 60, size=(400, 3))
    d = MovingShape(mesh).distance(q, 0.0)
    exact = point_triangle_distance(q, mesh.triangles).min(axis=1)
    assert np.all(d <= exact + 1e-9)
    assert np.all(exact <= d + mesh.cover_radius + 1e-9)
    assert mesh.cover_radius <= 3.0 / np.sqrt(3.0) + 1e-12
    # the bound is not empty: some points come within a fifth of the cover of it
    assert np.max(exact - d) > 0.2 * mesh.cover_radius


def test_point_triangle_distance_matches_dense_surface_samples():
    """Ericson's closest point by region against 30k samples of an icosphere's surface."""
    m = trimesh.creation.icosphere(2, 30.0)
    q = np.random.default_rng(4).normal(size=(200, 3)) * 50.0
    d = point_triangle_distance(q, np.asarray(m.triangles)).min(axis=1)
    samples = trimesh.sample.sample_surface_even(m, 30000, seed=0)[0]
    dense = np.linalg.norm(q[:, None] - samples[None], axis=-1).min(axis=1)
    assert np.all(d <= dense + 1e-9) and np.max(dense - d) < 0.5


@pytest.mark.parametrize("kind", ["box", "cylinder", "capsule", "halfspace"])
def test_exact_distances_agree_with_the_closed_forms(kind):
    """The verifiers' brute-force distances against the planner's closed forms: equal for the box (both exact),
    the capsule, cylinder and half space (different formulas: triangles, 2-D segments, definitions)."""
    shapes = {
        "box": Box((20, 30, 40), Pose((1, 2, 3), Q30)),
        "cylinder": Cylinder(20, 50, Pose((0, 5, 0), Q30)),
        "capsule": Capsule(10, 50, Pose((0, 0, 9), Q30)),
        "halfspace": HalfSpace((0, 0.6, 0.8), 4.0),
    }
    ms = MovingShape(shapes[kind], StraightLine((0, 0, 0), (10, 0, 0), 2.0), Breathing(0.1, 1.0))
    q = np.random.default_rng(5).normal(size=(1500, 3)) * 60
    for t in (0.0, 1.3):
        closed, exact = ms.distance(q, t), exact_distance(ms, q, t)
        np.testing.assert_allclose(exact, closed, atol=1e-9)


# ------------------------------------------------------------------ chords and the checker
def _dense_chord_min(ms: MovingShape, P: np.ndarray, t0: float, t1: float) -> float:
    u = np.linspace(0.0, 1.0, 41)[None, :, None]
    pts = (P[:-1, None, :] + u * (P[1:] - P[:-1])[:, None, :]).reshape(-1, 3)
    return min(float(exact_distance(ms, pts, t).min()) for t in np.linspace(t0, t1, 11))


@pytest.mark.parametrize("kind", ["box", "cylinder", "capsule", "halfspace", "mesh", "points"])
def test_chord_bound_is_below_the_dense_minimum(kind, tmp_path):
    """chord_clearance never exceeds the brute-force minimum over the chord's points and the
    window's times, for a moving, turning, breathing shape, and comes within 6 mm of it (not a vacuous bound)."""
    rng = np.random.default_rng(6)
    _, m = _pipe(tmp_path)
    geometry = {
        "box": Box((30, 20, 10), Pose((0, 0, 0), Q30)),
        "cylinder": Cylinder(20, 60),
        "capsule": Capsule(10, 60),
        "halfspace": HalfSpace((0, 0, 1), -40.0),
        "mesh": Mesh(np.asarray(m.triangles), 3.0),
        "points": PointCloud(rng.uniform(-30, 30, size=(200, 3)), 2.0),
    }[kind]
    motion = Keyframes((0.0, 1.0), ((0, 0, 0), (0, 10, 0)), ((1, 0, 0, 0), tuple(Q30)))
    ms = MovingShape(geometry, motion, Breathing(0.05, 2.0))
    for _ in range(4):
        P = np.cumsum(rng.normal(size=(8, 3)) * 8.0, axis=0) + rng.uniform(-60, 60, size=3)
        t0 = float(rng.uniform(0, 0.9))
        t1 = t0 + 0.05
        bound = chord_clearance((ms,), P[None], np.array([t0]), np.array([t1]))[0]
        dense = _dense_chord_min(ms, P, t0, t1)
        assert bound <= dense + 1e-9
        assert dense - bound < 6.0


def test_checker_bounds_the_dense_body_clearance():
    """The checker's clearance of random configurations among a turning box and a wall is at most the
    independent dense clearance (400 backbone points, brute-force distance) minus disc radius and D_sf, and
    finds the configurations that collide."""
    m = Model(load_robot(ROBOT))
    box = MovingShape(Box((40, 30, 25), Pose((30, 40, 250), Q30)))
    wall = MovingShape(HalfSpace((-1, 0, 0), -60.0))
    scene = Scene(shapes=(box, wall), safety_distance=5.0)
    checker = StateValidityChecker(m, scene, check_points=15)
    X = checker.limits.sample(np.random.default_rng(7), 150)
    c = checker.clearance(X, 0.0)
    pts = m.points(X, 400)
    dense = np.minimum(
        exact_distance(box, pts.reshape(-1, 3), 0.0).reshape(len(X), -1).min(axis=1),
        exact_distance(wall, pts.reshape(-1, 3), 0.0).reshape(len(X), -1).min(axis=1),
    )
    truth = dense - m.robot.body_radius - 5.0
    assert np.all(c <= truth + 1e-6)
    assert np.any(truth < 0) and np.any(truth > 0)
    near = np.abs(truth) < 30.0
    assert np.max(truth[near] - c[near]) < 6.0  # within the sagitta and the chord's tangent bound


@pytest.mark.parametrize("kind", ["mesh", "points", "box"])
def test_pruned_row_minimum_is_the_full_brute_force_one(kind, tmp_path):
    """exact_min_clearance (only the pieces that can be nearest) equals the minimum of every distance."""
    rng = np.random.default_rng(8)
    _, m = _pipe(tmp_path)
    geometry = {
        "mesh": Mesh(np.asarray(m.triangles), 3.0),
        "points": PointCloud(rng.uniform(-30, 30, size=(300, 3)), 2.0),
        "box": Box((30, 20, 10)),
    }[kind]
    ms = MovingShape(geometry, StraightLine((0, 0, 0), (0, 0, 30), 1.0))
    pts = rng.uniform(-70, 70, size=(20, 30, 3))
    times = rng.uniform(0, 1, size=20)
    full = np.array([exact_distance(ms, pts[i], times[i]).min() for i in range(20)])
    if kind == "mesh":  # against every triangle, no pruning
        full = np.array(
            [point_triangle_distance((pts[i] - ms.frame(times[i])[0]), geometry.triangles).min() for i in range(20)]
        )
    np.testing.assert_allclose(exact_min_clearance(ms, pts, times), full, atol=1e-9)
