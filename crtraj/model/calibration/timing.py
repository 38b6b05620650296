"""Time alignment of a calibration dataset: the lag between the actuator motion and the marker motion (s).

A dataset pairs actuator values with marker positions at the same times. When the stream log and the capture
were joined with a wrong time offset, the markers move a fixed time before or after the actuators. The two
speed signals (the norm of the actuator speeds, each actuator scaled by its typical step; the mean marker
speed) are cross-correlated over lags of up to a quarter of the record; the lag of the peak is the residual
offset. Both signals are smoothed over a few samples first, so marker noise does not dominate the speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Smoothing window (samples) of the speed signals.
SMOOTH = 5
# Fewest samples for an estimate.
MIN_SAMPLES = 20


@dataclass(frozen=True)
class TimeOffset:
    """The markers' lag behind the actuator values (s; > 0: the markers move later), the speed correlation
    at that lag and at zero lag, and the sample interval (s) it is resolved to."""

    lag: float
    correlation: float
    correlation_at_zero: float
    step: float

    def is_gross(self, tolerance: float) -> bool:
        """True when the lag exceeds `tolerance` s and two samples and beats zero lag clearly."""
        big = abs(self.lag) > max(tolerance, 2.0 * self.step)
        return big and self.correlation > self.correlation_at_zero + 0.1


def _smooth(x: np.ndarray) -> np.ndarray:
    k = np.ones(SMOOTH) / SMOOTH
    return np.convolve(x, k, mode="same")


def _speeds(t: np.ndarray, values: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(actuator speed signal, marker speed signal), both (N-1,), standardised."""
    dt = np.diff(t)
    dv = np.diff(values, axis=0)
    typical = np.median(np.abs(dv), axis=0)
    typical = np.where(typical > 0, typical, 1.0)
    a = np.linalg.norm(dv / typical, axis=1) / dt
    dm = np.linalg.norm(np.diff(positions, axis=0), axis=2)  # (N-1, M), NaN where a marker was not seen
    seen = np.isfinite(dm)
    b = np.where(seen.any(axis=1), np.nansum(dm, axis=1) / np.maximum(seen.sum(axis=1), 1), 0.0) / dt
    out = []
    for s in (a, b):
        s = _smooth(s - np.mean(s))
        sd = float(np.std(s))
        out.append(s / sd if sd > 0 else s)
    return out[0], out[1]


def detect_time_offset(t: np.ndarray, values: np.ndarray, positions: np.ndarray) -> TimeOffset | None:
    """The markers' lag behind the actuators (see the module docstring); None when the samples are too few
    or not evenly spaced in time (a record with gaps, or samples that are not a motion)."""
    n = t.size
    if n < MIN_SAMPLES:
        return None
    dt = np.diff(t)
    step = float(np.median(dt))
    if not step > 0 or np.mean(np.abs(dt - step) < 0.1 * step) < 0.9:
        return None
    a, b = _speeds(t, values, positions)
    m = a.size
    size = 1 << math.ceil(math.log2(2 * m))
    cc = np.fft.irfft(np.conj(np.fft.rfft(a, size)) * np.fft.rfft(b, size), size)  # cc[k] = sum a[i] b[i+k]
    kmax = m // 4
    lags = np.arange(-kmax, kmax + 1)
    overlap = m - np.abs(lags)
    corr = cc[lags % size] / overlap
    best = int(np.argmax(corr))
    return TimeOffset(float(lags[best] * step), float(corr[best]), float(corr[kmax]), step)
