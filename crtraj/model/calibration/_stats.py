"""Residual statistics and the result and input records of a calibration fit (mm)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from crtraj.model.calibration._layout import Layout
from crtraj.model.calibration._sites import MarkerSite

if TYPE_CHECKING:
    from crtraj.model.calibration._identify import Identifiability


@dataclass(frozen=True)
class MarkerStats:
    """Residual norms of one marker (mm): RMS, 95th percentile, max, count; and the RMS without outliers
    (norms above OUTLIER_FACTOR times the median) with the outlier count."""

    rms: float
    p95: float
    max: float
    count: int
    rms_inliers: float = math.nan
    outliers: int = 0

    def to_dict(self) -> dict[str, float]:
        return {
            "rms_mm": self.rms,
            "p95_mm": self.p95,
            "max_mm": self.max,
            "count": self.count,
            "rms_inliers_mm": self.rms_inliers,
            "outliers": self.outliers,
        }


# A residual norm above this many times the marker's median is counted as an outlier in the report
# (for Gaussian noise the median norm is 1.54 sigma: 4 medians is 6 sigma).
OUTLIER_FACTOR = 4.0


def marker_stats(e: np.ndarray, names: Sequence[str]) -> dict[str, MarkerStats]:
    """Per-marker residual statistics of residuals (N, M, 3) mm (NaN rows are missing markers)."""
    out = {}
    for j, name in enumerate(names):
        d = np.linalg.norm(e[:, j], axis=1)
        d = d[np.isfinite(d)]
        if d.size == 0:
            out[name] = MarkerStats(math.nan, math.nan, math.nan, 0)
            continue
        inl = d[d <= OUTLIER_FACTOR * np.median(d)]
        out[name] = MarkerStats(
            float(np.sqrt(np.mean(d**2))),
            float(np.percentile(d, 95)),
            float(d.max()),
            int(d.size),
            float(np.sqrt(np.mean(inl**2))) if inl.size else math.nan,
            int(d.size - inl.size),
        )
    return out


@dataclass(frozen=True)
class Held:
    """A parameter the data cannot determine (held at its prior) and what it cannot be told apart from."""

    name: str
    confounded_with: tuple[str, ...]
    relative_residual: float


@dataclass(frozen=True)
class CalibrationResult:
    """The outcome of `fit` (mm, rad). theta: fitted parameters (prior where not fitted or held).
    free: the parameters fitted. std_error: standard errors (NaN where not fitted). singular_values: of the
    column-scaled, robust-weighted Jacobian of the fitted parameters (descending). held: parameters that
    were asked for but cannot be determined. before/after: per-marker residual statistics, split into
    'fit' and 'heldout'. before is the uncalibrated model (prior parameters with the best rigid capture
    frame). success, status, iterations, solve_time: IPOPT's verdict, its status text, iterations and
    time (s). residuals: after-fit residuals (N, M, 3); heldout_mask: (N,) True for held-out samples.
    identifiability: the analysis at the prior and at the fit (`crtraj.model.calibration._identify`)."""

    layout: Layout
    theta: np.ndarray
    prior: np.ndarray
    free: np.ndarray
    std_error: np.ndarray
    singular_values: np.ndarray
    held: tuple[Held, ...]
    before: dict[str, dict[str, MarkerStats]]
    after: dict[str, dict[str, MarkerStats]]
    success: bool
    status: str
    iterations: int
    solve_time: float
    sigma: float
    residuals: np.ndarray = field(repr=False)
    heldout_mask: np.ndarray = field(repr=False)
    at_bound: tuple[str, ...] = ()
    identifiability: Identifiability | None = field(default=None, repr=False)

    def value(self, name: str) -> float:
        return float(self.theta[self.layout.names.index(name)])

    def capture(self) -> np.ndarray:
        """The capture frame (6,): rotation vector (rad) and translation (mm), capture -> robot."""
        return self.theta[-6:].copy()


@dataclass(frozen=True)
class Observations:
    """What the fit reads: actuator values (N, nq), capture-frame marker positions (N, M, 3; NaN = not
    seen), the marker sites, and the held-out mask (N,)."""

    values: np.ndarray
    positions: np.ndarray
    sites: tuple[MarkerSite, ...]
    heldout: np.ndarray


def split(n: int, fraction: float, seed: int) -> np.ndarray:
    """A held-out mask of n samples: round(fraction n) of them, drawn with `seed`."""
    mask = np.zeros(n, dtype=bool)
    k = round(fraction * n)
    if k:
        mask[np.random.default_rng(seed).permutation(n)[:k]] = True
    return mask
