"""Actuators, limits, set-points, admission, the streamer, transports, protocol, simulated devices. Above: control.

Start here: `admit` (only an admitted motion drives a device) and `Streamer`. Public names load on first use
(`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.hardware.actuators": ("Actuators",),
        "crtraj.hardware.admission": ("admit", "AdmittedMotion", "MotionRecord"),
        "crtraj.hardware.verify": ("FrameVerifier", "VerifyOptions"),
        "crtraj.hardware.stream": (
            "Streamer",
            "StreamReport",
            "open_link",
            "StreamOptions",
            "StreamError",
        ),
        "crtraj.hardware.transport": ("Transport", "TransportError"),
        "crtraj.hardware.sim": (
            "SimDevice",
            "Faults",
        ),
        "crtraj.hardware.dynamixel": (
            "SimDynamixel",
            "HomingState",
        ),
    },
)
