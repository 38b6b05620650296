"""Planned trajectories as actuator set-points sampled at the streaming rate.

A path is a piecewise cubic in time through its waypoints (actuator values, `Actuators.command` of the
actuation q of a result read by `crtraj.io.results` and admitted by `crtraj.hardware.admission`):

- a plan's waypoints (`from_actuation`): shape-preserving cubic (PCHIP slopes, with zero slope at both
  ends so the motion starts and ends at rest). PCHIP never overshoots the waypoints, so interpolation
  invents no motion the plan did not contain. A retimed plan's waypoints are already one per stream
  period, so the streamer sends exactly them.
- a replan run's executed actuation, one sample per control period (`from_executed`): the run's
  clamped uniform cubic B-spline (`crtraj.control.executed.executed_curve`, given to the cubic as its
  knot values and slopes). Its acceleration is at most the samples' second difference over the period
  squared and its speed at most their first difference over the period, at every instant, so the
  set-points keep the limits the loop kept, at any stream rate and any slow-down (PCHIP would amplify
  the acceleration up to about 4 times where the motion starts, stops or reverses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from crtraj.control.executed import executed_curve
from crtraj.core.errors import InputError
from crtraj.core.fields import check_float
from crtraj.core.splines import HermiteCubic, pchip_slopes
from crtraj.hardware.actuators import Actuators

# `--time-scale` range: at most 1000 times slower (or faster); beyond that a
# replay is either a different experiment or a flood of set-points.
MIN_TIME_SCALE = 1.0e-3
MAX_TIME_SCALE = 1.0e3
# Most set-points one path may be sampled into (5.5 h at 100 Hz): bounds the
# memory of `sample` (stamps and values) before it allocates anything.
MAX_SETPOINTS = 2_000_000

# Cubic smoothstep s(u) = 3u^2 - 2u^3 (two waypoints, zero end slopes): peak |s'| = 3/2, peak |s''| = 6.
_STRAIGHT_V = 1.5
_STRAIGHT_A = 6.0


def check_time_scale(factor: Any, name: str = "--time-scale") -> float:
    """Validate a replay slow-down factor: a finite number in [MIN_TIME_SCALE, MAX_TIME_SCALE]."""
    return check_float(factor, name, ge=MIN_TIME_SCALE, le=MAX_TIME_SCALE)


@dataclass(frozen=True)
class SetpointPath:
    """Actuator values over time: waypoint times t (s, strictly increasing) and values (N, n).

    `sample(rate)` gives the set-points the streamer sends; `stamps` are
    trajectory times (s), values in actuator units (rad, mm). slopes (N, n):
    the cubic's derivative (units/s) at the waypoints; None: PCHIP slopes,
    zero at both ends.
    """

    t: np.ndarray
    values: np.ndarray
    source: str = ""
    approach: SetpointPath | None = None  # the move to the first waypoint, ending at t[0]
    slopes: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        v = np.asarray(self.values, dtype=float)
        if t.ndim != 1 or t.size < 2:
            raise InputError(f"{self.source}waypoints: need at least 2 waypoints, got {t.size}")
        if v.shape[0] != t.size:
            raise InputError(f"{self.source}waypoints: {t.size} times but {v.shape[0]} value rows")
        for name, a in (("t", t), ("values", v)):
            if not np.all(np.isfinite(a)):
                raise InputError(f"{self.source}waypoints.{name}: contains NaN or infinity")
        dt = np.diff(t)
        bad = np.flatnonzero(~(dt > 0))
        if bad.size:
            k = int(bad[0]) + 1
            raise InputError(f"{self._where(k)}.t: time must increase strictly (got {t[k]:g} s after {t[k - 1]:g} s)")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "values", v)
        if self.slopes is not None:
            m = np.asarray(self.slopes, dtype=float)
            if m.shape != v.shape or not np.all(np.isfinite(m)):
                raise InputError(f"{self.source}waypoints: slopes must be finite, one per value, got {m.shape}")
            object.__setattr__(self, "slopes", m)

    def _where(self, k: int) -> str:
        return f"{self.source}waypoints[{k}]" if self.source else f"waypoints[{k}]"

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    # ---------------------------------------------------------- constructors
    @classmethod
    def from_actuation(cls, t: Any, q: Any, actuators: Actuators, source: str = "") -> SetpointPath:
        """From waypoint times (s) and robot actuation q (N, nq) in mm."""
        t_arr = np.asarray(t, dtype=float)
        q_arr = np.asarray(q, dtype=float)
        if q_arr.ndim != 2 or q_arr.shape[1] != actuators.n:
            raise InputError(
                f"{source}waypoints.q: expected {actuators.n} actuation values per waypoint "
                f"({', '.join(actuators.names)}), got shape {q_arr.shape}"
            )
        bad = np.argwhere(~np.isfinite(q_arr))
        if bad.size:
            k, i = (int(x) for x in bad[0])
            raise InputError(f"{source}waypoints[{k}].q[{i}]: must be finite, got {q_arr[k, i]}")
        bad_t = np.flatnonzero(~np.isfinite(t_arr))
        if bad_t.size:
            k = int(bad_t[0])
            raise InputError(f"{source}waypoints[{k}].t: must be finite, got {t_arr[k]}")
        return cls(t_arr, actuators.command(q_arr), source)

    @classmethod
    def from_executed(cls, t0: float, period: float, q: Any, actuators: Actuators, source: str = "") -> SetpointPath:
        """From a run's executed actuation q (M, nq) in mm, sampled every `period` s from t0 (s): its
        clamped cubic B-spline (`crtraj.control.executed.executed_curve`), from t0 - period to the last
        sample's time + period, at rest at both ends."""
        check_float(period, f"{source}executed.dt", gt=0.0)
        path = cls.from_actuation(t0 + period * np.arange(len(np.atleast_2d(q))), q, actuators, source)
        t, values, slopes = executed_curve(float(path.t[0]), float(period), path.values)
        return cls(t, values, source, slopes=slopes)

    # -------------------------------------------------------------- transforms
    def scaled(self, factor: float) -> SetpointPath:
        """The same path `factor` times slower (factor > 1 slows down)."""
        check_time_scale(factor)
        if self.approach is not None:
            raise InputError("time scale: apply it before adding the approach move")
        slopes = None if self.slopes is None else self.slopes / factor
        return SetpointPath(self.t[0] + (self.t - self.t[0]) * factor, self.values, self.source, slopes=slopes)

    def with_approach(self, start: np.ndarray, actuators: Actuators, margin: float = 1.25) -> SetpointPath:
        """Prepend a rest-to-rest straight move from `start` (actuator values) to the first waypoint.

        The move (a cubic with zero end slopes, as `sample` interpolates two
        waypoints) lasts the shortest time for which every actuator keeps
        within ``1/margin`` of its velocity and acceleration limits: peak
        speed 1.5 d / T, peak acceleration 6 d / T^2 for a distance d. It is a
        straight line in actuator and configuration space (the maps are
        affine) and is not collision checked here: `crtraj.hardware.verify`
        checks it, with everything else that is sent, before it leaves.
        """
        start = np.asarray(start, dtype=float)
        d = np.abs(self.values[0] - start)
        if not np.any(d > 0):
            return self
        T = margin * float(
            max(np.max(_STRAIGHT_V * d / actuators.vmax), np.max(np.sqrt(_STRAIGHT_A * d / actuators.amax)))
        )
        return self.with_approach_path(np.array([self.t[0] - T, self.t[0]]), np.stack([start, self.values[0]]))

    def with_approach_path(self, t: Any, values: Any) -> SetpointPath:
        """Prepend an approach: waypoint times t (s, strictly increasing, ending at this path's first time)
        and actuator values (K, n) ending at this path's first values. It starts and ends at rest."""
        if self.approach is not None:
            raise InputError("approach: this path already has one")
        ap = SetpointPath(np.asarray(t, dtype=float), np.asarray(values, dtype=float), self.source + "approach: ")
        if ap.t[-1] != self.t[0] or not np.array_equal(ap.values[-1], self.values[0]):
            raise InputError(f"{self.source}approach: must end at the path's first waypoint (t={self.t[0]:g} s)")
        return replace(self, approach=ap)

    @property
    def start_time(self) -> float:
        """Time of the first waypoint (s), of the approach's first when there is one."""
        return float(self.t[0] if self.approach is None else self.approach.t[0])

    def approach_frames(self, rate: float) -> int:
        """How many set-points of `sample(rate)` belong to the approach (before the first waypoint)."""
        if self.approach is None:
            return 0
        return math.ceil((float(self.t[0]) - self.start_time) * rate - 1e-9)

    # --------------------------------------------------------------- sampling
    def sample(self, rate: float) -> tuple[np.ndarray, np.ndarray]:
        """Set-points every 1/rate s from the approach (if any) through the last waypoint (included).

        Returns (stamps (M,), values (M, n)). The stamps are ``t[0] + k / rate``
        for k from -`approach_frames` on (one grid anchored at the first
        waypoint, so adding an approach never changes the motion's own
        set-points), except the last, which is the final waypoint time. An
        approach whose duration is not a whole number of periods starts by
        holding its first values for the fraction of a period before it.
        """
        check_float(rate, "rate", gt=0.0)
        dt = 1.0 / rate
        t0, t1 = float(self.t[0]), float(self.t[-1])
        n = (t1 - self.start_time) * rate
        if not n <= MAX_SETPOINTS:  # also catches inf and NaN, before anything is allocated
            raise InputError(
                f"{self.source}waypoints: {t1 - self.start_time:g} s at {rate:g} Hz is more than {MAX_SETPOINTS} "
                "set-points; shorten the run, lower the rate or the time scale"
            )
        m = math.ceil((t1 - t0) / dt - 1e-9)
        na = self.approach_frames(rate)
        stamps = t0 + dt * np.arange(-na, m + 1)
        stamps[-1] = t1
        values = _spline(self.t, self.values, self.slopes)(np.maximum(stamps, t0))
        if self.approach is not None:
            ap = self.approach
            values[:na] = _spline(ap.t, ap.values)(np.clip(stamps[:na], ap.t[0], ap.t[-1]))
        return stamps, values


def _spline(t: np.ndarray, values: np.ndarray, slopes: np.ndarray | None = None) -> HermiteCubic:
    """The cubic through the waypoints with the given slopes; by default PCHIP slopes with zero slope at
    both ends: starts and ends at rest, never overshoots a waypoint."""
    if slopes is not None:
        return HermiteCubic(t, values, slopes)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # subnormal steps: slope 0
        slopes = pchip_slopes(t, values)
    slopes[0] = 0.0
    slopes[-1] = 0.0
    return HermiteCubic(t, values, slopes)
