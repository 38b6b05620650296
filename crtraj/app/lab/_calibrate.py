"""Use case: fit the robot file's parameters to a calibration dataset (`crtraj calibrate`).

Reads the robot file and the dataset (`crtraj.io.calibration_data`), fits the chosen parameter groups
(`crtraj.model.calibration._fit`: one CasADi NLP, pseudo-Huber loss, exact Jacobians, bounds, held-out
split), judges the fit with the sanity gate (`crtraj.model.calibration._gate`: time offset, held-out
residual against the noise, outliers, bounds, convergence), prints the report, and writes:

- the calibrated robot file (--out): the original text with only the fitted values replaced
  (`crtraj.core.tomledit`) and a ``[calibration]`` table with the dataset, the date, the capture frame,
  what was fitted and held, the held-out RMS with and without outliers, the outlier count and the noise;
- the report (--report, JSON) and the residual plot (--plot, PNG).

No output may be an input (`check_outputs_not_inputs`, before any work). All files are staged first and
renamed together at the end, so a refusal at any point replaces nothing. A fit that fails the gate exits 1
with one line naming the failed check and the likely cause; its report and plot are kept for diagnosis
beside the usual names (``cal.report.failed.json``, ``cal.residuals.failed.png``) and nothing else is
written: a good calibrated file is never replaced by a failed one.
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj.app.lab._calibration_report import calibrated_text, report_dict, report_lines
from crtraj.app.lab._record import marker_sites, record_dataset
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, check_float
from crtraj.core.fileio import (
    StagedFile,
    check_output_file,
    check_outputs_not_inputs,
    failed_sibling,
    json_document,
    read_text,
    to_jsonable,
)
from crtraj.hardware.actuators import Actuators
from crtraj.io.calibration_data import Dataset, read_calibration, read_dataset
from crtraj.io.calibration_numbers import display_path
from crtraj.io.calibration_plot import residual_plot_png
from crtraj.io.problem import load_robot
from crtraj.model.calibration import (
    CalibrateOptions,
    CalibrationModel,
    CalibrationResult,
    GateInput,
    GateOptions,
    GateVerdict,
    Hardware,
    Layout,
    Observations,
    detect_time_offset,
    estimate_noise,
    fit,
    judge,
    likely_cause,
    parse_groups,
    split,
    usual_cause,
)
from crtraj.model.robot import Robot

__all__ = ["calibrate", "calibrate_command", "gate"]

logger = logging.getLogger(__name__)


def calibrate(
    dataset: Dataset,
    robot: Robot,
    groups: tuple[str, ...],
    options: CalibrateOptions | None = None,
    capture: np.ndarray | None = None,
) -> CalibrationResult:
    """Fit `groups` of `robot` (with its actuators) to `dataset`; see `crtraj.model.calibration._fit`."""
    o = options or CalibrateOptions()
    act = Actuators.from_robot(robot)
    hw = Hardware(act.spool_radius, act.sign)
    obs = Observations(dataset.values, dataset.positions, dataset.sites, split(dataset.n, o.holdout, o.seed))
    return fit(robot, hw, act.zero_offset, obs, groups, o, capture=capture)


def _model(robot: Robot, dataset: Dataset, res: CalibrationResult) -> CalibrationModel:
    act = Actuators.from_robot(robot)
    return CalibrationModel(robot, Hardware(act.spool_radius, act.sign), dataset.sites, res.layout)


def gate(dataset: Dataset, robot: Robot, res: CalibrationResult, options: GateOptions | None = None) -> GateVerdict:
    """The sanity gate on a fit of `dataset` (`crtraj.model.calibration._gate`), with the likely cause of a
    failure: a time offset, swapped marker names or a reversed actuator when one explains the residuals."""
    o = options or GateOptions()
    cm = _model(robot, dataset, res)
    off = detect_time_offset(cm, res.prior, dataset.t, dataset.values, dataset.positions)
    verdict = judge(GateInput(res, off, estimate_noise(dataset.t, res.residuals)), o)
    failed = verdict.failed()
    if failed is None:
        return verdict
    if failed.name in ("time_offset", "residual"):
        cause = likely_cause(cm, res.prior, dataset.values, dataset.positions, off, o.time_tolerance)
    else:
        cause = usual_cause(failed.name)
    logger.info("calibration gate failed: %s", failed.detail)
    return replace(verdict, cause=cause)


@dataclass(frozen=True)
class _Paths:
    """The outputs of one run: calibrated robot file, report, plot and their failed siblings."""

    out: Path
    report: Path
    plot: Path

    @property
    def failed_report(self) -> Path:
        return failed_sibling(self.report)

    @property
    def failed_plot(self) -> Path:
        return failed_sibling(self.plot)


def _paths(args: argparse.Namespace) -> _Paths:
    """Check every output path before any work: writable, and none of them an input."""
    out = check_output_file(args.out, "--out")
    p = _Paths(
        out,
        Path(args.report) if args.report else out.with_suffix(".report.json"),
        Path(args.plot) if args.plot else out.with_suffix(".residuals.png"),
    )
    for flag, path in (("--report", p.report), ("--plot", p.plot)):
        check_output_file(path, flag)
    check_outputs_not_inputs(
        {
            "--out": p.out,
            "--report": p.report,
            "--plot": p.plot,
            "--report (failed)": p.failed_report,
            "--plot (failed)": p.failed_plot,
        },
        {"--robot": args.robot, "DATA": args.data, "--log": args.log, "--markers": args.markers},
    )
    return p


def _dataset(args: argparse.Namespace, robot: Robot, act: Actuators) -> tuple[Dataset, str]:
    """(the dataset, how to name its source, printable): DATA, or --log joined with --markers on the fly."""
    if (args.data is None) == (args.log is None):
        raise InputError("calibrate: give a dataset (DATA) or --log with --markers, not both")
    if args.data is not None:
        return read_dataset(args.data, act.names, robot.n_segments), display_path(args.data)
    if args.markers is None:
        raise InputError("--log: needs --markers (the motion-capture file to join it with)")
    sites = marker_sites(args.marker, robot)
    data, dropped = record_dataset(
        args.log, args.markers, robot, sites, time_offset=args.time_offset, prefer=args.values
    )
    log_name, markers_name = display_path(args.log), display_path(args.markers)
    print(f"joined {log_name} with {markers_name}: {data.n} samples ({dropped} capture frames outside the log)")
    return data, f"{log_name} + {markers_name} (time offset {args.time_offset:g} s)"


def _gate_options(args: argparse.Namespace, robot: Robot, opts: CalibrateOptions) -> GateOptions:
    """The gate's options from --noise and --allow-at-bound (each checked, one line when bad)."""
    noise = getattr(args, "noise", None)
    if noise is not None:
        noise = check_float(noise, "--noise", gt=0.0, limit=MAX_LENGTH)
    allowed = tuple(getattr(args, "allow_at_bound", None) or ())
    act = Actuators.from_robot(robot)
    names = Layout.build(robot, act.zero_offset, np.zeros(6), opts).names
    for n in allowed:
        if n not in names:
            raise InputError(f"--allow-at-bound: unknown parameter {display_path(n)!r} (known: {', '.join(names)})")
    return GateOptions(noise=noise, allow_at_bound=allowed)


def _commit_all(files: list[tuple[Path, bytes]]) -> None:
    """Stage every file, then rename them all: a failure while staging replaces nothing."""
    staged: list[StagedFile] = []
    try:
        for path, data in files:
            s = StagedFile(path)
            staged.append(s)
            s.write(data)
        for s in staged:
            s.commit()
    finally:
        for s in staged:
            s.discard()


def _plot(robot: Robot, data: Dataset, res: CalibrationResult) -> bytes:
    cm = _model(robot, data, res)
    before = cm.residuals(res.prior, data.values, data.positions)
    names = [s.name for s in data.sites]
    return residual_plot_png(cm.predict(res.theta, data.values), before, res.residuals, res.heldout_mask, names)


def calibrate_command(args: argparse.Namespace) -> int:
    """`crtraj calibrate DATA --robot FILE --out calibrated.toml [...]` (or --log LOG --markers FILE instead of
    DATA: the join of `crtraj record` on the fly); returns the exit code."""
    groups = parse_groups(args.fit)
    paths = _paths(args)
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(
            f"{display_path(args.robot)}: robot.actuators: missing; calibration needs the servo conversion"
        )
    original = read_text(args.robot, max_bytes=4 * 1024 * 1024, kind="TOML")
    act = Actuators.from_robot(robot)
    opts = CalibrateOptions(
        **{k: v for k, v in (("loss_scale", args.loss_scale), ("holdout", args.holdout)) if v is not None}
    )
    gate_opts = _gate_options(args, robot, opts)
    data, source = _dataset(args, robot, act)
    rec = read_calibration(args.robot)
    prior_capture = rec.capture if rec is not None and "capture_frame" not in groups else None
    res = calibrate(data, robot, groups, opts, capture=prior_capture)
    verdict = gate(data, robot, res, gate_opts)
    for line in report_lines(res, verdict):
        print(line)
    report = json_document(to_jsonable(report_dict(res, verdict, source, display_path(args.robot)))).encode()
    if not verdict.ok:
        _commit_all([(paths.failed_report, report), (paths.failed_plot, _plot(robot, data, res))])
        print(f"report: {display_path(paths.failed_report)}")
        out = display_path(args.out)
        print(f"crtraj: calibrate failed: {verdict.line()}; {out} not written", file=sys.stderr)
        return 1
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    text = calibrated_text(original, res, verdict, source, date)  # refuses before anything is written
    _commit_all([(paths.out, text.encode()), (paths.report, report), (paths.plot, _plot(robot, data, res))])
    print(
        f"calibrated robot: {display_path(paths.out)}\nreport: {display_path(paths.report)}\n"
        f"plot: {display_path(paths.plot)}"
    )
    return 0
