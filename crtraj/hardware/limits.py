"""The one place where actuator limits are enforced before anything leaves for the device.

A MOVE frame is admitted only if every value is within its position limits,
and the discrete velocity ``(p_k - p_{k-1}) / dt`` and acceleration
``(v_k - v_{k-1}) / dt`` computed against the frames already sent are within
the velocity and acceleration limits. HOLD and ESTOP frames must repeat the
last admitted positions exactly: they command zero velocity, i.e. braking,
which is always allowed. Nothing is ever clamped: a frame that fails is
refused and the caller reports the `Violation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import ESTOP, HOLD, MOVE

# Relative slack for round-off in comparisons against limits.
_REL_TOL = 1e-9


@dataclass(frozen=True)
class Violation:
    """One refused value. quantity: position, velocity, acceleration or hold."""

    quantity: str
    actuator: str
    value: float
    limit: str  # the limit as text, with units
    unit: str
    index: int = 0
    stamp: float = float("nan")

    def message(self) -> str:
        at = f" at t={self.stamp:.3f} s" if np.isfinite(self.stamp) else ""
        if self.quantity == "position":
            return f"{self.actuator} position {self.value:.6g} {self.unit} outside limits {self.limit}{at}"
        if self.quantity == "hold":
            return (
                f"{self.actuator} hold value {self.value:.6g} {self.unit} differs from the last commanded position{at}"
            )
        if self.quantity == "nonfinite":
            return f"{self.actuator} value is not finite{at}"
        return f"{self.actuator} {self.quantity} {self.value:.6g} {self.unit} exceeds limit {self.limit}{at}"


class LimitsGate:
    """Checks frames against per-actuator limits, given the frames already sent.

    dt: nominal time between frames (s), the streamer's 1/rate.
    """

    def __init__(self, actuators: Actuators, dt: float) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        self.actuators = actuators
        self.dt = float(dt)
        a = actuators
        self._lo = a.lower - _REL_TOL * np.maximum(np.abs(a.lower), 1.0)
        self._hi = a.upper + _REL_TOL * np.maximum(np.abs(a.upper), 1.0)
        self._vmax = a.vmax * (1 + _REL_TOL)
        self._amax = a.amax * (1 + _REL_TOL)
        self._prev: np.ndarray | None = None
        self._vprev = np.zeros(a.n)

    @property
    def position(self) -> np.ndarray | None:
        """The last admitted positions (None before `reset`)."""
        return None if self._prev is None else self._prev.copy()

    @property
    def velocity(self) -> np.ndarray:
        return self._vprev.copy()

    def reset(self, position: np.ndarray) -> Violation | None:
        """Start from `position` at rest (after a hold or at start); refuses positions outside limits."""
        p = np.asarray(position, dtype=float)
        v = self._positions(p[None, :], np.array([float("nan")]))
        if v is not None:
            return v
        self._prev = p.copy()
        self._vprev = np.zeros(self.actuators.n)
        return None

    def check(self, kind: int, values: np.ndarray, stamp: float = float("nan")) -> Violation | None:
        """The first violation of one frame, without changing the gate's state."""
        if self._prev is None:
            raise RuntimeError("LimitsGate.check before reset(): the start position is unknown")
        p = np.asarray(values, dtype=float)
        if p.shape != (self.actuators.n,):
            raise ValueError(f"expected {self.actuators.n} values, got shape {p.shape}")
        if kind in (HOLD, ESTOP):
            bad = np.flatnonzero(~(p == self._prev))
            if bad.size:
                i = int(bad[0])
                u = self.actuators.units[i]
                return Violation("hold", self.actuators.names[i], float(p[i]), f"{self._prev[i]:g} {u}", u, 0, stamp)
            return self._positions(p[None, :], np.array([stamp]))
        if kind != MOVE:
            raise ValueError(f"unknown frame kind {kind}")
        return self.check_path(p[None, :], np.array([stamp]), self._prev, self._vprev)

    def commit(self, kind: int, values: np.ndarray) -> None:
        """Record a frame that was admitted and sent."""
        p = np.asarray(values, dtype=float)
        if kind == MOVE:
            self._vprev = (p - self._prev) / self.dt
        else:
            self._vprev = np.zeros(self.actuators.n)
        self._prev = p.copy()

    def check_path(
        self,
        values: np.ndarray,
        stamps: np.ndarray,
        start: np.ndarray | None = None,
        start_velocity: np.ndarray | None = None,
    ) -> Violation | None:
        """First violation of consecutive MOVE frames `values` (N, n) sent every dt.

        start / start_velocity: the state before the first frame; by default
        the first frame itself at rest (a path that starts where the device is).
        """
        P = np.asarray(values, dtype=float)
        v = self._positions(P, stamps)
        if v is not None:
            return v
        V, A = self.rates(P, start, start_velocity)
        bad_v = np.abs(V) > self._vmax
        bad_a = np.abs(A) > self._amax
        first_v = _first(bad_v)
        first_a = _first(bad_a)
        names, units = self.actuators.names, self.actuators.units
        if first_v is None and first_a is None:
            return None
        if first_a is None or (first_v is not None and first_v[0] <= first_a[0]):
            k, i = first_v  # type: ignore[misc]
            u = f"{units[i]}/s"
            return Violation(
                "velocity", names[i], float(V[k, i]), f"{self.actuators.vmax[i]:g} {u}", u, k, float(stamps[k])
            )
        k, i = first_a
        u = f"{units[i]}/s^2"
        return Violation(
            "acceleration", names[i], float(A[k, i]), f"{self.actuators.amax[i]:g} {u}", u, k, float(stamps[k])
        )

    def rates(
        self, values: np.ndarray, start: np.ndarray | None = None, start_velocity: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(velocities, accelerations) (N, n) per s and per s^2 of MOVE frames `values` (N, n) sent every
        dt after `start` moving at `start_velocity` (default: the first frame, at rest): the finite
        differences `check_path` compares with the limits."""
        P = np.asarray(values, dtype=float)
        p0 = P[0] if start is None else np.asarray(start, dtype=float)
        v0 = np.zeros(P.shape[1]) if start_velocity is None else np.asarray(start_velocity, dtype=float)
        V = np.diff(np.vstack([p0[None, :], P]), axis=0) / self.dt
        return V, np.diff(np.vstack([v0[None, :], V]), axis=0) / self.dt

    def _positions(self, P: np.ndarray, stamps: np.ndarray) -> Violation | None:
        names, units = self.actuators.names, self.actuators.units
        nonfinite = _first(~np.isfinite(P))
        if nonfinite is not None:
            k, i = nonfinite
            return Violation("nonfinite", names[i], float(P[k, i]), "finite", units[i], k, float(stamps[k]))
        bad = _first((self._lo > P) | (self._hi < P))
        if bad is None:
            return None
        k, i = bad
        lim = f"[{self.actuators.lower[i]:g}, {self.actuators.upper[i]:g}] {units[i]}"
        return Violation("position", names[i], float(P[k, i]), lim, units[i], k, float(stamps[k]))


class LimitPeaks:
    """The largest actuator speed and acceleration a device was sent, as fractions of the limits.

    `add` takes each batch of MOVE frames as it leaves, with the state before it, and keeps the running
    maxima of |v| / vmax and |a| / amax by the limits gate's finite differences (every dt s): the figure a
    live run reports is what the device received, not a reconstruction from the loop's model.
    """

    def __init__(self, actuators: Actuators, dt: float) -> None:
        self._gate = LimitsGate(actuators, dt)
        self._amax, self._vmax = actuators.amax, actuators.vmax
        self.velocity = math.nan  # NaN until a frame is sent
        self.acceleration = math.nan

    def add(self, values: np.ndarray, start: np.ndarray | None, start_velocity: np.ndarray | None) -> None:
        """Count frames `values` (N, n) sent after `start` at `start_velocity` (None: from rest at the first)."""
        V, A = self._gate.rates(values, start, start_velocity)
        v, a = float(np.max(np.abs(V) / self._vmax)), float(np.max(np.abs(A) / self._amax))
        self.velocity = v if math.isnan(self.velocity) else max(self.velocity, v)
        self.acceleration = a if math.isnan(self.acceleration) else max(self.acceleration, a)

    def as_dict(self) -> dict[str, float]:
        """{"max_velocity_fraction", "max_acceleration_fraction"} (NaN before any frame)."""
        return {"max_velocity_fraction": self.velocity, "max_acceleration_fraction": self.acceleration}


def _first(mask: np.ndarray) -> tuple[int, int] | None:
    """(row, column) of the first True in row-major order, or None."""
    flat = np.flatnonzero(mask)
    if flat.size == 0:
        return None
    k, i = divmod(int(flat[0]), mask.shape[1])
    return k, i
