"""Cosserat-rod statics of a tendon-driven robot (shooting in CasADi), its cable-length mode, its generated C, the
rod driven by a PCC robot's actuation, the rod's tabulated correction to PCC and the planner's model of the rod's
body built on it. Units mm, rad, N.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.model.cosserat._cables": ("CableDrivenRod",),
        "crtraj.model.cosserat._drive": (
            "RodDrive",
            "RodShape",
            "robot_rod",
        ),
        "crtraj.model.cosserat._rod_model": (
            "RodModel",
            "RodModelOptions",
            "load_rod_model",
            "power_products",
        ),
        "crtraj.model.cosserat._map": (
            "pcc_nodes",
            "tensions_for_bending",
        ),
        "crtraj.model.cosserat._statics": (
            "CosseratRod",
            "RodLoad",
            "RodSolution",
        ),
        "crtraj.model.cosserat._surrogate": ("BOUND_FACTOR", "SurrogateOptions", "sample_within_limits"),
    },
)
