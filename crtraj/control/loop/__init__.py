"""The closed loop: `ClosedLoop` and its parts (step policy, reference manager and worker, pacer, recorder, tip
sensing, scene checks), its options and the run's record (`ReplanRun`).

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.control.loop._closed_loop": ("ClosedLoop",),
        "crtraj.control.loop._options": ("LoopOptions",),
        "crtraj.control.loop._pacer": ("CallableClock",),
        "crtraj.control.loop._problem": (
            "ProblemRun",
            "UnsolvableTaskError",
            "spec_from_problem",
        ),
        "crtraj.control.loop._reference": ("PlannerReference",),
        "crtraj.control.loop._run_record": (
            "ReplanRun",
            "RunStatus",
            "StepStatus",
            "REPORT_POINTS",
            "StateRecord",
            "StepRecord",
        ),
        "crtraj.control.loop._scene_checks": ("SceneChecks",),
        "crtraj.control.loop._setup": ("assemble",),
        "crtraj.control.loop._step_policy": ("RobotNow",),
    },
)
