"""Use cases called by the CLI and the examples: plan a problem, run a loop, stream a result. Above: viz, bench.

The library calls a script makes instead of a command: `plan_problem`, `write_run`, `admit_result`,
`admit_plan`, `excitation_motion`, `record_dataset`, `calibrate_robot`, `verify_cosserat`. Public names load
on first use (`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.app.plan": ("plan_problem", "ProblemPlan"),
        "crtraj.app.run_output": ("write_run",),
        "crtraj.app.devices": ("admit_result",),
        "crtraj.app.plan_motion": ("admit_plan",),
        "crtraj.app.lab": (
            "excitation_motion",
            "record_dataset",
            "calibrate_robot",
            "Calibration",
            "verify_cosserat",
            "Verification",
        ),
    },
)
