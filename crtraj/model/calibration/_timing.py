"""Time alignment of a calibration dataset: the lag between the actuator motion and the marker motion (s).

A dataset pairs actuator values with marker positions at the same times. When the stream log and the capture
were joined with a wrong time offset, the markers move a fixed time before or after the actuators. The model
(at the prior parameters) predicts the markers from the actuator values; signals that no capture frame
changes (the distance of every pair of markers and each marker's speed) are computed for the prediction and
for the measurement and cross-correlated over lags of up to a quarter of the record; the lag of the peak is
the residual offset. Speed norms of the actuators alone are not enough: an excitation that turns at a steady
rate has a steady speed, whose only feature is its slow envelope. Samples are decimated to at most 20 per
second and median-filtered over a few samples first, so marker noise and outliers do not dominate; when the
signals correlate weakly at every lag (below `MIN_CORRELATION`) there is no estimate.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from crtraj.model.calibration._model import CalibrationModel

# Median-filter window (samples) of the values and positions before their speeds are taken.
SMOOTH = 5
# Fewest samples for an estimate.
MIN_SAMPLES = 20
# Samples closer than this (s) are decimated to it.
MIN_STEP = 0.05
# Smallest correlation of the signals at the best lag for an estimate.
MIN_CORRELATION = 0.3
# Most samples the cross-correlation runs over (longer records are decimated).
MAX_SAMPLES = 20_000


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


def _median_filtered(x: np.ndarray) -> np.ndarray:
    """x (N, ...) with each entry the median of SMOOTH consecutive samples (NaN ignored): marker noise and
    outliers (a swapped label for one frame) do not reach the speeds."""
    win = sliding_window_view(x, SMOOTH, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a marker unseen over a whole window stays NaN
        return np.nanmedian(win, axis=-1)


def _standardised(x: np.ndarray) -> np.ndarray:
    """Columns of x with mean 0 and standard deviation 1 (a constant column stays 0; NaN becomes 0)."""
    x = np.nan_to_num(x - np.nanmean(x, axis=0))
    sd = np.std(x, axis=0)
    return x / np.where(sd > 0, sd, 1.0)


def _invariants(p: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Signals of marker positions p (N, M, 3) that no capture frame changes, (N-1, S): the distance of every
    pair of markers and each marker's speed (mm, mm/s; NaN where a marker was not seen)."""
    cols = [np.linalg.norm(p[1:, a] - p[1:, b], axis=1) for a in range(p.shape[1]) for b in range(a + 1, p.shape[1])]
    cols += [np.linalg.norm(np.diff(p[:, j], axis=0), axis=1) / dt for j in range(p.shape[1])]
    return np.stack(cols, axis=1)


def _correlation(a: np.ndarray, b: np.ndarray, kmax: int) -> np.ndarray:
    """Mean over the columns of the correlation of a[:, s] with b[:, s] shifted by each lag in -kmax..kmax
    (b later for a positive lag), (2 kmax + 1,)."""
    m = a.shape[0]
    size = 1 << math.ceil(math.log2(2 * m))
    cc = np.fft.irfft(np.conj(np.fft.rfft(a, size, axis=0)) * np.fft.rfft(b, size, axis=0), size, axis=0)
    lags = np.arange(-kmax, kmax + 1)
    return np.mean(cc[lags % size], axis=1) / (m - np.abs(lags))


def detect_time_offset(
    cm: CalibrationModel, theta: np.ndarray, t: np.ndarray, values: np.ndarray, positions: np.ndarray
) -> TimeOffset | None:
    """The markers' lag behind the actuators (see the module docstring): the model `cm` at parameters theta
    predicts the markers from the values. None when the samples are too few, not evenly spaced in time (a
    record with gaps, or samples that are not a motion) or the signals do not follow each other at any lag."""
    if t.size < MIN_SAMPLES:
        return None
    dt = np.diff(t)
    step = float(np.median(dt))
    if not step > 0 or np.mean(np.abs(dt - step) < 0.1 * step) < 0.9:
        return None
    k = max(1, round(MIN_STEP / step), math.ceil(t.size / MAX_SAMPLES))  # the motion, not the noise, matters
    t, values, positions, step = t[::k], values[::k], positions[::k], step * k
    if t.size < MIN_SAMPLES + SMOOTH:
        return None
    dt = np.diff(t)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a marker never seen: all-NaN columns
        a = _standardised(_median_filtered(_invariants(cm.predict(theta, values), dt)))
        b = _standardised(_median_filtered(_invariants(positions, dt)))
    kmax = a.shape[0] // 4
    corr = _correlation(a, b, kmax)
    best = int(np.argmax(corr))
    if corr[best] < MIN_CORRELATION:
        return None
    return TimeOffset(float((best - kmax) * step), float(corr[best]), float(corr[kmax]), step)
