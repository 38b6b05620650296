"""crtraj: safety-constrained motion planning for cable-driven continuum robots.

``import crtraj`` gives every name a user needs (``__all__``), each loaded from its sub-package when it is
first read (PEP 562), so the import itself costs nothing and ``crtraj --help`` stays fast. Each name has one
home: the sub-package that defines it (``crtraj.Model`` is ``crtraj.model.Model``). Units: mm, rad, s.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

# name -> the sub-package whose __all__ holds it; grouped as a script uses them
_HOMES = {
    # errors every call may raise: bad input (one line naming the field), a refused motion
    "crtraj.core": ("InputError", "AdmissionError"),
    # loading a robot and a problem; reading results
    "crtraj.io": ("Problem", "Task", "load_robot", "Result", "read_result"),
    # the model: the robot description, the PCC model, the Cosserat-rod mechanics model
    "crtraj.model": ("Robot", "Model", "Mechanics", "CosseratRod"),
    # scenes and obstacles
    "crtraj.world": ("Scene", "Obstacle", "ObstacleFeed"),
    # planning: the entry point, its options and results, the planner registry
    "crtraj.planning": (
        "PlanningContext",
        "plan_executable",
        "ExecutablePlan",
        "PlannerOptions",
        "SteerOptions",
        "StopCondition",
        "PlanResult",
        "PlanStatus",
        "BUILTIN",
        "make_planner",
    ),
    # the closed loop
    "crtraj.control": ("ClosedLoop", "ReplanRun", "LoopOptions", "ReplanOptions", "TrackingOptions", "Replanner"),
    # admission and streaming, the simulated device, frame verification
    "crtraj.hardware": (
        "Actuators",
        "admit",
        "AdmittedMotion",
        "Streamer",
        "StreamOptions",
        "StreamReport",
        "SimDevice",
        "Faults",
        "FrameVerifier",
    ),
    # the view
    "crtraj.viz": ("Visualizer",),
    # library calls the commands are made of: plan a problem file, write a run, admit, calibrate, verify
    "crtraj.app": (
        "plan_problem",
        "ProblemPlan",
        "write_run",
        "admit_result",
        "admit_plan",
        "excitation_motion",
        "record_dataset",
        "calibrate_robot",
        "Calibration",
        "verify_cosserat",
        "Verification",
    ),
}
_HOME_OF = {name: package for package, names in _HOMES.items() for name in names}

__all__ = ["__version__", *_HOME_OF]


def __getattr__(name: str) -> object:  # (typing is not imported: it costs more than the rest)
    package = _HOME_OF.get(name)
    if package is None:
        raise AttributeError(f"module 'crtraj' has no attribute {name!r}")
    value = getattr(importlib.import_module(package), name)
    globals()[name] = value  # bound: the next read is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOME_OF))
