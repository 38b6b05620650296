"""Use case: write a calibration dataset (`crtraj record`).

Join mode: a stream log (`crtraj stream --log`, `crtraj replan --stream`) and a motion-capture marker
file are joined by timestamp (`crtraj.io.mocap.join`: the actuator values interpolated at every capture
frame; non-overlapping times refused) into a dataset (`crtraj.io.calibration_data`).

Excitation mode (``--excite``): the built-in excitation path (`crtraj.model.excitation`) is timed within
the actuators' speed and acceleration limits, admitted like any result (`crtraj.hardware.admission.admit`:
set-points verified as sent against the scene: an empty one, or --problem's) and streamed to the device
with its log; with --markers the log is then joined as above.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np

from crtraj.app.devices import failure_line, print_report, stream_motion
from crtraj.app.lab._record_plant import plant_dataset
from crtraj.app.plant_sim import PLANTS, PRETENSION
from crtraj.core.errors import InputError
from crtraj.core.fields import check_float
from crtraj.core.fileio import check_output_file, check_outputs_not_inputs
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion, MotionRecord, admit
from crtraj.hardware.stream import StreamOptions
from crtraj.io.calibration_data import Dataset, parse_marker_option
from crtraj.io.calibration_numbers import TIME_LIMIT, display_path
from crtraj.io.mocap import join, read_markers, read_stream_log
from crtraj.io.problem import Problem, load_robot
from crtraj.model.calibration import (
    CalibrateOptions,
    CalibrationModel,
    Hardware,
    Layout,
    MarkerSite,
    Observations,
    check_sites,
    detect_time_offset,
    initial_capture,
    paper_markers,
)
from crtraj.model.cosserat import RodDrive
from crtraj.model.excitation import excitation_path
from crtraj.model.robot import Robot
from crtraj.world.scene import Scene

# Share of each actuator's speed and acceleration limit the excitation may use.
LIMIT_SHARE = 0.5
# Largest lag (s) between the marker and the actuator motion a dataset may have.
TIME_TOLERANCE = 0.25

logger = logging.getLogger(__name__)


def excitation_motion(
    robot: Robot, actuators: Actuators, scene: Scene, *, duration: float | None = None, rate: float = 100.0
) -> AdmittedMotion:
    """The excitation path, timed within LIMIT_SHARE of the actuator limits (at least `duration` s) and
    admitted for `actuators` against `scene` (`AdmissionError` when any set-point fails the check)."""
    s, x = excitation_path(robot)
    lim = actuators.rate_limits(robot)
    ds = s[1] - s[0]
    dv = np.abs(np.gradient(x, ds, axis=0) @ lim.jacobian.T)  # d value / d s
    av = np.abs(np.gradient(np.gradient(x, ds, axis=0), ds, axis=0) @ lim.jacobian.T)
    t_v = float(np.max(dv / (LIMIT_SHARE * lim.vmax)))
    t_a = float(np.sqrt(np.max(av / (LIMIT_SHARE * lim.amax))))
    T = max(t_v, t_a, duration or 0.0, 1.0)
    if T > 3600:
        raise InputError(f"--duration: the excitation would take {T:.0f} s (at most 3600 s)")
    rec = MotionRecord(
        source="excitation",
        kind="plan",
        status="excitation",
        success=True,
        safety=True,
        collisions=0,
        safety_violations=0,
        robot=robot,
        scene=scene,
        t=s * T,
        q=robot.cables(x),
    )
    return admit(rec, actuators, robot=robot, rate=rate)


def marker_sites(options: list[str] | None, robot: Robot) -> tuple[MarkerSite, ...]:
    """The marker sites of ``--marker NAME=SEGMENT:ARC`` options (none: the paper's three markers)."""
    if not options:
        return paper_markers(robot.n_segments)
    sites = tuple(parse_marker_option(m, robot.n_segments) for m in options)
    names = [s.name for s in sites]
    if len(set(names)) != len(names):
        raise InputError(f"--marker: a marker is named twice ({', '.join(names)})")
    check_sites(sites, robot)
    return sites


def record_dataset(
    log: str | Path,
    markers: str | Path,
    robot: Robot,
    sites: tuple[MarkerSite, ...],
    *,
    time_offset: float = 0.0,
    prefer: str = "measured",
) -> tuple[Dataset, int]:
    """(the dataset of `log` joined with `markers`, capture frames dropped).

    `InputError` when the markers are not in mm (their spread against the robot's) or when their motion
    lags the actuators' grossly (`crtraj.model.calibration._timing`: a wrong --time-offset).
    """
    time_offset = check_float(time_offset, "--time-offset", limit=TIME_LIMIT)
    act = Actuators.from_robot(robot)
    series = read_stream_log(log, prefer)
    if series.names != act.names:
        where = display_path(log)
        raise InputError(f"{where}: actuators {list(series.names)} are not robot {robot.name!r}'s {list(act.names)}")
    frames = read_markers(markers, sites)
    t, values, positions, dropped = join(series, frames, time_offset)
    layout = Layout.build(robot, act.zero_offset, np.zeros(6), CalibrateOptions())
    cm = CalibrationModel(robot, Hardware(act.spool_radius, act.sign), sites, layout)
    _check_units(cm, values, positions)
    _check_timing(cm, t, values, positions, time_offset)
    source = {
        "log": display_path(log),
        "markers": display_path(markers),
        "time_offset": time_offset,
        "values": series.kind,
        "robot": robot.name,
    }
    return Dataset(act.names, sites, t, values, positions, source), dropped


def _check_units(cm: CalibrationModel, values: np.ndarray, positions: np.ndarray) -> None:
    """The unit check `crtraj calibrate` applies: the markers' spread against the nominal model's (mm)."""
    rows = np.flatnonzero(np.isfinite(positions).all(axis=2).any(axis=1))
    if rows.size:
        obs = Observations(values, positions, cm.sites, np.zeros(values.shape[0], dtype=bool))
        initial_capture(cm, cm.layout.prior, obs, rows)


def _check_timing(
    cm: CalibrationModel, t: np.ndarray, values: np.ndarray, positions: np.ndarray, time_offset: float
) -> None:
    """Refuse a gross lag between the marker and the actuator motion (one line naming --time-offset)."""
    off = detect_time_offset(cm, cm.layout.prior, t, values, positions)
    if off is None:
        logger.info("time alignment: not measurable (too few or unevenly spaced samples, or no common motion)")
        return
    logger.info("time alignment: the markers move %+.3f s after the actuator values", off.lag)
    if off.is_gross(TIME_TOLERANCE):
        raise InputError(
            f"--time-offset: the markers move {off.lag:+.3g} s after the actuator values (their motion against "
            f"the model's); the time offset is likely {time_offset + off.lag:.6g} s, not {time_offset:g} s"
        )


def _record_plant(args: argparse.Namespace, robot: Robot, sites: tuple[MarkerSite, ...], out: Path) -> int:
    """`--excite --plant MODEL`: the excitation filmed on the simulated rod (`crtraj.app.lab._record_plant`)."""
    if not args.excite or any(x is not None for x in (args.udp, args.serial, args.dry_run, args.log, args.markers)):
        raise InputError("--plant: a simulated capture of the excitation: give --excite and none of --udp, "
                         "--serial, --dry-run, --log, --markers")  # fmt: skip
    if args.plant not in PLANTS:
        raise InputError(f"--plant: unknown plant {args.plant!r} (choose from {', '.join(PLANTS)})")
    drive = RodDrive(robot, pretension=PRETENSION, gravity=args.plant == "cosserat")
    prob = Problem.load(args.problem) if args.problem else None
    scene = prob.options(Scene, "scene") if prob else Scene()
    motion = excitation_motion(robot, Actuators.from_robot(robot), scene, duration=args.duration)
    data = plant_dataset(motion, drive, sites, rate=args.capture_rate, seed=prob.seed if prob else 0)
    data.write(out)
    print(
        f"dataset: {display_path(out)}: {data.n} samples of {len(sites)} markers filmed on the {args.plant} rod "
        f"({data.t[-1]:.1f} s of excitation at {args.capture_rate:g} Hz, 0.3 mm capture noise)"
    )
    return 0


def record_command(args: argparse.Namespace) -> int:
    """`crtraj record ...` (arguments from `crtraj.cli`); returns the exit code."""
    out = check_output_file(args.out, "--out")
    written = {"--out": args.out, "--dry-run": args.dry_run, "--log": args.log if args.excite else None}
    read = {"--robot": args.robot, "--markers": args.markers, "--problem": args.problem}
    check_outputs_not_inputs(written, {**read, "--log": None if args.excite else args.log})
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(f"{args.robot}: robot.actuators: missing; a dataset records actuator values")
    sites = marker_sites(args.marker, robot)
    log = args.log
    if getattr(args, "plant", None):
        return _record_plant(args, robot, sites, out)
    if args.excite:
        if sum(x is not None for x in (args.udp, args.serial, args.dry_run)) != 1:
            raise InputError("--excite: give exactly one of --udp, --serial, --dry-run")
        prob = Problem.load(args.problem) if args.problem else None
        opts = prob.options(StreamOptions, "stream") if prob else StreamOptions()
        scene = prob.options(Scene, "scene") if prob else Scene()
        motion = excitation_motion(robot, Actuators.from_robot(robot), scene, duration=args.duration, rate=opts.rate)
        log = log or Path("out") / "record" / f"excite-{time.strftime('%Y%m%d-%H%M%S')}.jsonl"
        stream_args = argparse.Namespace(
            result="excitation", udp=args.udp, serial=args.serial, baud=args.baud, dry_run=args.dry_run, approach=False
        )
        rep = stream_motion(stream_args, motion, opts, Path(log))
        print_report(rep, args.dry_run)
        if not rep.ok:
            print(f"crtraj: record failed: the excitation stream {failure_line(rep)}", file=sys.stderr)
            return 1
        if args.markers is None:
            shown, out_shown = display_path(log), display_path(out)
            print(
                f"excitation streamed; join it with the capture: crtraj record --log {shown} --markers FILE "
                f"--out {out_shown}"
            )
            return 0
    elif args.log is None or args.markers is None:
        raise InputError("record: give --log and --markers (or --excite to stream the excitation motion)")
    data, dropped = record_dataset(log, args.markers, robot, sites, time_offset=args.time_offset, prefer=args.values)
    data.write(out)
    seen = np.isfinite(data.positions).all(axis=2).sum(axis=0)
    counts = ", ".join(f"{s.name} {int(c)}" for s, c in zip(sites, seen, strict=True))
    print(
        f"dataset: {display_path(out)}: {data.n} samples ({data.source['values']} actuator values; "
        f"markers seen: {counts}); "
        f"{dropped} capture frames outside the log dropped"
    )
    return 0
