"""Problem files and the versioned result schema, plots. Above: hardware (it composes every section's options).

Public names load on first use (`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.io.problem": ("Problem", "Task", "load_robot"),
        "crtraj.io.results": ("Result", "read_result"),
        "crtraj.io.calibration_data": ("Dataset", "read_dataset"),
        "crtraj.io.mocap": ("read_markers", "read_stream_log"),
        "crtraj.io.plots": ("plot_run",),
    },
)
