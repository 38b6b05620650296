"""A verified braking manoeuvre: how a stream stops when it is held or e-stopped while moving.

A hold used to latch the last set-point: a device then stops as hard as its
servos can, outside the acceleration limits, and the body's travel while it
brakes was never checked. `Braking.plan` instead plans the stop from the
stream's state (the last frame sent and the velocity between the last two,
as the limits gate knows them) within the acceleration limits, and verifies
it with the motion's `crtraj.hardware.verify.FrameVerifier` (the dense body
check with D_sf against the scene at the frames' times, cables, limits),
the same check as every frame of the motion.

The stop: every actuator's frame-to-frame velocity falls linearly from its
current ``v_i`` to 0 over the same ``N`` periods, ``N = ceil(max_i |v_i| /
a_i / dt)``, so all actuators stop together (the body keeps its direction
in actuator space) and each deceleration ``|v_i| / (N dt)`` is within its
limit ``a_i``. Frame k (1..N) is ``p_k = p_{k-1} + dt v_i (1 - k/N)``; the
last two frames are equal (at rest). Units: rad, mm, s.

A plan that fails the check (e.g. a moving obstacle in the way) is not sent:
the stream latches the last set-point as before, and that is counted
(`BrakeCounts.latched`) and reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crtraj.hardware.actuators import Actuators


@dataclass(frozen=True)
class BrakePlan:
    """The stop's frames: stamps (N,) s and values (N, n) rad / mm; `why`: the check's failure, or None."""

    stamps: np.ndarray
    values: np.ndarray
    why: str | None = None

    @property
    def ok(self) -> bool:
        return self.why is None


@dataclass
class BrakeCounts:
    """What the stream's stops did: planned and sent stops, their frames, and latches (no verified stop)."""

    braked: int = 0
    frames: int = 0
    latched: int = 0
    unverified: int = 0  # stops sent within the limits but without a scene to check them against


def stop_frames(position: np.ndarray, velocity: np.ndarray, amax: np.ndarray, dt: float) -> np.ndarray:
    """(N, n) frames that bring actuators at `position` moving at `velocity` (per s) to rest within `amax`
    (per s^2), one every `dt` s (see the module doc); (0, n) when already at rest."""
    p = np.asarray(position, dtype=float)
    v = np.asarray(velocity, dtype=float)
    t_stop = float(np.max(np.abs(v) / np.asarray(amax, dtype=float)))
    n = math.ceil(t_stop / dt - 1e-9)
    if n <= 0:
        return np.empty((0, p.size))
    k = np.arange(1, n + 1, dtype=float)
    u = v[None, :] * (1.0 - k / n)[:, None]  # frame-to-frame velocities, the last one 0
    return p[None, :] + dt * np.cumsum(u, axis=0)


class Braking:
    """Plans and verifies stops for one stream. actuators: the limits; dt: the stream period (s);
    verifier: the motion's `FrameVerifier` (None: a live stream without a scene, checked against the limits
    only)."""

    def __init__(self, actuators: Actuators, dt: float, verifier: object | None = None) -> None:
        self.actuators = actuators
        self.dt = float(dt)
        self.verifier = verifier
        self.counts = BrakeCounts()

    def plan(self, position: np.ndarray, velocity: np.ndarray, t0: float) -> BrakePlan:
        """The stop from the last frame (`position` at trajectory time `t0` s, moving at `velocity`)."""
        values = stop_frames(position, velocity, self.actuators.amax, self.dt)
        stamps = t0 + self.dt * np.arange(1, len(values) + 1, dtype=float)
        if not len(values):
            return BrakePlan(stamps, values)
        if self.verifier is None:
            self.counts.unverified += 1
            return BrakePlan(stamps, values)
        why = self.verifier.failure(stamps, values, start=position, start_velocity=velocity)
        return BrakePlan(stamps, values, why)
