"""How close a run's executed motion comes to the actuator limits, sampled as it will be streamed.

A run's recorded actuation (one sample per replan step) is what `crtraj stream` sends: each actuator
is interpolated with a shape-preserving cubic (PCHIP slopes, zero slope at both ends, so the motion
starts and ends at rest) and sampled at the stream rate; the limits gate then takes finite
differences of the samples against the frames before (the first from rest). This module repeats that
computation on the actuator values relative to their offsets (``J x``, `RateLimits`): PCHIP commutes
with a per-actuator offset and scale, so the fractions are those of the streamed values. Units: s and
the actuators' own units.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import CubicHermiteSpline, PchipInterpolator

from crtraj.planning.rate_limits import RateLimits

# The streamer's default rate (Hz, `crtraj.hardware.stream.StreamOptions.rate`).
STREAM_RATE = 100.0


def streamed_values(t: np.ndarray, values: np.ndarray, rate: float = STREAM_RATE) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (M,), values (M, m)): `values` (N, m) at times t (N,) s interpolated as the streamer does."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(values, dtype=float)
    m = math.ceil((t[-1] - t[0]) * rate - 1e-9)
    stamps = t[0] + np.arange(m + 1) / rate
    stamps[-1] = t[-1]
    slopes = PchipInterpolator(t, v, axis=0).derivative()(t)
    slopes[0] = 0.0
    slopes[-1] = 0.0
    return stamps, CubicHermiteSpline(t, v, slopes, axis=0)(stamps)


def limit_fractions(t: np.ndarray, x: np.ndarray, limits: RateLimits, rate: float = STREAM_RATE) -> dict[str, float]:
    """Largest actuator speed and acceleration, as fractions of their limits, of the configurations x
    (N, nx) at times t (N,) s, streamed at `rate` Hz: the limits gate's finite differences, from rest.

    Keys: max_velocity_fraction, max_acceleration_fraction (NaN with fewer than 2 samples).
    """
    if len(t) < 2:
        return {"max_velocity_fraction": math.nan, "max_acceleration_fraction": math.nan}
    _, vals = streamed_values(t, np.asarray(x, dtype=float) @ limits.jacobian.T, rate)
    h = 1.0 / rate
    vel = np.diff(vals, axis=0, prepend=vals[:1]) / h
    acc = np.diff(vel, axis=0, prepend=np.zeros((1, vel.shape[1]))) / h
    return {
        "max_velocity_fraction": float(np.max(np.abs(vel) / limits.vmax)),
        "max_acceleration_fraction": float(np.max(np.abs(acc) / limits.amax)),
    }
