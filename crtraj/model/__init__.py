"""The robot description and its symbolic PCC model (kinematics, Jacobians, export), the Cosserat-rod
mechanics model, and calibration (`crtraj.model.calibration`). Above: core.

Public names load on first use (`crtraj.core.lazy.lazy_exports`): CasADi is imported only when a model is.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.model.robot": ("Robot", "Segment"),
        "crtraj.model.kinematics": ("Model",),
        "crtraj.model.actuator_limits": ("ActuatorLimits",),
        "crtraj.model.rate_limits": ("RateLimits",),
        "crtraj.model.mechanics": ("Mechanics",),
        "crtraj.model.cosserat": (
            "CosseratRod",
            "RodLoad",
            "RodSolution",
        ),
        "crtraj.model.excitation": ("excitation_path",),
        "crtraj.model.export": ("ExportReport", "export_model"),
    },
)
