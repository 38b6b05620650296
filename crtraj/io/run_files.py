"""The files of a replan run folder: their names, and the arrays file (run.npz).

A run folder holds run.json (`crtraj.io.results.run_document`), run.npz
(`save_npz`), run.png (`crtraj.io.plots.plot_run`), run.html (the 3-D replay)
and, when the run was streamed, stream.jsonl. `crtraj.app.run_output` writes
them as one set.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from crtraj.control.loop import ReplanRun
from crtraj.core.fileio import atomic_write_bytes

# every file a run folder may hold (`crtraj.app.run_output.write_run`, and a streamed run's log): a folder
# with anything else in it is not a run folder and is never replaced
RUN_FILES = frozenset({"run.json", "run.npz", "run.png", "run.html", "stream.jsonl"})

# the run's arrays saved by `save_npz`, by attribute name of `ReplanRun`
_ARRAYS = (
    "t", "x", "q", "q_command", "tip", "backbone", "centers", "radii", "clearance", "distance",
    "clearance_bound", "planned", "tip_error", "goal_error", "nlp_time", "plan_time", "iter_time",
    "iterations", "replanned", "dense_t", "dense_x", "commands", "control_dt", "executed", "tree_edges", "goal",
)  # fmt: skip


def save_npz(run: ReplanRun, path: str | os.PathLike[str]) -> Path:
    """Every array of the run in one .npz, written atomically (no pickled objects: strings are unicode arrays)."""
    arrays: dict[str, np.ndarray] = {name: np.asarray(getattr(run, name)) for name in _ARRAYS}
    arrays["status"] = np.array(run.step_status, dtype=str)
    arrays["solver_status"] = np.array(run.solver_status, dtype=str)
    arrays["reason"] = np.array(run.reason, dtype=str)
    for i, (k, tips) in enumerate(run.reference_tips):
        arrays[f"reference_{i}_tip"] = tips
        arrays[f"reference_{i}_step"] = np.array(k)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return atomic_write_bytes(path, buf.getvalue())
