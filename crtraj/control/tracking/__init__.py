"""The tracking controller: planned configurations -> rate-limited actuator commands; its LQR design, its limits,
the servo model and the compiled step. Units mm, rad, s.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.control.tracking._compiled": ("CompiledTracking",),
        "crtraj.control.tracking._controller": ("TrackingController",),
        "crtraj.control.tracking._options": ("TrackingOptions",),
        "crtraj.control.tracking._servo": ("ServoModel",),
    },
)
