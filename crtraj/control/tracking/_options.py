"""The ``[tracking]`` problem section: the tracking controller's options (units mm, rad, s)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from crtraj.core.options import Options, option

MODES = ("configuration", "tip")


@dataclass(frozen=True)
class TrackingOptions(Options):
    """The ``[tracking]`` problem section.

    dt: control period the gain is designed for (s). mode: "configuration"
    (track x_ref) or "tip" (also correct the measured tip error, eq. 17).
    servo_tau / servo_tau_z: first-order lag of the cable servos / base stage (s).
    max_cable_rate / max_z_rate: actuator rate limits (mm/s).
    bending_error_scale (rad) / z_error_scale (mm): Bryson scales of Q.
    effort_weight: multiplies R (larger = gentler). damping: DLS lambda of the
    tip mode (mm/rad, paper: 0.3).
    """

    SECTION: ClassVar[str] = "tracking"

    dt: float = option(0.02, gt=0.0, le=1.0)
    mode: str = option("configuration", choices=MODES)
    servo_tau: float = option(0.05, gt=0.0, le=10.0)
    servo_tau_z: float = option(0.1, gt=0.0, le=10.0)
    max_cable_rate: float = option(10.0, gt=0.0)
    max_z_rate: float = option(50.0, gt=0.0)
    bending_error_scale: float = option(0.01, gt=0.0)
    z_error_scale: float = option(0.5, gt=0.0)
    effort_weight: float = option(1.0, gt=0.0)
    damping: float = option(0.3, ge=0.0)
