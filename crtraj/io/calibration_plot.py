"""The calibration's residual plot: each marker's residual (mm) against its workspace position.

Three panels (the robot frame's x, y and z of the marker as the calibrated model places it), the
uncalibrated residuals in grey behind the calibrated ones, held-out samples drawn hollow. A pattern
left in the calibrated residuals over the workspace is model error the parameters could not absorb.
matplotlib's object API only (no pyplot, no global backend switch), written atomically.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from crtraj.core.fileio import atomic_write_bytes


def residual_plot(
    path: str | Path,
    positions: np.ndarray,
    before: np.ndarray,
    after: np.ndarray,
    heldout: np.ndarray,
    names: Sequence[str],
) -> Path:
    """Write the PNG of `residual_plot_png` atomically to `path`."""
    return atomic_write_bytes(path, residual_plot_png(positions, before, after, heldout, names))


def residual_plot_png(
    positions: np.ndarray, before: np.ndarray, after: np.ndarray, heldout: np.ndarray, names: Sequence[str]
) -> bytes:
    """The PNG. positions (N, M, 3) robot-frame marker positions (mm); before/after (N, M, 3) residuals
    (mm, NaN: not seen); heldout (N,) mask; names: the M markers."""
    fig = Figure(figsize=(12, 4), dpi=100)
    axes = fig.subplots(1, 3, sharey=True)
    nb = np.linalg.norm(before, axis=2)
    na = np.linalg.norm(after, axis=2)
    top = np.nanpercentile(np.concatenate([nb.ravel(), na.ravel()]), 99) if np.isfinite(nb).any() else 1.0
    for a, ax_name in enumerate("xyz"):
        ax = axes[a]
        ax.scatter(positions[..., a].ravel(), nb.ravel(), s=4, c="0.8", label="uncalibrated")
        for j, name in enumerate(names):
            for mask, face in ((~heldout, None), (heldout, "none")):
                ax.scatter(
                    positions[mask, j, a],
                    na[mask, j],
                    s=6,
                    facecolors=face,
                    edgecolors=f"C{j}",
                    c=None if face == "none" else f"C{j}",
                    label=f"{name}{' (held out)' if face == 'none' else ''}",
                )
        ax.set_xlabel(f"{ax_name} (mm, robot frame)")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_ylim(0, max(float(top) * 1.2, 1.0))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("residual |e| (mm)")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("Marker residuals over the workspace: uncalibrated (grey) and calibrated")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
