"""State and motion validity: the conservative clearance of the body, vectorised motion checks, the compiled C
kernels that batch them, and the paper's own check (sec. IV-B). Units mm, rad, s.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.planning.validity._compiled": (
            "MAX_COMPILED_POINTS",
            "ProjectionLimits",
            "ProjectionSteps",
            "ValidityKernel",
            "kernel_key",
        ),
        "crtraj.planning.validity._held": ("held_clearance",),
        "crtraj.planning.validity._kernels": ("Kernels",),
        "crtraj.planning.validity._motion": ("MotionValidator",),
        "crtraj.planning.validity._paper_check": ("PaperValidator",),
        "crtraj.planning.validity._rod_kernel": ("RodKernel",),
        "crtraj.planning.validity._state": ("StateValidityChecker",),
    },
)
