"""The safety-constrained steer step (paper eq. 15-18): its NLP, its backends (IPOPT, SQP, generated C), its
options and its result. Units mm, rad, s.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.planning.steer._backends": ("RescuedBackend",),
        "crtraj.planning.steer._compiled": ("CompiledBackend",),
        "crtraj.planning.steer._options": ("SteerOptions",),
        "crtraj.planning.steer._solver": ("SteerSolver",),
    },
)
