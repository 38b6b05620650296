"""A verified braking manoeuvre: a hold or e-stop while moving is a stop planned within the acceleration
limits from the current state, checked against the obstacles over its whole duration.

One planner serves both places that stop a moving robot:

- the hardware streamer (`crtraj.hardware.stream._braking`, on the streamed frames: position and the velocity
  between the last two frames, as the limits gate knows them), verified with the motion's
  `crtraj.hardware.verify.FrameVerifier`;
- the closed loop's own hold (`servo_stop`, on the actual actuation at the end of each control period,
  with the set-points that make the first-order servo model follow the stop exactly), verified by the
  loop's dense check (`crtraj.control.loop.SceneChecks.verify`).

The stop (`stop_frames`): every coordinate's frame-to-frame velocity falls linearly from its current
``v_i`` to 0 over the same ``N`` periods, so all coordinates stop together (the body keeps its direction)
and each limited rate ``w = J v`` (``J`` the rate limits' Jacobian; the identity for actuator values)
decelerates by ``|w_j| / (N dt)``, within ``a_j`` for ``N = ceil(max_j |w_j| / a_j / dt)``. Frame k (1..N)
is ``p_k = p_{k-1} + dt v (1 - k/N)``; the last two frames are equal (at rest). The second difference at
the junction with the frame before the stop is ``-dt^2 v / N``: within the limits too. Units: rad, mm, s.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

# A stop longer than this (s) comes from an inconsistent state (a position jump read as a velocity), not a motion
# the loop made: `servo_stop` does not plan it (logged; the hold then commands the measured position).
MAX_STOP_TIME = 60.0

log = logging.getLogger(__name__)


class StopVerifier(Protocol):
    """What checks a stop's frames (`crtraj.hardware.verify.FrameVerifier` implements it): the first reason the
    frames (stamps (N,) s, values (N, n)) after `start` moving at `start_velocity` may not be sent, or None."""

    def failure(self, stamps: np.ndarray, values: np.ndarray, **start: Any) -> str | None: ...


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
    """What a run's stops did: planned and sent stops, their frames, and latches (no verified stop)."""

    braked: int = 0
    frames: int = 0
    latched: int = 0
    unverified: int = 0  # stops sent within the limits but without a scene to check them against


def stop_periods(velocity: np.ndarray, amax: np.ndarray, dt: float, jacobian: np.ndarray | None = None) -> int:
    """Fewest periods of `dt` s in which `velocity` (per s) falls linearly to rest with every limited rate
    (``jacobian @ velocity``, or the velocity itself) decelerating within `amax` (per s^2); 0 at rest."""
    v = np.asarray(velocity, dtype=float)
    w = v if jacobian is None else np.asarray(jacobian, dtype=float) @ v
    t_stop = float(np.max(np.abs(w) / np.asarray(amax, dtype=float))) if w.size else 0.0
    return max(math.ceil(t_stop / dt - 1e-9), 0)


def stop_frames(
    position: np.ndarray, velocity: np.ndarray, amax: np.ndarray, dt: float, jacobian: np.ndarray | None = None
) -> np.ndarray:
    """(N, n) frames that bring coordinates at `position` moving at `velocity` (per s) to rest within `amax`
    (per s^2, of ``jacobian @`` the coordinates' rates when given), one every `dt` s (see the module doc);
    (0, n) when already at rest."""
    p = np.asarray(position, dtype=float)
    v = np.asarray(velocity, dtype=float)
    n = stop_periods(v, amax, dt, jacobian)
    if n <= 0:
        return np.empty((0, p.size))
    k = np.arange(1, n + 1, dtype=float)
    u = v[None, :] * (1.0 - k / n)[:, None]  # frame-to-frame velocities, the last one 0
    return p[None, :] + dt * np.cumsum(u, axis=0)


class Braking:
    """Plans and verifies stops of frames sent every `dt` s within `amax` (per actuator, per s^2).
    verifier: checks a stop's frames (None: a live stream without a scene, checked against the limits only)."""

    def __init__(self, amax: np.ndarray, dt: float, verifier: StopVerifier | None = None) -> None:
        self.amax = np.asarray(amax, dtype=float)
        self.dt = float(dt)
        self.verifier = verifier
        self.counts = BrakeCounts()

    def count_latched(self) -> None:
        """A stop that could not be sent or finished: the device's latch stopped it."""
        self.counts.latched += 1

    def count_braked(self) -> None:
        """A stop planned, verified and started."""
        self.counts.braked += 1

    def count_frame(self) -> None:
        """One frame of a stop sent."""
        self.counts.frames += 1

    def plan(self, position: np.ndarray, velocity: np.ndarray, t0: float) -> BrakePlan:
        """The stop from the last frame (`position` at trajectory time `t0` s, moving at `velocity`)."""
        values = stop_frames(position, velocity, self.amax, self.dt)
        stamps = t0 + self.dt * np.arange(1, len(values) + 1, dtype=float)
        if not len(values):
            return BrakePlan(stamps, values)
        if self.verifier is None:
            self.counts.unverified += 1
            return BrakePlan(stamps, values)
        why = self.verifier.failure(stamps, values, start=position, start_velocity=velocity)
        return BrakePlan(stamps, values, why)


def servo_stop(servo: Any, q: np.ndarray, q_last: np.ndarray, h: float, limits: Any) -> tuple[np.ndarray, np.ndarray]:
    """The closed loop's stop of actuators at actual positions `q` (mm) that were at `q_last` one control
    period of `h` s before: (Q (N, nq) actual positions at the ends of the next N periods, C (N, nq) the
    set-point of each period). Q is `stop_frames` on the actuation, within ``limits`` (a `RateLimits` on
    configurations, mapped through the servo's affine ``config``); C inverts the first-order servo model
    over one period (``Q_k = C_k + d (Q_{k-1} - C_k)``, ``d = servo.decay(h)``), so the simulated plant
    executes Q exactly. Empty arrays at rest (or for a stop over `MAX_STOP_TIME`: an inconsistent state)."""
    q = np.asarray(q, dtype=float)
    nq = q.size
    dxdq = servo.config(np.eye(nq)) - servo.config(np.zeros(nq))  # (nq, nx): row i = d config / d q_i
    J = np.asarray(limits.jacobian, dtype=float) @ dxdq.T  # limited actuator rate per mm/s of actuation
    v = (q - np.asarray(q_last, dtype=float)) / h
    if stop_periods(v, limits.amax, h, J) * h > MAX_STOP_TIME:
        log.warning("servo_stop: a stop over %g s: q and q_last are not one period apart; not planned", MAX_STOP_TIME)
        return np.empty((0, q.size)), np.empty((0, q.size))
    Q = stop_frames(q, v, limits.amax, h, J)
    if not len(Q):
        return Q, Q.copy()
    d = servo.decay(h)
    prev = np.vstack([q[None], Q[:-1]])
    return Q, (Q - d * prev) / (1.0 - d)
