"""The sanity gate of a calibration fit: success only when the fit explains the data down to its noise.

Checks, each with a one-phrase verdict:

- ``time_offset``: the markers' motion does not lag the actuators' by more than a tolerance
  (`crtraj.model.calibration._timing`);
- ``residual``: the held-out residual RMS without outliers is at most `GateOptions.residual_factor` times
  the noise RMS ``sqrt(3) sigma`` (sigma per axis: ``--noise``, or estimated from the data);
- ``outliers``: the fraction of marker observations counted as outliers is below a bound;
- ``bounds``: no fitted parameter ends at its bound (unless declared in `GateOptions.allow_at_bound`);
- ``solver``: IPOPT converged; "Solved_To_Acceptable_Level" counts only when every other check passes.

The noise estimate from the data: third differences of each marker's residual series in time order
(evenly spaced samples only). They cancel any error that varies smoothly with the motion (a wrong
parameter, a wrong capture frame) up to a quadratic, so what is left is the marker noise even when the fit
is wrong: for independent noise of sigma per axis they have the standard deviation sqrt(20) sigma, and the
median of their absolute value is 0.6745 sqrt(20) sigma (robust to outliers).

A failed check names the likely cause (`crtraj.model.calibration._diagnose`). Units: mm, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from crtraj.model.calibration._stats import CalibrationResult, MarkerStats
from crtraj.model.calibration._timing import TimeOffset

# Fewest third differences for a noise estimate.
MIN_DIFFERENCES = 20


@dataclass(frozen=True)
class GateOptions:
    """noise: marker noise per axis (mm; None: estimated from the data). residual_factor: largest held-out
    RMS (without outliers) over the noise RMS sqrt(3) noise. max_outlier_fraction: largest share of marker
    observations that are outliers. allow_at_bound: parameters that may end at their bound. time_tolerance:
    largest lag (s) between the marker and the actuator motion."""

    noise: float | None = None
    residual_factor: float = 2.0
    max_outlier_fraction: float = 0.1
    allow_at_bound: tuple[str, ...] = ()
    time_tolerance: float = 0.25


@dataclass(frozen=True)
class GateCheck:
    """One check of the gate: its name, whether it passed, and what it found (one phrase)."""

    name: str
    ok: bool
    detail: str


@dataclass(frozen=True)
class GateVerdict:
    """The gate's verdict: the checks, the noise the residuals were judged against (mm per axis, and where
    it came from), the held-out RMS with and without outliers (mm), the outlier count and fraction, the
    detected time offset (None: not measurable) and the likely cause of a failure ("" when it passed).
    heldout_*: of the held-out samples (of the fit samples when none is held out); outlier_fraction: of every
    marker observation."""

    checks: tuple[GateCheck, ...]
    noise: float
    noise_source: str
    heldout_rms: float
    heldout_rms_inliers: float
    heldout_outliers: int
    outlier_fraction: float
    time_offset: TimeOffset | None
    cause: str = ""

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.checks)

    def failed(self) -> GateCheck | None:
        """The first check that failed, or None."""
        return next((c for c in self.checks if not c.ok), None)

    def line(self) -> str:
        """One line: the failed check, what it found and the likely cause ("" when the gate passed)."""
        c = self.failed()
        if c is None:
            return ""
        return f"{c.name} check failed: {c.detail}" + (f"; likely cause: {self.cause}" if self.cause else "")

    def to_dict(self) -> dict[str, object]:
        off = self.time_offset
        return {
            "passed": self.ok,
            "checks": [{"name": c.name, "ok": c.ok, "detail": c.detail} for c in self.checks],
            "noise_mm": self.noise,
            "noise_source": self.noise_source,
            "heldout_rms_mm": self.heldout_rms,
            "heldout_rms_inliers_mm": self.heldout_rms_inliers,
            "heldout_outliers": self.heldout_outliers,
            "outlier_fraction": self.outlier_fraction,
            "time_offset_s": None if off is None else off.lag,
            "cause": self.cause,
        }


def estimate_noise(t: np.ndarray, residuals: np.ndarray) -> float | None:
    """Marker noise per axis (mm) from the residuals (N, M, 3) at times t (N,) s; see the module docstring.

    None when there are too few windows of four evenly spaced samples with the marker seen.
    """
    order = np.argsort(t, kind="stable")
    ts, e = t[order], residuals[order]
    if ts.size < 4:
        return None
    dt = np.diff(ts)
    even = (np.abs(dt[1:] - dt[:-1]) <= 0.01 * np.maximum(dt[1:], 1e-12)) & (dt[1:] > 0)
    window = even[1:] & even[:-1]  # samples i..i+3 evenly spaced
    d3 = e[3:] - 3 * e[2:-1] + 3 * e[1:-2] - e[:-3]  # (N-3, M, 3), NaN where a marker was missing
    d3 = d3[window].reshape(-1)
    d3 = d3[np.isfinite(d3)]
    if d3.size < MIN_DIFFERENCES:
        return None
    return float(np.median(np.abs(d3)) / (0.6745 * math.sqrt(20.0)))


def _overall(stats: dict[str, MarkerStats]) -> tuple[float, float, int, int]:
    """(RMS, RMS without outliers, outliers, count) over every marker of per-marker statistics."""
    n = sum(s.count for s in stats.values())
    if n == 0:
        return math.nan, math.nan, 0, 0
    rms = math.sqrt(sum(s.rms**2 * s.count for s in stats.values() if s.count) / n)
    out = sum(s.outliers for s in stats.values())
    inl = [(s.rms_inliers, s.count - s.outliers) for s in stats.values() if s.count > s.outliers]
    k = sum(c for _, c in inl)
    rms_in = math.sqrt(sum(r**2 * c for r, c in inl) / k) if k else math.nan
    return rms, rms_in, out, n


@dataclass(frozen=True)
class GateInput:
    """What the gate judges: the fit, the detected time offset and the noise estimated from the data (mm per
    axis; None: not measurable)."""

    result: CalibrationResult
    time_offset: TimeOffset | None
    noise_estimate: float | None


def judge(g: GateInput, o: GateOptions, cause: str = "") -> GateVerdict:
    """The gate's verdict on a fit (see the module docstring). cause: the likely cause to name on failure."""
    res = g.result
    part = "heldout" if any(s.count for s in res.after["heldout"].values()) else "fit"
    rms, rms_in, out_part, _ = _overall(res.after[part])
    _, _, out_all, n_all = _overall({f"{p}{k}": s for p in ("fit", "heldout") for k, s in res.after[p].items()})
    frac = out_all / n_all if n_all else 0.0
    noise, source = (o.noise, "--noise") if o.noise is not None else (g.noise_estimate, "data")
    checks = []
    off = g.time_offset
    if off is not None and off.is_gross(o.time_tolerance):
        checks.append(GateCheck("time_offset", False, f"the markers move {off.lag:+.3g} s after the actuators"))
    else:
        lag = "not measurable" if off is None else f"{off.lag:+.3g} s"
        checks.append(GateCheck("time_offset", True, f"lag {lag}"))
    if noise is None:
        checks.append(GateCheck("residual", False, "the noise cannot be estimated from this data; give --noise MM"))
        noise, source = math.nan, "none"
    else:
        limit = o.residual_factor * math.sqrt(3.0) * noise
        ok = rms_in <= limit
        checks.append(
            GateCheck(
                "residual",
                ok,
                f"{part} RMS without outliers {rms_in:.3g} mm {'<=' if ok else '>'} {o.residual_factor:g} x the "
                f"noise RMS {math.sqrt(3.0) * noise:.3g} mm (noise {noise:.3g} mm per axis from {source})",
            )
        )
    ok = frac <= o.max_outlier_fraction
    checks.append(GateCheck("outliers", ok, f"{out_all} of {n_all} marker observations ({100 * frac:.1f} %)"))
    bound = [n for n in res.at_bound if n not in o.allow_at_bound]
    checks.append(GateCheck("bounds", not bound, f"at its bound: {', '.join(bound)}" if bound else "none at bound"))
    acceptable = res.status == "Solved_To_Acceptable_Level" and all(c.ok for c in checks)
    conv = res.status == "Solve_Succeeded" or acceptable
    checks.append(GateCheck("solver", conv, f"IPOPT {res.status} after {res.iterations} iterations"))
    verdict = GateVerdict(tuple(checks), float(noise), source, rms, rms_in, out_part, frac, off, cause)
    return verdict


def usual_cause(check: str) -> str:
    """The usual cause of a failed check other than the residual and time checks (one phrase)."""
    return {
        "outliers": "markers misidentified or swapped in part of the capture, or occlusion glitches; clean the "
        "marker file",
        "bounds": "the data disagree with the robot file beyond the prior range (units, an actuator's sign, the "
        "marker sites); declare it with --allow-at-bound NAME if the range is meant",
        "solver": "the solver stopped before converging; record more varied motion or start from a closer robot file",
    }.get(check, "")
