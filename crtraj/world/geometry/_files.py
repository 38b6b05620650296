"""Reading obstacle data files: triangle meshes (STL, OBJ, PLY, by `trimesh`) and point clouds (a PLY,
an N x 3 ``.npy`` or a ``.csv`` of x, y, z rows), all in mm. Every failure is one `InputError` line that
names the field and the file; a file larger than the limits is refused before it is read whole.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.world.geometry._points import MAX_POINTS, MAX_TRIANGLES

MESH_SUFFIXES = (".stl", ".obj", ".ply")
POINT_SUFFIXES = (".ply", ".npy", ".csv")
# Largest data file read (bytes): a binary STL of MAX_TRIANGLES is 25 MB, a CSV of MAX_POINTS about 40 MB.
MAX_FILE_BYTES = 200_000_000


def _checked_path(path: str | os.PathLike[str], field: str, suffixes: tuple[str, ...]) -> Path:
    p = Path(path)
    if p.suffix.lower() not in suffixes:
        raise InputError(f"{field}: {p.name} is not one of {', '.join(suffixes)}; convert it")
    if not p.is_file():
        raise InputError(f"{field}: no such file {p}")
    size = p.stat().st_size
    if size > MAX_FILE_BYTES:
        raise InputError(f"{field}: {p.name} is {size} bytes, more than {MAX_FILE_BYTES}; thin it")
    return p


def _trimesh_load(p: Path, field: str) -> Any:
    import trimesh  # the only user of trimesh: imported when a data file is read

    try:
        return trimesh.load(str(p), force=None, process=False)
    except Exception as exc:  # trimesh raises many kinds for a file that is not what its name says
        raise InputError(f"{field}: {p.name} could not be read as {p.suffix[1:].upper()} ({exc})") from None


def load_triangles(path: str | os.PathLike[str], field: str = "file") -> np.ndarray:
    """Triangles (T, 3, 3) mm of a mesh file (STL, OBJ or PLY; a scene of several meshes is joined)."""
    p = _checked_path(path, field, MESH_SUFFIXES)
    obj = _trimesh_load(p, field)
    if hasattr(obj, "dump") and not hasattr(obj, "faces"):  # a trimesh.Scene
        geoms = [g for g in obj.dump() if hasattr(g, "faces")]
        tri = np.concatenate([np.asarray(g.triangles) for g in geoms]) if geoms else np.zeros((0, 3, 3))
    elif hasattr(obj, "faces") and hasattr(obj, "triangles"):
        tri = np.asarray(obj.triangles, dtype=float)
    else:
        tri = np.zeros((0, 3, 3))
    if len(tri) == 0:
        raise InputError(f"{field}: {p.name} holds no triangles; give a triangle mesh")
    if len(tri) > MAX_TRIANGLES:
        raise InputError(f"{field}: {p.name} has {len(tri)} triangles, more than {MAX_TRIANGLES}; decimate it")
    if not np.isfinite(tri).all():
        raise InputError(f"{field}: {p.name} has a vertex that is NaN or infinite")
    return tri


def _npy_points(p: Path, field: str) -> np.ndarray:
    try:
        arr = np.load(p, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise InputError(f"{field}: {p.name} is not a numpy .npy array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{field}: {p.name} has shape {arr.shape}, expected (N, 3) points in mm")
    if arr.shape[0] > MAX_POINTS:
        raise InputError(f"{field}: {p.name} has {arr.shape[0]} points, more than {MAX_POINTS}; thin it")
    return np.array(arr, dtype=float)


def _csv_points(p: Path, field: str) -> np.ndarray:
    lines = 0
    with open(p, "rb") as f:
        for _ in f:
            lines += 1
            if lines > MAX_POINTS + 1:  # one header line allowed
                raise InputError(f"{field}: {p.name} has more than {MAX_POINTS} points; thin it")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # an empty file: refused below, in one line
        try:
            arr = np.loadtxt(p, delimiter=",", ndmin=2, comments="#")
        except ValueError:
            try:
                arr = np.loadtxt(p, delimiter=",", ndmin=2, comments="#", skiprows=1)
            except ValueError as exc:
                raise InputError(f"{field}: {p.name} is not rows of x, y, z numbers ({exc})") from None
    if arr.size and arr.shape[1] != 3:
        raise InputError(f"{field}: {p.name} has {arr.shape[1]} columns, expected x, y, z (mm)")
    return arr.reshape(-1, 3)


def load_points(path: str | os.PathLike[str], field: str = "file") -> np.ndarray:
    """Points (N, 3) mm of a point-cloud file (PLY, ``.npy`` of shape (N, 3), or ``.csv`` of x, y, z rows)."""
    p = _checked_path(path, field, POINT_SUFFIXES)
    suffix = p.suffix.lower()
    if suffix == ".npy":
        pts = _npy_points(p, field)
    elif suffix == ".csv":
        pts = _csv_points(p, field)
    else:
        obj = _trimesh_load(p, field)
        pts = np.asarray(getattr(obj, "vertices", np.zeros((0, 3))), dtype=float).reshape(-1, 3)
    if len(pts) > MAX_POINTS:
        raise InputError(f"{field}: {p.name} has {len(pts)} points, more than {MAX_POINTS}; thin it")
    if len(pts) == 0:
        raise InputError(f"{field}: {p.name} holds no points; give at least one")
    if not np.isfinite(pts).all():
        raise InputError(f"{field}: {p.name} has a point that is NaN or infinite")
    return pts
