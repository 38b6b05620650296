"""A run's executed motion as it is streamed, and how close it comes to the actuator limits.

The closed loop records the actual actuation at the end of every control period h (the servo
model's response to the tracking set-points, `ClosedLoop`). `crtraj stream` sends the clamped
uniform cubic B-spline whose control points are these samples, with the first and the last tripled
(`executed_curve`): it starts at the first sample and ends at the last one, at rest, and lasts h
longer at each end than the samples. On each period the B-spline is a cubic whose second derivative
is a convex combination of the neighbouring second differences of the control points over h^2, and
whose first derivative is a convex combination of first differences over h; so at every instant

    |accel| <= max |second difference| / h^2,    |velocity| <= max |first difference| / h,

and finite differences of its samples at any period, being averages of these derivatives, keep the
same bounds. The loop keeps the samples' differences within the limits (tracking set-points and the
servos' positive averaging, `crtraj.control.tracking._controller`), so the streamed set-points keep them at any
stream rate and slow-down. At its knots the B-spline is (p[k-1] + 4 p[k] + p[k+1]) / 6: it stays
within a sixth of a second difference (hundredths of a millimetre) of the motion the loop verified,
and admission verifies its own frames anyway (`crtraj.hardware.verify`).

`limit_fractions` repeats the streamer's computation on the actuator values relative to their
offsets (``J x``, `RateLimits`): the B-spline commutes with a per-actuator offset and scale.
Units: s and the actuators' own units.
"""

from __future__ import annotations

import math

import numpy as np

from crtraj.core.splines import HermiteCubic
from crtraj.model.rate_limits import RateLimits

# The streamer's default rate (Hz, `crtraj.hardware.stream.StreamOptions.rate`).
STREAM_RATE = 100.0


def executed_curve(t0: float, h: float, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The clamped cubic B-spline of `samples` (M, m) taken every h s from t0 (s), as Hermite data:
    (knot times (M+2,) from t0 - h to t0 + M h, values (M+2, m) and slopes (M+2, m) /s at the knots).
    Starts at samples[0] and ends at samples[-1] with zero slope (and zero second derivative)."""
    c = np.atleast_2d(np.asarray(samples, dtype=float))
    P = np.vstack([c[:1], c[:1], c, c[-1:], c[-1:]])
    values = (P[:-2] + 4.0 * P[1:-1] + P[2:]) / 6.0
    slopes = (P[2:] - P[:-2]) / (2.0 * h)
    values[0], values[-1] = c[0], c[-1]  # exact ends (the formula gives them up to rounding)
    return t0 + h * (np.arange(len(values)) - 1.0), values, slopes


def streamed_values(
    t0: float, h: float, samples: np.ndarray, rate: float = STREAM_RATE
) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (M,), values (M, m)): the executed curve of `samples` (taken every h s from t0) sampled
    every 1/rate s from its start, the last stamp at its end (as `SetpointPath.sample`)."""
    t, values, slopes = executed_curve(t0, h, samples)
    m = math.ceil((t[-1] - t[0]) * rate - 1e-9)
    stamps = t[0] + np.arange(m + 1) / rate
    stamps[-1] = t[-1]
    return stamps, HermiteCubic(t, values, slopes)(stamps)


def limit_fractions(
    t0: float, h: float, x: np.ndarray, limits: RateLimits, rate: float = STREAM_RATE
) -> dict[str, float]:
    """Largest actuator speed and acceleration, as fractions of their limits, of the executed
    configurations x (M, nx) taken every h s from t0 (s), streamed at `rate` Hz: the limits gate's
    finite differences, from rest.

    Keys: max_velocity_fraction, max_acceleration_fraction (NaN with fewer than 2 samples).
    """
    if len(x) < 2:
        return {"max_velocity_fraction": math.nan, "max_acceleration_fraction": math.nan}
    _, vals = streamed_values(t0, h, np.asarray(x, dtype=float) @ limits.jacobian.T, rate)
    dt = 1.0 / rate
    vel = np.diff(vals, axis=0, prepend=vals[:1]) / dt
    acc = np.diff(vel, axis=0, prepend=np.zeros((1, vel.shape[1]))) / dt
    return {
        "max_velocity_fraction": float(np.max(np.abs(vel) / limits.vmax)),
        "max_acceleration_fraction": float(np.max(np.abs(acc) / limits.amax)),
    }
