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
import time
from pathlib import Path

import numpy as np

from crtraj.app.stream import _print_report, _stream
from crtraj.core.errors import InputError
from crtraj.core.fileio import check_output_file
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion, MotionRecord, admit
from crtraj.hardware.stream import StreamOptions
from crtraj.io.calibration_data import Dataset, parse_marker_option
from crtraj.io.mocap import join, read_markers, read_stream_log
from crtraj.io.problem import Problem, load_robot
from crtraj.model.calibration import MarkerSite, check_sites, paper_markers
from crtraj.model.excitation import excitation_path
from crtraj.model.robot import Robot
from crtraj.world.scene import Scene

# Share of each actuator's speed and acceleration limit the excitation may use.
LIMIT_SHARE = 0.5


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
    """(the dataset of `log` joined with `markers`, capture frames dropped)."""
    act = Actuators.from_robot(robot)
    series = read_stream_log(log, prefer)
    if series.names != act.names:
        raise InputError(f"{log}: actuators {list(series.names)} are not robot {robot.name!r}'s {list(act.names)}")
    frames = read_markers(markers, sites)
    t, values, positions, dropped = join(series, frames, time_offset)
    source = {
        "log": str(log),
        "markers": str(markers),
        "time_offset": time_offset,
        "values": series.kind,
        "robot": robot.name,
    }
    return Dataset(act.names, sites, t, values, positions, source), dropped


def record_command(args: argparse.Namespace) -> int:
    """`crtraj record ...` (arguments from `crtraj.cli`); returns the exit code."""
    out = check_output_file(args.out, "--out")
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(f"{args.robot}: robot.actuators: missing; a dataset records actuator values")
    sites = marker_sites(args.marker, robot)
    log = args.log
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
        rep = _stream(stream_args, motion, opts, Path(log))
        _print_report(rep, args.dry_run)
        if not rep.ok:
            return 1
        if args.markers is None:
            print(
                f"excitation streamed; join it with the capture: crtraj record --log {log} --markers FILE --out {out}"
            )
            return 0
    elif args.log is None or args.markers is None:
        raise InputError("record: give --log and --markers (or --excite to stream the excitation motion)")
    data, dropped = record_dataset(log, args.markers, robot, sites, time_offset=args.time_offset, prefer=args.values)
    data.write(out)
    seen = np.isfinite(data.positions).all(axis=2).sum(axis=0)
    counts = ", ".join(f"{s.name} {int(c)}" for s, c in zip(sites, seen, strict=True))
    print(
        f"dataset: {out}: {data.n} samples ({data.source['values']} actuator values; markers seen: {counts}); "
        f"{dropped} capture frames outside the log dropped"
    )
    return 0
