"""The likely cause of a calibration that fails its gate: time offset, marker names, an actuator's sign.

Each hypothesis is tested on the uncalibrated model (prior parameters): the markers are aligned rigidly
(Kabsch) with the model's markers as they are, with two markers' names exchanged, and with one actuator's
value mirrored about its zero offset (a reversed sign). A hypothesis is named when it brings the aligned
RMS below `IMPROVEMENT` times the plain one: a calibration corrects errors of a few millimetres, while a
swap or a sign flip puts the markers tens to hundreds of millimetres away. A gross time offset (measured by
`crtraj.model.calibration._timing`) is named first. Units: mm, s.
"""

from __future__ import annotations

import math

import numpy as np

from crtraj.model.calibration._frames import align
from crtraj.model.calibration._model import CalibrationModel
from crtraj.model.calibration._timing import TimeOffset

# A hypothesis is named when it brings the aligned RMS below this share of the plain one.
IMPROVEMENT = 0.5
GENERIC = (
    "the model does not explain the data: check the marker sites (--marker), the robot file's actuators and "
    "the marker units (mm); give --noise MM if the capture's noise is larger than estimated"
)


def _aligned_rms(m: np.ndarray, P: np.ndarray) -> float:
    """RMS (mm) of the markers m (N, M, 3) after the best rigid alignment with the model's P (N, M, 3)."""
    ok = np.isfinite(m).all(axis=2)
    if ok.sum() < 3:
        return math.nan
    R, t, _ = align(m[ok], P[ok])
    e = m[ok] @ R.T + t - P[ok]
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def _swapped(cm: CalibrationModel, prior: np.ndarray, values: np.ndarray, m: np.ndarray, base: float) -> str:
    P = cm.predict(prior, values)
    best, what = IMPROVEMENT * base, ""
    names = [s.name for s in cm.sites]
    for a in range(cm.M):
        for b in range(a + 1, cm.M):
            perm = list(range(cm.M))
            perm[a], perm[b] = b, a
            r = _aligned_rms(m[:, perm], P)
            if r < best:
                best, what = r, f"marker names: {names[a]} and {names[b]} look swapped"
    return what


def _flipped(
    cm: CalibrationModel, prior: np.ndarray, zero: np.ndarray, values: np.ndarray, m: np.ndarray, base: float
) -> str:
    best, what = IMPROVEMENT * base, ""
    names = cm.layout.actuator_names
    for i in range(values.shape[1]):
        v = values.copy()
        v[:, i] = 2 * zero[i] - v[:, i]
        r = _aligned_rms(m, cm.predict(prior, v))
        if r < best:
            best, what = r, f"sign: actuator {names[i]} looks reversed (its sign or direction in the robot file)"
    return what


def likely_cause(
    cm: CalibrationModel,
    prior: np.ndarray,
    values: np.ndarray,
    positions: np.ndarray,
    time_offset: TimeOffset | None = None,
    time_tolerance: float = 0.25,
) -> str:
    """The likely cause of a failed fit (one phrase); see the module docstring.

    prior: the prior parameters (Layout order); values (N, nq); positions (N, M, 3) capture frame mm.
    """
    if time_offset is not None and time_offset.is_gross(time_tolerance):
        return (
            f"time offset: the markers move {time_offset.lag:+.3g} s after the actuator values; add "
            f"{time_offset.lag:+.3g} s to --time-offset (marker time minus log time) and record again"
        )
    base = _aligned_rms(positions, cm.predict(prior, values))
    if not math.isfinite(base):
        return GENERIC
    n = cm.robot.n_segments
    zero = prior[n + 2 : n + 3 + 3 * n]  # the actuators' zero offsets, the stage's last
    return _swapped(cm, prior, values, positions, base) or _flipped(cm, prior, zero, values, positions, base) or GENERIC
