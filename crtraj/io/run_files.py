"""The files of a replan run folder: their names, and the arrays file (run.npz).

A run folder holds run.json (`crtraj.io.results.run_document`), run.npz
(`save_npz`), run.png (`crtraj.io.plots.plot_run`), run.html (the 3-D replay)
and, when the run was streamed, stream.jsonl. `crtraj.app.run_output` writes
them as one set.
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

from crtraj.control.loop import ReplanRun
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_bytes
from crtraj.io import run_schema as rs

# every file a run folder may hold (`crtraj.app.run_output.write_run`, and a streamed run's log): a folder
# with anything else in it is not a run folder and is never replaced
RUN_FILES = frozenset({"run.json", "run.npz", "run.png", "run.html", "stream.jsonl"})

# per-step arrays (K,) and per-time arrays (K+1, ...) of run.npz: their lengths must agree
_PER_STEP = ("nlp_time", "plan_time", "iter_time", "iterations", "replanned", "status", "solver_status", "reason")
_PER_TIME = ("t", "x", "q", "q_command", "tip", "backbone", "centers", "radii", "clearance", "distance",
             "clearance_bound", "planned", "tip_error", "goal_error")  # fmt: skip


def save_npz(run: ReplanRun, path: str | os.PathLike[str]) -> Path:
    """Every array of the run in one .npz (the fields of `crtraj.io.run_schema.NPZ`, in order), written
    atomically (no pickled objects: strings are unicode arrays)."""
    arrays: dict[str, np.ndarray] = {f.key: f.get(run) for f in rs.NPZ if f.get is not None}
    for i, (k, tips) in enumerate(run.reference_tips):
        arrays[f"reference_{i}_tip"] = tips
        arrays[f"reference_{i}_step"] = np.array(k)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())


def read_npz(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """The arrays of a run.npz by key, validated against `crtraj.io.run_schema.NPZ`: a missing array, one
    of an unreadable kind, or per-time / per-step arrays of disagreeing lengths is one `InputError` naming
    the file and the key."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable run.npz ({exc})") from None
    for f in rs.NPZ:
        if f.required and f.key not in arrays:
            raise InputError(f"{path}: {f.key}: missing (required)")
    for key, a in arrays.items():
        if a.dtype.kind not in "biufU":
            raise InputError(f"{path}: {key}: expected numbers or text, got dtype {a.dtype}")
    t = arrays["t"]
    if t.ndim != 1 or len(t) < 1:
        raise InputError(f"{path}: t: expected a non-empty (K+1,) array, got shape {t.shape}")
    for key in _PER_TIME:
        if len(arrays[key]) != len(t):
            raise InputError(f"{path}: {key}: {len(arrays[key])} rows, but t has {len(t)}")
    for key in _PER_STEP:
        if len(arrays[key]) != len(t) - 1:
            raise InputError(f"{path}: {key}: {len(arrays[key])} steps, but t has {len(t)} times")
    return arrays
