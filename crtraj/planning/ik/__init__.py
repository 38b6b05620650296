"""Safety-constrained inverse kinematics from many seeded starts, with its rescue stage. Units mm, rad.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.planning.ik._run": (
            "IKRun",
            "format_statuses",
        ),
        "crtraj.planning.ik._safe_ik": ("SafeIK",),
        "crtraj.planning.ik._start": ("resolve_start",),
    },
)
