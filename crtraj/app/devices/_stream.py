"""Use case: stream a result to a device (`crtraj stream`): read it, admit it, send its set-points.

Reading goes through `crtraj.io.results.read_result`, the refusals through
`crtraj.hardware.admission.admit` (a failed, colliding, ``--no-safety`` or
scene-less result, one for another robot, set-points that fail the check as
sent, `crtraj.hardware.verify`, e.g. a slowed replay that meets a moving
obstacle), the sending through `crtraj.hardware.stream.Streamer`, which
streams only admitted motions. ``--approach`` injects the planned approach
(`crtraj.app.devices.plan_approach`) into the streamer. A refusal before
anything is sent is one line on stderr and exit 1.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from crtraj.app.devices._approach import plan_approach
from crtraj.core.errors import AdmissionError, InputError
from crtraj.core.fileio import StagedFile, check_output_file, check_outputs_not_inputs
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion, admit
from crtraj.hardware.dynamixel import DEFAULT_BAUD, HomingState, homing_command, read_homing, read_stop, state_path
from crtraj.hardware.setpoints import check_time_scale
from crtraj.hardware.stream import Streamer, StreamOptions, StreamReport, open_link
from crtraj.hardware.transport import parse_hostport
from crtraj.io.problem import Problem, load_robot
from crtraj.io.results import Result, read_result
from crtraj.planning.body import body_mismatch


def admit_result(
    result: Mapping[str, Any] | str | Path | Result,
    robot_file: str | Path | None = None,
    *,
    time_scale: float = 1.0,
    rate: float = 100.0,
) -> AdmittedMotion:
    """Read a result and admit its motion for a device (one-line `InputError` / `AdmissionError` otherwise).

    robot_file: the device's robot TOML whose ``[robot.actuators]`` are used
    (default: the result's own robot, which must then have them).
    time_scale: play the motion this many times slower. rate: the stream rate (Hz) its set-points are
    verified at.
    """
    device = None
    if robot_file is not None:  # the flag's file first: a bad --robot is named before the result is read
        device = load_robot(robot_file)
        if device.actuators is None:
            raise InputError(f"{robot_file}: robot.actuators: missing; add a [robot.actuators] table")
    res = read_result(result)
    device = res.robot if device is None else device
    if device.actuators is None:
        raise InputError(
            "robot.actuators: the result's robot has no [robot.actuators]; pass --robot problems/robots/cdsr2.toml"
        )
    why = body_mismatch((res.data.get("options") or {}).get("body"), device)
    if why is not None:  # a rod plan's commanded cable lengths hold only for the mechanics it was planned with
        raise AdmissionError(f"{res.source or 'result'}: {why}")
    actuators = Actuators.from_robot(device)
    # the robot's other hardware tables are read whatever the transport: a typo in them is named now, not at
    # the first stream to servos that reads them
    read_homing(device, actuators)
    read_stop(device)
    return admit(res.motion_record(), actuators, robot=device, time_scale=time_scale, rate=rate)


def _target(args: argparse.Namespace, frames: StagedFile | None) -> str:
    """The transport URL of --udp, --serial, --dynamixel or the staged --dry-run file."""
    if args.udp is not None:
        host, port = parse_hostport(args.udp, "--udp")
        return f"udp://{host}:{port}"
    if args.serial is not None:
        return f"serial://{_given(args.serial, '--serial')}?baud={args.baud or 115200}"
    if getattr(args, "dynamixel", None) is not None:
        return f"dynamixel://{_given(args.dynamixel, '--dynamixel')}?baud={args.baud or DEFAULT_BAUD}"
    if frames is None:
        raise InputError("stream: give one of --udp, --serial, --dry-run or --dynamixel")
    return f"file://{frames.path.resolve()}"


def _given(value: str, flag: str) -> str:
    """`value` of `flag`; an empty one is an error (it would otherwise read as "no device")."""
    if not value:
        raise InputError(f"{flag}: must not be empty")
    return value


def _homing(args: argparse.Namespace, motion: AdmittedMotion) -> dict[str, Any]:
    """The absolute-position check of a ``--dynamixel`` stream (the homing state beside ``--robot``; none
    without it: a multi-turn actuator is then refused, naming the command that homes it) and what happens
    to the torque after a stop (``[robot.stop]``)."""
    if getattr(args, "dynamixel", None) is None:
        return {}
    # the file itself (the link records where it lets each servo go), else no state
    state = state_path(args.robot) if args.robot else HomingState()
    return {
        "homing": state,
        "home_command": homing_command(args.robot, args.dynamixel),
        "stop_torque": (stop := read_stop(load_robot(args.robot) if args.robot else motion.robot)).torque,
        "bus_watchdog": stop.bus_watchdog,
    }


def stream_motion(args: argparse.Namespace, motion: AdmittedMotion, opts: StreamOptions, log: Path) -> StreamReport:
    """Open the transport and stream; a dry run's frames replace FILE only when the stream completes."""
    # the frames go to a temporary file that replaces FILE only when the stream completes:
    # a refused or failed dry run leaves FILE as it was
    dry_run = None if args.dry_run is None else _given(args.dry_run, "--dry-run")
    frames = StagedFile(check_output_file(dry_run, "--dry-run")) if dry_run is not None else None
    # the log is a journal, written as the stream goes (a crash keeps its lines); an existing log is replaced
    # only by the log of a stream that ended (not by an interrupted one: crtraj.core.interrupt)
    staged_log = StagedFile(log) if Path(log).exists() else None
    with frames or contextlib.nullcontext(), staged_log or contextlib.nullcontext():
        transport = open_link(_target(args, frames), motion.actuators, **_homing(args, motion))
        if args.approach and not transport.has_telemetry:
            transport.close()
            raise InputError(
                "--approach: this link reports no device position to approach from (a --dry-run has none); "
                "use --udp, --serial or --dynamixel"
            )
        to = f"file://{Path(args.dry_run).resolve()}" if frames is not None else transport.description
        path = motion.path
        n = round(path.duration * opts.rate) + 1
        what = f"{len(path.t)} waypoints" if path.slopes is None else f"B-spline of {len(path.t) - 2} executed samples"
        print(
            f"streaming {args.result} ({what}, {path.duration:.2f} s, ~{n} set-points at {opts.rate:g} Hz) to {to}",
            flush=True,
        )
        streamer = Streamer(transport, motion.actuators, opts, log if staged_log is None else staged_log.path)
        rep = streamer.run_path(motion, approach=args.approach, plan_approach=plan_approach)
        if frames is not None and rep.ok:
            frames.commit()
        if staged_log is not None:
            rep = dataclasses.replace(rep, log=str(staged_log.commit()))
    return rep


def print_report(rep: StreamReport, dry_run: str | None) -> None:
    dev = ", ".join(f"{k} {v}" for k, v in rep.device.items())
    fe = "" if rep.final_error is None else f", final error {rep.final_error:.3g}"
    print(f"{rep.status}: {rep.message}")
    print(
        f"  {rep.frames} frames ({rep.moves} move, {rep.holds} hold, {rep.estops} e-stop) in {rep.duration:.2f} s; "
        f"telemetry {rep.telemetry} ({rep.telemetry_errors} bad){fe}"
    )
    if dev:
        print(f"  device: {dev}")
    v, a = rep.max_velocity_fraction, rep.max_acceleration_fraction
    if v is not None and a is not None:
        print(
            f"  sent: actuators at most {v:.2f} of their velocity limit and {a:.2f} of their acceleration limit "
            "(every frame, stops included)"
        )
    if rep.brakes or rep.latched:
        print(f"  stop: {rep.brakes} planned stop(s) in {rep.brake_frames} frames; {rep.latched} latched")
    if rep.late_ticks:
        print(f"  {rep.late_ticks} ticks late (max {rep.max_lateness * 1000:.1f} ms)")
    print(f"  log: {rep.log}")
    if dry_run and rep.ok:
        print(f"  frames: {dry_run} (COBS + 0x00 delimited, see docs/protocol.md)")
    elif dry_run:
        print(f"  frames: none written ({dry_run} left as it was: the stream did not complete)")


def stream_command(args: argparse.Namespace) -> int:
    """`crtraj stream RESULT ...` (arguments from `crtraj.cli`); returns the exit code."""
    check_time_scale(args.time_scale)
    opts = Problem.load(args.problem).options(StreamOptions, "stream") if args.problem else StreamOptions()
    over = {k: v for k, v in (("rate", args.rate), ("watchdog", args.watchdog)) if v is not None}
    opts = dataclasses.replace(opts, **over)
    log = args.log or Path("out") / "stream" / f"{Path(args.result).stem}-{time.strftime('%Y%m%d-%H%M%S')}.jsonl"
    # outputs are checked before the result is admitted (the long part): a log or frames file that is one
    # of the inputs would destroy it
    check_outputs_not_inputs(
        {"--log": log, "--dry-run": args.dry_run},
        {"RESULT": args.result, "--robot": args.robot, "--problem": args.problem},
    )
    check_output_file(log, "--log")
    motion = admit_result(args.result, args.robot, time_scale=args.time_scale, rate=opts.rate)
    rep = stream_motion(args, motion, opts, Path(log))
    if rep.status == "refused" and rep.moves == 0:  # refused before anything was sent: one line, exit 1
        raise AdmissionError(f"{args.result}: {rep.message}")
    print_report(rep, args.dry_run)
    if not rep.ok:
        print(f"crtraj: stream failed: {failure_line(rep)}", file=sys.stderr)
    return 0 if rep.ok else 1


def failure_line(rep: StreamReport) -> str:
    """Why a stream did not complete, on one line: its status, its message and where its record is."""
    return " ".join(f"{rep.status}: {rep.message} (log {rep.log})".split())
