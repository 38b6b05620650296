"""What `crtraj calibrate` reports: the printed lines, the JSON report and the calibrated robot file's text.

Every figure is the honest one: the held-out residual with and without outliers and the outlier count, the
noise it was judged against, the gate's checks, and identifiability judged at the prior and at the fit (a
parameter without effect at the prior is never called inert when the fit shows it confounded; the standard
errors of parameters confounded at the fit are withheld). Units: mm, rad, s.
"""

from __future__ import annotations

import math
from typing import Any

from crtraj.core.tomledit import set_values
from crtraj.model.calibration import CalibrationResult, GateVerdict

STIFFNESS_NOTE = (
    "no per-segment stiffness ratio: the model's eq. 8 uses one bending stiffness for both segments "
    "(one NiTi backbone), so there is none to fit"
)


def toml_changes(res: CalibrationResult) -> dict[tuple[Any, ...], Any]:
    """The robot-file key paths and new values of the fitted parameters (held and unfitted ones excluded)."""
    out: dict[tuple[Any, ...], Any] = {}
    for i, name in enumerate(res.layout.names):
        if not res.free[i] or name.startswith("capture."):
            continue
        v = float(res.theta[i])
        if name.startswith("segment["):
            out[("robot", "segment", int(name[8 : name.index("]")]), "length")] = v
        elif name in ("coupling", "cable_radius"):
            out[("robot", name)] = v
        elif name == "z.zero_offset":
            out[("robot", "actuators", "z", "zero_offset")] = v
        else:  # s<k>c<i>.zero_offset: a per-servo override
            out[("robot", "actuators", "servo", name.split(".")[0], "zero_offset")] = v
    return out


def calibrated_text(original: str, res: CalibrationResult, verdict: GateVerdict, dataset_name: str, date: str) -> str:
    """The robot file's text with the fitted values and the ``[calibration]`` table set.

    dataset_name: printable (`crtraj.io.calibration_numbers.display_path`): it is written into the TOML.
    """
    changes = toml_changes(res)
    cap = res.capture()
    cal: dict[str, Any] = {
        "dataset": dataset_name,
        "date": date,
        "fitted": [n for i, n in enumerate(res.layout.names) if res.free[i]],
        "held": [h.name for h in res.held],
        "confounded": list(res.identifiability.withheld) if res.identifiability else [],
        "capture_rotation": [float(x) for x in cap[:3]],
        "capture_translation": [float(x) for x in cap[3:]],
        "heldout_outliers": int(verdict.heldout_outliers),
    }
    for key, v in (
        ("heldout_rms_mm", verdict.heldout_rms),
        ("heldout_rms_inliers_mm", verdict.heldout_rms_inliers),
        ("noise_mm", verdict.noise),
    ):
        if math.isfinite(v):
            cal[key] = float(v)
    changes.update({("calibration", k): v for k, v in cal.items()})
    return set_values(original, changes)


def _identifiability_dict(res: CalibrationResult) -> dict[str, Any]:
    ident = res.identifiability
    if ident is None:
        return {}
    return {
        "held_at_prior": [{"name": h.name, "confounded_with": list(h.confounded_with)} for h in ident.held_prior],
        "held_at_fit": [{"name": h.name, "confounded_with": list(h.confounded_with)} for h in ident.held_fit],
        "confounded_at_fit": [h.name for h in ident.confounded_at_fit()],
        "std_error_withheld": list(ident.withheld),
        "singular_values_at_prior": ident.sv_prior,
        "singular_values_at_fit": ident.sv_fit,
    }


def report_dict(res: CalibrationResult, verdict: GateVerdict, dataset_path: str, robot_path: str) -> dict[str, Any]:
    """The JSON report: the gate, residuals before/after, fitted values with standard errors, identifiability."""
    L = res.layout
    params = [
        {
            "name": n,
            "group": L.groups[i],
            "unit": L.units[i],
            "prior": float(res.prior[i]),
            "value": float(res.theta[i]),
            "std_error": None if not math.isfinite(res.std_error[i]) else float(res.std_error[i]),
            "fitted": bool(res.free[i]),
        }
        for i, n in enumerate(L.names)
    ]

    def stats(d: dict[str, dict[str, Any]]) -> dict[str, Any]:
        return {split_: {m: s.to_dict() for m, s in v.items()} for split_, v in d.items()}

    return {
        "kind": "calibration-report",
        "dataset": dataset_path,
        "robot": robot_path,
        "success": res.success and verdict.ok,
        "status": res.status,
        "gate": verdict.to_dict(),
        "iterations": res.iterations,
        "solve_time_s": res.solve_time,
        "sigma_mm": res.sigma,
        "parameters": params,
        "held": [{"name": h.name, "confounded_with": list(h.confounded_with)} for h in res.held],
        "identifiability": _identifiability_dict(res),
        "at_bound": list(res.at_bound),
        "singular_values": [float(s) for s in res.singular_values],
        "residuals_before": stats(res.before),
        "residuals_after": stats(res.after),
        "note": STIFFNESS_NOTE,
    }


def _held_lines(res: CalibrationResult) -> list[str]:
    """Warnings for the parameters held at the prior and those confounded at the fit."""
    ident = res.identifiability
    out = []
    for h in res.held:
        if h.confounded_with:
            why = f"cannot be told apart from {', '.join(h.confounded_with)}"
        else:
            partners = ident.effect_at_fit(h.name) if ident else ()
            why = (
                f"no effect at the prior values, but at the fit it cannot be told apart from {', '.join(partners)}"
                if partners
                else "no effect on these markers for this motion, at the prior and at the fit"
            )
        out.append(f"warning: {h.name} is not identifiable from this data ({why}); held at its prior")
    if ident is not None:
        held = {h.name for h in res.held}
        for h in ident.confounded_at_fit():
            if h.name not in held:
                out.append(
                    f"warning: at the fit, {h.name} cannot be told apart from {', '.join(h.confounded_with)} "
                    "(not at the prior): their values depend on the parameters held"
                )
        if ident.withheld:
            out.append(f"warning: standard errors withheld (confounded at the fit): {', '.join(ident.withheld)}")
    return out


def report_lines(res: CalibrationResult, verdict: GateVerdict | None = None) -> list[str]:
    """The human-readable report."""
    L = res.layout
    out = [f"solver: {res.status} after {res.iterations} iterations, {res.solve_time:.2f} s"]
    out.append(
        "residuals per marker (mm): RMS / p95 / max, uncalibrated -> calibrated; then RMS without the outliers "
        "(> 4 x median) and their count"
    )
    for part in ("fit", "heldout"):
        for m, a in res.after[part].items():
            b = res.before[part][m]
            if a.count:
                out.append(
                    f"  {part:8s} {m:8s} n={a.count:5d}  {b.rms:8.3f} / {b.p95:8.3f} / {b.max:8.3f}  ->  "
                    f"{a.rms:7.3f} / {a.p95:7.3f} / {a.max:7.3f};  {a.rms_inliers:6.3f} ({a.outliers} outliers)"
                )
    out.append("parameters: prior -> fitted +- standard error")
    for i, n in enumerate(L.names):
        if res.free[i]:
            se = res.std_error[i]
            err = f"{se:.2g}" if math.isfinite(se) else "withheld"
            out.append(f"  {n:24s} {res.prior[i]:12.5g} -> {res.theta[i]:12.6g} +- {err} {L.units[i]}")
    out += _held_lines(res)
    for n in res.at_bound:
        out.append(f"warning: {n} ended at its bound; the data or the model disagree with its prior range")
    ident = res.identifiability
    if ident is not None and ident.sv_fit.size:
        out.append(
            "identifiability: smallest singular values of the scaled weighted Jacobian of the parameters asked for: "
            f"at the prior {_smallest(ident.sv_prior)}; at the fit {_smallest(ident.sv_fit)}"
        )
    if verdict is not None:
        out += [f"gate: {c.name}: {'ok' if c.ok else 'FAILED'}: {c.detail}" for c in verdict.checks]
    out.append(f"note: {STIFFNESS_NOTE}")
    return out


def _smallest(sv: Any, k: int = 3) -> str:
    return ", ".join(f"{s:.3g}" for s in list(sv)[-k:])
