"""Drawing a scene's shapes (`crtraj.world.geometry`) in meshcat: boxes, cylinders, capsules, spheres, half
spaces, meshes as meshes and point clouds as points, each with its D_sf shell where the shell is a shape of
the same kind (a primitive grown by D_sf: the box's shell is the box of half extents + D_sf, which contains
the true offset surface). Every shape is a node ``shapes/<k>`` whose transform is the shape's frame (origin,
rotation, breathing scale) at a time; its geometry sits under it in the shape's own frame. Lengths in mm on
the way in, metres on the way out.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from crtraj.viz.geometry import M_PER_MM, Q_Y_TO_Z, f32, quat_to_matrix
from crtraj.viz.options import ViewOptions, color_value
from crtraj.world.geometry import Box, Capsule, Cylinder, HalfSpace, Mesh, MovingShape, PointCloud, Sphere

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    import meshcat.geometry as mg

# half the side (mm) of the square drawn for a half space's plane
PLANE_HALF = 300.0


def _y_to_z() -> np.ndarray:
    """4x4 transform turning meshcat's cylinder axis (y) onto z."""
    m = np.eye(4)
    m[:3, :3] = quat_to_matrix(Q_Y_TO_Z)
    return m


def _offset(m: np.ndarray, z: float) -> np.ndarray:
    out = m.copy()
    out[2, 3] = z * M_PER_MM
    return out


def _plane_frame(normal: np.ndarray, offset: float) -> np.ndarray:
    """4x4 transform placing a thin box's z axis along `normal`, centred on the plane."""
    n = np.asarray(normal, dtype=float)
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, a)
    u /= np.linalg.norm(u)
    m = np.eye(4)
    m[:3, :3] = np.stack([u, np.cross(n, u), n], axis=1)
    m[:3, 3] = n * offset * M_PER_MM
    return m


def _parts(shape: Any, grow: float) -> list[tuple[Any, np.ndarray]]:  # long: one branch per kind of shape
    """(meshcat geometry, 4x4 transform in the shape's frame) of `shape` grown by `grow` mm."""
    eye = np.eye(4)
    if isinstance(shape, Box):
        return [(mg.Box([2.0 * (h + grow) * M_PER_MM for h in shape.half_extents]), eye)]
    if isinstance(shape, Sphere):
        return [(mg.Sphere((shape.radius + grow) * M_PER_MM), eye)]
    if isinstance(shape, Cylinder):
        cyl = mg.Cylinder((shape.length + 2.0 * grow) * M_PER_MM, (shape.radius + grow) * M_PER_MM)
        return [(cyl, _y_to_z())]
    if isinstance(shape, Capsule):
        r = (shape.radius + grow) * M_PER_MM
        half = 0.5 * shape.length
        return [
            (mg.Cylinder(shape.length * M_PER_MM, r), _y_to_z()),
            (mg.Sphere(r), _offset(eye, half)),
            (mg.Sphere(r), _offset(eye, -half)),
        ]
    if isinstance(shape, HalfSpace):
        side = 2.0 * PLANE_HALF * M_PER_MM
        frame = _plane_frame(np.asarray(shape.normal), shape.offset + grow - 1.0)
        return [(mg.Box([side, side, 2.0 * M_PER_MM]), frame)]
    if isinstance(shape, Mesh):
        if grow:
            return []
        tri = shape.triangles.reshape(-1, 3) * M_PER_MM
        faces = np.arange(len(tri)).reshape(-1, 3)
        return [(mg.TriangularMeshGeometry(tri, faces), eye)]
    if isinstance(shape, PointCloud):
        if grow:
            return []
        pts = f32(shape.points.T * M_PER_MM)
        cols = f32(np.tile(np.array([[0.84], [0.15], [0.16]]), (1, pts.shape[1])))
        return [(mg.PointCloud(pts, cols, size=2.0 * shape.radius * M_PER_MM), eye)]
    return []


def shape_matrix(ms: MovingShape, t: float) -> np.ndarray:
    """4x4 transform (metres) of the shape's frame at time t (s): origin, rotation, breathing scale."""
    o, r, s = ms.frame(t)
    m = np.eye(4)
    m[:3, :3] = r * s
    m[:3, 3] = o * M_PER_MM
    return m


def draw_shapes(vis: Any, shapes: tuple[MovingShape, ...], safety: float, options: ViewOptions, t: float) -> None:
    """Draw `shapes` under the node ``shapes`` at time t (absolute s), each with its D_sf shell (`safety` mm)."""
    vis["shapes"].delete()
    color = color_value(options.obstacle_color, "view.obstacle_color")
    body = mg.MeshPhongMaterial(
        color=color, opacity=options.obstacle_opacity, transparent=options.obstacle_opacity < 1.0, side=2
    )
    shell = mg.MeshLambertMaterial(color=color, opacity=options.shell_opacity, transparent=True, depthWrite=False)
    for k, ms in enumerate(shapes):
        node = vis[f"shapes/{k}"]
        for kind, grow, mat in (("body", 0.0, body), ("shell", safety, shell)):
            for j, (geom, m) in enumerate(_parts(ms.shape, grow)):
                if isinstance(ms.shape, PointCloud):  # points carry their own colours
                    node[f"{kind}/{j}"].set_object(geom)
                else:
                    node[f"{kind}/{j}"].set_object(geom, mat)
                node[f"{kind}/{j}"].set_transform(m)
        node.set_transform(shape_matrix(ms, t))


def shape_tracks(ms: MovingShape, times: np.ndarray) -> dict[str, tuple[str, np.ndarray]]:
    """Animation tracks (position, quaternion (x, y, z, w), scale) of a moving shape's node at `times` (s)."""
    pos, quat, scale = [], [], []
    for t in times:
        o, r, s = ms.frame(float(t))
        pos.append(o * M_PER_MM)
        quat.append(_quat_xyzw(r))
        scale.append([s, s, s])
    return {
        "position": ("vector3", np.array(pos)),
        "quaternion": ("quaternion", np.array(quat)),
        "scale": ("vector3", np.array(scale)),
    }


def _quat_xyzw(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of rotation matrix r (Shepperd's method)."""
    tr = float(np.trace(r))
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-300))
        q = [0.0, 0.0, 0.0, (r[k, j] - r[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
    return np.array(q)


def shape_extent(shapes: tuple[MovingShape, ...], t: float) -> np.ndarray:
    """Points (K, 3) mm that bound the bounded shapes at time t (s), for framing the camera: each shape's
    bounding sphere's six extreme points (a half space is left out: it has no bound)."""
    pts = [np.zeros((0, 3))]
    for ms in shapes:
        r = ms.shape.local_radius
        if not math.isfinite(r):
            continue
        o, _, s = ms.frame(t)
        pts.append(o + s * r * np.concatenate([np.eye(3), -np.eye(3)]))
    return np.concatenate(pts)
