"""Plots of results: a replan run's body-obstacle distances and tip errors over time (run.png).

matplotlib is used through its object API (`Figure` rendered by the Agg
canvas), never pyplot: importing this module switches no global backend, so a
notebook that imports crtraj keeps its own.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from crtraj.control.loop import REPORT_POINTS, ReplanRun
from crtraj.core.fileio import atomic_write_bytes
from crtraj.io.results import RunContext
from crtraj.model.kinematics import Model


def per_obstacle_distance(
    run: ReplanRun, model: Model, scene: Any, n_points: int = REPORT_POINTS
) -> tuple[np.ndarray, np.ndarray]:
    """Surface distance (mm) from the body (backbone + body radius) to each obstacle over the run.

    Returns (times (S,), distances (S, m)); negative = penetration. With known
    obstacle motion every verification sample is used (`run.dense_t`); with
    a live feed, the recorded step times and obstacle states.
    """
    if run.live:
        T, P, C, R = run.t, model.points(run.x, n_points), run.centers, run.radii
    else:
        T = run.dense_t
        P = model.points(run.dense_x, n_points)  # (S, n, 3)
        C, R = scene.states(T)  # (S, m, 3), (S, m)
    d = np.linalg.norm(P[:, :, None, :] - C[:, None, :, :], axis=-1).min(axis=1)  # (S, m)
    return T, d - R - model.robot.body_radius


def plot_run(run: ReplanRun, context: RunContext, path: str | os.PathLike[str], title: str = "") -> Path:
    """PNG: body-obstacle distance over time (the paper's Fig. 4, panels a-5 and b-5) and tip errors; context:
    the run's model, scene and goal tolerance."""
    scene = context.scene
    fig = Figure(figsize=(8.0, 6.4), dpi=110)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    if scene.n_obstacles:
        T, d = per_obstacle_distance(run, context.model, scene)
        for i, o in enumerate(scene.obstacles):
            ax1.plot(T, d[:, i], lw=1.4, label=o.name or f"obstacle {i}")
    ax1.axhline(scene.safety_distance, color="tab:orange", ls="--", lw=1, label=f"D_sf = {scene.safety_distance:g} mm")
    ax1.axhline(0.0, color="tab:red", lw=1)
    bad = run.distance[1:] < 0
    if np.any(bad):
        ax1.plot(run.t[1:][bad], run.distance[1:][bad], "r.", ms=5, label="collision")
    ax1.set_ylabel("body-obstacle distance (mm)")
    ax1.legend(loc="best", fontsize=8)
    ax1.grid(alpha=0.3)
    s = run.summary()
    head = title or ("with collision-free terms" if run.safety else "without collision-free terms")
    ax1.set_title(
        f"{head}: min distance {s['min_distance_mm']:.2f} mm, min clearance {s['min_clearance_mm']:.2f} mm, "
        f"{s['collisions']} collision steps",
        fontsize=9,
    )
    ax2.semilogy(run.t, np.maximum(run.tip_error, 1e-4), label="tip tracking error (actual vs planned)")
    ax2.semilogy(run.t, np.maximum(run.goal_error, 1e-4), label="distance tip-goal")
    ax2.axhline(
        context.goal_tolerance,
        color="tab:green",
        ls="--",
        lw=1,
        label=f"goal tolerance {context.goal_tolerance:g} mm",
    )
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("mm")
    ax2.legend(loc="best", fontsize=8)
    ax2.grid(alpha=0.3, which="both")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return atomic_write_bytes(path, buf.getvalue())
