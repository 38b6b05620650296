"""The streamer's verified braking manoeuvre: how a stream stops when it is held or e-stopped while moving.

A hold used to latch the last set-point: a device then stops as hard as its servos can, outside the
acceleration limits, and the body's travel while it brakes was never checked. `Braking.plan` instead
plans the stop from the stream's state (the last frame sent and the velocity between the last two, as
the limits gate knows them) within the actuators' acceleration limits, and verifies it with the motion's
`crtraj.hardware.verify.FrameVerifier` (the dense body check with D_sf against the scene at the frames'
times, cables, limits), the same check as every frame of the motion.

The planner is the control layer's (`crtraj.control.braking`: the closed loop's own hold uses the same
code); this module binds it to the actuators. A plan that fails the check is not sent: the stream latches
the last set-point as before, and that is counted (`BrakeCounts.latched`) and reported. Units: rad, mm, s.
"""

from __future__ import annotations

from crtraj.control.braking import Braking as _Braking
from crtraj.control.braking import StopVerifier
from crtraj.hardware.actuators import Actuators

__all__ = ["Braking"]


class Braking(_Braking):
    """Plans and verifies stops for one stream. actuators: the limits; dt: the stream period (s);
    verifier: the motion's `FrameVerifier` (None: a live stream without a scene, checked against the limits
    only)."""

    def __init__(self, actuators: Actuators, dt: float, verifier: StopVerifier | None = None) -> None:
        super().__init__(actuators.amax, dt, verifier)
        self.actuators = actuators

    def checked_by(self, verifier: StopVerifier) -> Braking:
        """A new braking for the same actuators and period whose stops `verifier` checks (its counts start at 0)."""
        return Braking(self.actuators, self.dt, verifier)
