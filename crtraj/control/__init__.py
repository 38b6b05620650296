"""The receding-horizon replanner, tracking, and the closed loop with its ports. Above: planning.

Start here: `ClosedLoop` (``ClosedLoop.from_problem(problem).run()``). Public names load on first use
(`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.control.loop": (
            "ClosedLoop",
            "ReplanRun",
            "RunStatus",
            "StepStatus",
            "LoopOptions",
        ),
        "crtraj.control.horizon": (
            "Replanner",
            "ReplanOptions",
            "HorizonResult",
            "HorizonStatus",
        ),
        "crtraj.control.tracking": (
            "TrackingController",
            "TrackingOptions",
        ),
    },
)
