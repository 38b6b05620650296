"""The set-point follower of a live link: frames that track a target within the actuators' limits.

A replan step's verified motion is a target the device should follow frame by frame; the follower turns it into
set-points whose velocity and per-frame velocity change stay within the limits, feeding the target's own velocity
forward and closing the rest of the error no faster than it can still brake to zero, so it never overshoots a
target that stops. Units: the actuators' values (rad for spools, mm for the stage), s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FollowerState:
    """Where the follower is: the last set-point (n,), its velocity (n,) per s, and the last target (n,)."""

    position: np.ndarray
    velocity: np.ndarray
    last_target: np.ndarray | None


class SetpointFollower:
    """Set-points at frame period `dt` (s) tracking a target with |v| <= vmax and |dv| <= amax dt per frame.

    vmax, amax: (n,) velocity (per s) and acceleration (per s^2) limits of the actuators' values.
    """

    def __init__(self, dt: float, vmax: np.ndarray, amax: np.ndarray) -> None:
        self.dt = float(dt)
        self.vmax, self.amax = np.asarray(vmax, dtype=float), np.asarray(amax, dtype=float)
        self.state = FollowerState(np.zeros(len(self.vmax)), np.zeros(len(self.vmax)), None)

    def reset(self, position: np.ndarray) -> None:
        """At rest at `position` (n,), which is also the last target."""
        p = np.asarray(position, dtype=float)
        self.state = FollowerState(p, np.zeros(len(self.vmax)), p)

    def restore(self, state: FollowerState) -> None:
        """Go back to `state` (one taken before a `follow` whose frames were not sent)."""
        self.state = state

    def follow(self, target: np.ndarray) -> np.ndarray:
        """The set-points (frames, n) tracking `target` (frames, n) from the current state; the state moves on."""
        dt, vmax, amax = self.dt, self.vmax, self.amax
        p, v = self.state.position, self.state.velocity
        prev = p if self.state.last_target is None else self.state.last_target
        out = np.empty_like(target)
        for k, d in enumerate(target):
            vt = (d - prev) / dt
            e = d - (p + vt * dt)
            corr = np.sign(e) * np.minimum(np.abs(e) / dt, np.sqrt(amax * np.abs(e)))
            v_new = np.clip(v + np.clip(vt + corr - v, -amax * dt, amax * dt), -vmax, vmax)
            p = p + v_new * dt
            v, prev = v_new, d
            out[k] = p
        self.state = FollowerState(p, v, prev)
        return out
