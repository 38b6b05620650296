"""Library call: calibrate a robot file from a dataset, as `crtraj calibrate` does, without the command line.

`calibrate_robot` fits the chosen parameter groups (`crtraj.app.lab._calibrate.calibrate`), judges the fit with
the sanity gate (`crtraj.app.lab._calibrate.gate`) and, only when the gate passes, writes the calibrated robot
file: the original text with the fitted values replaced and a ``[calibration]`` table
(`crtraj.app.lab._calibration_report.calibrated_text`), renamed into place. A failed fit writes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from crtraj.app.lab._calibrate import calibrate, gate
from crtraj.app.lab._calibration_report import calibrated_text, report_lines
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_text, check_output_file, check_outputs_not_inputs, read_text
from crtraj.hardware.actuators import Actuators
from crtraj.io.calibration_data import Dataset, read_calibration, read_dataset
from crtraj.io.calibration_numbers import display_path
from crtraj.io.problem import load_robot
from crtraj.model.calibration import CalibrateOptions, CalibrationResult, GateOptions, GateVerdict, parse_groups


@dataclass(frozen=True)
class Calibration:
    """A fit and its verdict. path: the calibrated robot file written (None when the gate failed or no
    `out` was given)."""

    result: CalibrationResult
    verdict: GateVerdict
    path: Path | None

    @property
    def ok(self) -> bool:
        """The fit passed the sanity gate."""
        return self.verdict.ok

    def report(self) -> list[str]:
        """The human-readable report `crtraj calibrate` prints."""
        return report_lines(self.result, self.verdict)


def calibrate_robot(
    data: Dataset | str | Path,
    robot_file: str | Path,
    out: str | Path | None = None,
    *,
    fit: str = "all",
    options: CalibrateOptions | None = None,
    gate_options: GateOptions | None = None,
) -> Calibration:
    """Fit `robot_file` (which needs ``[robot.actuators]``) to `data` (a `Dataset` or a dataset file of
    `crtraj record`) and, when the gate passes, write the calibrated robot file to `out`.

    fit: comma-separated parameter groups (lengths, coupling, cable_radius, zero_offsets, base_z,
    capture_frame) or "all". A capture frame recorded in the robot file's ``[calibration]`` is kept when
    it is not fitted. Units: mm, rad. Bad input raises a one-line `InputError`.
    """
    groups = parse_groups(fit)
    target = None
    if out is not None:
        target = check_output_file(out, "out")
        given = None if isinstance(data, Dataset) else data
        check_outputs_not_inputs({"out": out}, {"robot_file": robot_file, "data": given})
    robot = load_robot(robot_file)
    if robot.actuators is None:
        where = display_path(robot_file)
        raise InputError(f"{where}: robot.actuators: missing; calibration needs the servo conversion")
    if isinstance(data, Dataset):
        dataset, source = data, _source_name(data)
    else:
        act = Actuators.from_robot(robot)
        dataset, source = read_dataset(data, act.names, robot.n_segments), display_path(data)
    rec = read_calibration(robot_file)
    capture = rec.capture if rec is not None and "capture_frame" not in groups else None
    res = calibrate(dataset, robot, groups, options, capture=capture)
    verdict = gate(dataset, robot, res, gate_options)
    if not verdict.ok or target is None:
        return Calibration(res, verdict, None)
    original = read_text(robot_file, max_bytes=4 * 1024 * 1024, kind="TOML")
    date = datetime.now(timezone.utc).isoformat(timespec="seconds")
    text = calibrated_text(original, res, verdict, source, date)
    return Calibration(res, verdict, atomic_write_text(target, text))


def _source_name(data: Dataset) -> str:
    """How the calibrated file names an in-memory dataset: its stream log and marker file when it has them."""
    src = data.source
    if "log" in src and "markers" in src:
        return f"{src['log']} + {src['markers']} (time offset {float(src.get('time_offset', 0.0)):g} s)"
    return "dataset in memory"
