"""Cosserat-rod statics of a tendon-driven robot (shooting in CasADi), its cable-length mode, its generated C, the
rod driven by a PCC robot's actuation and the rod's tabulated correction to PCC. Units mm, rad, N.

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
        "crtraj.model.cosserat._surrogate": ("sample_within_limits",),
    },
)
