"""The receding-horizon (MPC) replanner: one CasADi NLP over N future configurations, built once; its build, its
backends, its broad phase, its options and its result. Units mm, rad, s.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.control.horizon._options": (
            "HorizonResult",
            "HorizonStatus",
            "ReplanOptions",
            "DIVERGED",
            "INTERPOLATION_GAIN",
            "MOVED_TO_LOOP",
            "horizon_status",
        ),
        "crtraj.control.horizon._replanner": ("Replanner",),
        "crtraj.control.horizon._rows": (
            "implied_rows",
            "merge_parallel_rows",
        ),
    },
)
