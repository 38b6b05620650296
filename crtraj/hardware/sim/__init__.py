"""The simulated device that speaks crtraj's wire protocol over UDP, its protocol core and its servo model.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.hardware.sim._device": (
            "Faults",
            "SimDevice",
        ),
        "crtraj.hardware.sim._device_core": ("DeviceCore",),
        "crtraj.hardware.sim._servo": ("ServoProfile",),
    },
)
