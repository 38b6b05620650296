"""The meshes of the scene examples in problems/ (issue 39), written as binary STL files (mm).

- problems/data/plate_hole.stl: a round plate 300 mm across and 6 mm thick with a round hole of 55 mm radius at
  its centre (`trimesh.creation.annulus`, closed), lying in its own xy plane;
- problems/data/bent_pipe.stl: the wall surface of a pipe of 55 mm radius (open at both ends): 120 mm straight
  along its own z axis from its mouth at z = 0, then a 90-degree bend of 150 mm centre-line radius toward +x.

Run: python examples/scene_meshes.py [FOLDER]   (writes both files into FOLDER, by default problems/data, whose
files the problems read; the same numbers give the same triangles)
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

DATA = Path(__file__).resolve().parents[1] / "problems" / "data"


def plate_with_hole(inner: float = 55.0, outer: float = 150.0, thick: float = 6.0) -> trimesh.Trimesh:
    """A closed round plate (mm) with a round hole, centred on the origin, its faces at z = +-thick / 2."""
    return trimesh.creation.annulus(r_min=inner, r_max=outer, height=thick, sections=96)


def pipe_centre_line(straight: float, bend: float, stations: int) -> tuple[np.ndarray, np.ndarray]:
    """(points (K, 3), unit tangents (K, 3)) of the pipe's centre line: up the z axis for `straight` mm, then a
    quarter circle of radius `bend` mm turning toward +x."""
    n1 = max(2, stations // 3)
    z = np.linspace(0.0, straight, n1)
    line = np.stack([np.zeros(n1), np.zeros(n1), z], axis=1)
    up = np.tile([0.0, 0.0, 1.0], (n1, 1))
    a = np.linspace(0.0, 0.5 * np.pi, stations - n1 + 1)[1:]
    arc = np.stack([bend * (1.0 - np.cos(a)), np.zeros_like(a), straight + bend * np.sin(a)], axis=1)
    tangent = np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], axis=1)
    return np.vstack([line, arc]), np.vstack([up, tangent])


def bent_pipe(radius: float = 55.0, straight: float = 120.0, bend: float = 150.0, around: int = 48) -> trimesh.Trimesh:
    """The open wall surface (mm) of the bent pipe of the module docstring."""
    centre, tangent = pipe_centre_line(straight, bend, 60)
    side = np.array([0.0, 1.0, 0.0])  # normal to the bend's plane, so a frame (tangent, side, other) per station
    other = np.cross(side, tangent)
    phi = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
    ring = np.cos(phi)[None, :, None] * other[:, None, :] + np.sin(phi)[None, :, None] * side[None, None, :]
    vertices = (centre[:, None, :] + radius * ring).reshape(-1, 3)
    faces = []
    for k in range(len(centre) - 1):
        for j in range(around):
            a, b = k * around + j, k * around + (j + 1) % around
            faces += [(a, b, b + around), (a, b + around, a + around)]
    return trimesh.Trimesh(vertices, np.array(faces), process=False)


def main() -> None:
    folder = Path(sys.argv[1]) if len(sys.argv) > 1 else DATA
    folder.mkdir(parents=True, exist_ok=True)
    for name, mesh in (("plate_hole.stl", plate_with_hole()), ("bent_pipe.stl", bent_pipe())):
        mesh.export(folder / name)
        print(f"wrote {folder / name} ({len(mesh.faces)} triangles)")


if __name__ == "__main__":
    main()
