"""The streamer: fixed-rate, time-stamped actuator set-points with limits, watchdog, e-stop and verified braking;
its buffer, cycle, monitor, sender, state machine, run log and options.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.hardware.stream._braking": ("Braking",),
        "crtraj.hardware.stream._options": ("StreamOptions",),
        "crtraj.hardware.stream._state": ("StreamError",),
        "crtraj.hardware.stream._streamer": (
            "StreamReport",
            "Streamer",
            "open_link",
        ),
    },
)
