"""The servo model of the simulated devices: a time-optimal motion generator and a first-order motor.

Each actuator is a servo controller with a motion generator: on every new set-point it plans the time-optimal
motion from its current reference position and velocity to the set-point at rest, within the actuator's velocity
and acceleration limits (a trapezoidal or triangular velocity profile, `ServoProfile`). The measured position
follows that reference through a first-order lag ``tau x' = r - x`` (the motor; ``tau = 0``: an ideal servo),
integrated exactly for a reference that is linear over each physics step (`SimServos`). So a simulated device
never moves faster than its limits, whatever it is told. Positions in rad or mm, times in s.
"""

from __future__ import annotations

import numpy as np


class ServoProfile:
    """Time-optimal motion of independent axes to a target at rest, |v| <= vmax, |a| <= amax.

    From position p0 and velocity v0 (clipped to the velocity limit) at time t0,
    each axis accelerates at amax toward the target (direction chosen so that it
    can still stop there), cruises at vmax if it reaches it, and brakes at amax
    to arrive at rest: the textbook trapezoidal (or triangular) profile.
    Positions in rad or mm, times in s.
    """

    def __init__(self, vmax: np.ndarray, amax: np.ndarray, position: np.ndarray) -> None:
        self.vmax = np.asarray(vmax, dtype=float)
        self.amax = np.asarray(amax, dtype=float)
        self.plan(position, np.zeros_like(self.vmax), position, 0.0)

    @property
    def target(self) -> np.ndarray:
        return self._target.copy()

    @property
    def end_time(self) -> float:
        """Time (s) when every axis has arrived."""
        return self._t0 + float(np.max(self._t1 + self._t2 + self._t3, initial=0.0))

    def plan(self, p0: np.ndarray, v0: np.ndarray, target: np.ndarray, t0: float) -> None:
        """Start a new motion from (p0, v0) at time t0 to `target`."""
        a, vm = self.amax, self.vmax
        p0 = np.asarray(p0, dtype=float).copy()
        v0 = np.clip(np.asarray(v0, dtype=float), -vm, vm)
        d = np.asarray(target, dtype=float) - p0
        # direction of the first acceleration: toward the target unless the axis must brake first
        s = np.sign(d - v0 * np.abs(v0) / (2 * a))
        s = np.where(s == 0, np.sign(v0), s)
        w = s * v0  # velocity along s
        dist = s * d  # distance along s
        vp = np.minimum(vm, np.sqrt(np.maximum(a * dist + 0.5 * w * w, 0.0)))
        t1 = np.maximum(vp - w, 0.0) / a
        d1 = (vp * vp - w * w) / (2 * a)
        d3 = vp * vp / (2 * a)
        d2 = np.maximum(dist - d1 - d3, 0.0)
        t2 = np.divide(d2, vp, out=np.zeros_like(d2), where=vp > 0)
        self._t0, self._p0, self._target = float(t0), p0, np.asarray(target, dtype=float).copy()
        self._s, self._w, self._vp = s, w, vp
        self._t1, self._t2, self._t3, self._d1, self._d2 = t1, t2, vp / a, d1, d2

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) at time t >= t0 (closed form)."""
        tau = max(float(t) - self._t0, 0.0)
        a, s, w, vp = self.amax, self._s, self._w, self._vp
        t1, t12 = self._t1, self._t1 + self._t2
        sig = tau - t12
        along = np.where(
            tau < t1,
            w * tau + 0.5 * a * tau * tau,
            np.where(tau < t12, self._d1 + vp * (tau - t1), self._d1 + self._d2 + vp * sig - 0.5 * a * sig * sig),
        )
        vel = np.where(tau < t1, w + a * tau, np.where(tau < t12, vp, vp - a * sig))
        done = tau >= t12 + self._t3
        p = np.where(done, self._target, self._p0 + s * along)
        v = np.where(done, 0.0, s * vel)
        return p, v


class SimServos:
    """The simulated servos: motion generator (`ServoProfile`) plus first-order motors, on device time (s).

    vmax, amax: the actuators' limits (rad/s, mm/s; rad/s^2, mm/s^2); position: start positions (rad, mm);
    tau: motor time constants (s, >= 0, one per actuator); physics_dt: longest integration step (s).
    """

    def __init__(
        self, vmax: np.ndarray, amax: np.ndarray, position: np.ndarray, tau: np.ndarray, physics_dt: float
    ) -> None:
        self.tau = tau
        self.physics_dt = float(physics_dt)
        self._profile = ServoProfile(vmax, amax, position)
        self._x = position  # measured (motor) positions
        self._r = position.copy()  # servo reference at _t
        self._t = 0.0

    @property
    def time(self) -> float:
        """Device time (s) the physics has reached; it never goes back."""
        return self._t

    @property
    def measured(self) -> np.ndarray:
        """The measured (motor) positions (rad, mm) at `time`; read only."""
        return self._x

    @property
    def target(self) -> np.ndarray:
        """Where the motion generator is heading (a copy)."""
        return self._profile.target

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The motion generator's (position, velocity) at device time t (s)."""
        return self._profile.sample(t)

    def advance(self, now: float) -> None:
        """Integrate the servos up to device time `now` (s); earlier times are ignored."""
        h = self.physics_dt
        tau = self.tau
        while self._t < now:
            t1 = min(self._t + h, now)
            dt = t1 - self._t
            r1, _ = self._profile.sample(t1)
            # exact solution of tau x' = r - x for r linear from _r to r1 over dt (tau = 0: x = r)
            e = np.exp(-np.divide(dt, tau, out=np.full_like(tau, np.inf), where=tau > 0))
            c = 1.0 - np.divide(tau, dt, out=np.zeros_like(tau), where=tau > 0) * (1.0 - e)
            self._x = e * self._x + (1.0 - e) * self._r + (r1 - self._r) * c
            self._r, self._t = r1, t1

    def command(self, target: np.ndarray, now: float) -> None:
        """A new set-point at device time `now` (s): plan from the current reference to `target` at rest."""
        r, v = self._profile.sample(now)
        self._profile.plan(r, v, target, now)

    def brake(self, now: float) -> None:
        """Stop at the acceleration limit from device time `now` (s): the target is where each axis can stop."""
        r, v = self._profile.sample(now)
        self._profile.plan(r, v, r + v * np.abs(v) / (2 * self._profile.amax), now)
