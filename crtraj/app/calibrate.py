"""Use case: fit the robot file's parameters to a calibration dataset (`crtraj calibrate`).

Reads the robot file and the dataset (`crtraj.io.calibration_data`), fits the chosen parameter groups
(`crtraj.model.calibration.fit`: one CasADi NLP, pseudo-Huber loss, exact Jacobians, bounds, held-out
split), prints the report, and writes:

- the calibrated robot file (--out): the original text with only the fitted values replaced
  (`crtraj.core.tomledit`, which re-parses it to prove that nothing else changed) and a ``[calibration]``
  table with the dataset, the date, the capture frame and what was fitted and held;
- the report (--report, JSON) and the residual plot (--plot, PNG).

A failed solve writes nothing and exits 1. Every file is written atomically.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.app.record import marker_sites, record_dataset
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_json, atomic_write_text, check_output_file, read_text
from crtraj.core.tomledit import set_values
from crtraj.hardware.actuators import Actuators
from crtraj.io.calibration_data import Dataset, read_calibration, read_dataset
from crtraj.io.calibration_plot import residual_plot
from crtraj.io.problem import load_robot
from crtraj.model.calibration import (
    CalibrateOptions,
    CalibrationModel,
    CalibrationResult,
    Hardware,
    Observations,
    fit,
    parse_groups,
    split,
)
from crtraj.model.robot import Robot

STIFFNESS_NOTE = (
    "no per-segment stiffness ratio: the model's eq. 8 uses one bending stiffness for both segments "
    "(one NiTi backbone), so there is none to fit"
)


def calibrate(
    dataset: Dataset,
    robot: Robot,
    groups: tuple[str, ...],
    options: CalibrateOptions | None = None,
    capture: np.ndarray | None = None,
) -> CalibrationResult:
    """Fit `groups` of `robot` (with its actuators) to `dataset`; see `crtraj.model.calibration.fit`."""
    o = options or CalibrateOptions()
    act = Actuators.from_robot(robot)
    hw = Hardware(act.spool_radius, act.sign)
    obs = Observations(dataset.values, dataset.positions, dataset.sites, split(dataset.n, o.holdout, o.seed))
    return fit(robot, hw, act.zero_offset, obs, groups, o, capture=capture)


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


def calibrated_text(original: str, res: CalibrationResult, dataset_name: str, date: str) -> str:
    """The robot file's text with the fitted values and the ``[calibration]`` table set."""
    changes = toml_changes(res)
    cap = res.capture()
    held_rms = _overall(res.after["heldout"])
    cal: dict[str, Any] = {
        "dataset": dataset_name,
        "date": date,
        "fitted": [n for i, n in enumerate(res.layout.names) if res.free[i]],
        "held": [h.name for h in res.held],
        "capture_rotation": [float(x) for x in cap[:3]],
        "capture_translation": [float(x) for x in cap[3:]],
    }
    if math.isfinite(held_rms):
        cal["heldout_rms_mm"] = held_rms
    changes.update({("calibration", k): v for k, v in cal.items()})
    return set_values(original, changes, comment="crtraj calibrate")


def _overall(stats: dict[str, Any]) -> float:
    """RMS over every marker of per-marker statistics (count-weighted)."""
    n = sum(s.count for s in stats.values())
    if n == 0:
        return math.nan
    return math.sqrt(sum(s.rms**2 * s.count for s in stats.values() if s.count) / n)


def report_dict(res: CalibrationResult, dataset_path: str, robot_path: str) -> dict[str, Any]:
    """The JSON report: residuals before/after, fitted values with standard errors, identifiability."""
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
        "success": res.success,
        "status": res.status,
        "iterations": res.iterations,
        "solve_time_s": res.solve_time,
        "sigma_mm": res.sigma,
        "parameters": params,
        "held": [{"name": h.name, "confounded_with": list(h.confounded_with)} for h in res.held],
        "at_bound": list(res.at_bound),
        "singular_values": [float(s) for s in res.singular_values],
        "residuals_before": stats(res.before),
        "residuals_after": stats(res.after),
        "note": STIFFNESS_NOTE,
    }


def report_lines(res: CalibrationResult) -> list[str]:
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
            out.append(f"  {n:24s} {res.prior[i]:12.5g} -> {res.theta[i]:12.6g} +- {res.std_error[i]:.2g} {L.units[i]}")
    for h in res.held:
        why = f"cannot be told apart from {', '.join(h.confounded_with)}" if h.confounded_with else "no effect"
        out.append(f"warning: {h.name} is not identifiable from this data ({why}); held at its prior")
    for n in res.at_bound:
        out.append(f"warning: {n} ended at its bound; the data or the model disagree with its prior range")
    sv = res.singular_values
    if sv.size:
        out.append(f"identifiability: singular values of the scaled weighted Jacobian {sv[0]:.3g} .. {sv[-1]:.3g}")
    out.append(f"note: {STIFFNESS_NOTE}")
    return out


def _same(a: str | Path, b: str | Path) -> bool:
    try:
        return Path(a).exists() and Path(b).exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _dataset(args: argparse.Namespace, robot: Robot, act: Actuators) -> tuple[Dataset, str]:
    """(the dataset, how to name its source): DATA, or --log joined with --markers on the fly."""
    if (args.data is None) == (args.log is None):
        raise InputError("calibrate: give a dataset (DATA) or --log with --markers, not both")
    if args.data is not None:
        return read_dataset(args.data, act.names, robot.n_segments), str(args.data)
    if args.markers is None:
        raise InputError("--log: needs --markers (the motion-capture file to join it with)")
    sites = marker_sites(args.marker, robot)
    data, dropped = record_dataset(
        args.log, args.markers, robot, sites, time_offset=args.time_offset, prefer=args.values
    )
    print(f"joined {args.log} with {args.markers}: {data.n} samples ({dropped} capture frames outside the log)")
    return data, f"{args.log} + {args.markers} (time offset {args.time_offset:g} s)"


def calibrate_command(args: argparse.Namespace) -> int:
    """`crtraj calibrate DATA --robot FILE --out calibrated.toml [...]` (or --log LOG --markers FILE instead of
    DATA: the join of `crtraj record` on the fly); returns the exit code."""
    groups = parse_groups(args.fit)
    out = check_output_file(args.out, "--out")
    if _same(out, args.robot) or Path(out).resolve() == Path(args.robot).resolve():
        raise InputError(f"--out: {args.out} is the robot file itself; write the calibrated file beside it")
    report_path = Path(args.report) if args.report else out.with_suffix(".report.json")
    plot_path = Path(args.plot) if args.plot else out.with_suffix(".residuals.png")
    for flag, p in (("--report", report_path), ("--plot", plot_path)):
        check_output_file(p, flag)
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(f"{args.robot}: robot.actuators: missing; calibration needs the servo conversion")
    original = read_text(args.robot, max_bytes=4 * 1024 * 1024, kind="TOML")
    act = Actuators.from_robot(robot)
    data, source = _dataset(args, robot, act)
    opts = CalibrateOptions(
        **{k: v for k, v in (("loss_scale", args.loss_scale), ("holdout", args.holdout)) if v is not None}
    )
    rec = read_calibration(args.robot)
    prior_capture = rec.capture if rec is not None and "capture_frame" not in groups else None
    res = calibrate(data, robot, groups, opts, capture=prior_capture)
    for line in report_lines(res):
        print(line)
    atomic_write_json(report_path, report_dict(res, source, str(args.robot)))
    if not res.success:
        print(f"report: {report_path}")
        print(f"crtraj: calibrate failed: {res.status}; {args.out} not written", file=sys.stderr)
        return 1
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    atomic_write_text(out, calibrated_text(original, res, source, date))
    cm = CalibrationModel(robot, Hardware(act.spool_radius, act.sign), data.sites, res.layout)
    names = [s.name for s in data.sites]
    before = cm.residuals(res.prior, data.values, data.positions)
    residual_plot(plot_path, cm.predict(res.theta, data.values), before, res.residuals, res.heldout_mask, names)
    print(f"calibrated robot: {out}\nreport: {report_path}\nplot: {plot_path}")
    return 0
