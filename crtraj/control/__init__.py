"""The receding-horizon replanner, tracking, and the closed loop with its ports. Above: planning.

Start here: `ClosedLoop` (``ClosedLoop.from_problem(problem).run()``). Public names load on first use
(`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.control.loop": ("ClosedLoop",),
        "crtraj.control.run_record": ("ReplanRun", "RunStatus", "StepStatus"),
        "crtraj.control.loop_options": ("LoopOptions",),
        "crtraj.control.horizon": ("Replanner",),
        "crtraj.control.horizon_options": ("ReplanOptions", "HorizonResult", "HorizonStatus"),
        "crtraj.control.tracking": ("TrackingController",),
        "crtraj.control.tracking_options": ("TrackingOptions",),
    },
)
