"""The ``crtraj`` command.

Each subcommand is a small function that parses its arguments, calls the
library, prints a short summary and returns an exit code. One rule for every
command: user input errors (malformed files, flags, output paths; `InputError`)
print one line ``crtraj: error: ...`` and exit 2, before any long work; a
well-formed task that cannot be solved (invalid_start, invalid_goal, timeout,
collision, ...) exits 1, prints its status and one stderr line
``crtraj: <command> failed: <status>: ...``. Outputs are staged and renamed
into place (`crtraj.core.fileio`); a failed result never replaces a successful one
at the same --out unless --overwrite-failed: it goes beside it (NAME.failed).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from crtraj import __version__
from crtraj.app.replan import ReplanRequest, run_replan
from crtraj.core.errors import InputError
from crtraj.core.fileio import (
    StagedFile,
    check_output_file,
    failed_sibling,
    is_successful_result,
)
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import check_replay_time_scale
from crtraj.hardware.transport import TransportError

DEFAULT_ROBOT = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"


def _resolve_robot(arg: str | None) -> Path:
    if arg:
        return Path(arg)
    return DEFAULT_ROBOT


# --------------------------------------------------------------------- export
def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write the symbolic model as .casadi files, C source and a shared library",
        description="Export every model function (FK, backbone, Jacobians, cable maps, limits) "
        "as CasADi .casadi files, generated C, a compiled library and manifest.json.",
    )
    p.add_argument("--robot", help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument("--out", default="out/export", help="output folder (default: out/export)")
    p.add_argument(
        "--points", type=int, default=None, help="backbone points, 2..1000 (default: robot.collision_points)"
    )
    p.add_argument(
        "--batch", type=int, default=1024, help="configurations per backbone_map call, 1..1000000 (default 1024)"
    )
    p.add_argument("--no-compile", action="store_true", help="write C source only, do not compile")
    p.set_defaults(func=_cmd_export)


def _cmd_export(args: argparse.Namespace) -> int:
    from crtraj.io.problem import load_robot
    from crtraj.model.export import export_model
    from crtraj.model.kinematics import MAX_BATCH, MAX_POINTS, Model

    # sizes first: a huge --batch or --points would build (or allocate) for minutes before failing
    if not 1 <= args.batch <= MAX_BATCH:
        raise InputError(f"--batch: must be in [1, {MAX_BATCH}], got {args.batch}")
    if args.points is not None and not 2 <= args.points <= MAX_POINTS:
        raise InputError(f"--points: must be in [2, {MAX_POINTS}], got {args.points}")
    robot = load_robot(_resolve_robot(args.robot))
    model = Model(robot, n_points=args.points)
    rep = export_model(model, args.out, batch=args.batch, compile=not args.no_compile)
    print(f"exported robot '{robot.name}' ({robot.n_segments} segments, {model.n_points} points) to {rep.out_dir}")
    print(f"  {len(rep.casadi_files)} .casadi files, C source {rep.c_source.name}")
    print(f"  library: {rep.library.name if rep.library else 'none'} ({rep.compiler_message})")
    print(f"  manifest: {rep.out_dir / 'manifest.json'}")
    return 0


# ----------------------------------------------------------------------- view
def _add_view(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="replay a plan/replan result in the browser (meshcat) or write it as standalone HTML",
        description="Draw the robot, obstacles, start, goal, planned path, planner tree and executed trail of "
        "a result file and replay the run with meshcat's time slider. Without --html, serves the page on "
        "127.0.0.1 until Ctrl-C.",
    )
    p.add_argument("result", help="result JSON written by crtraj plan or crtraj replan")
    p.add_argument("--html", metavar="FILE", help="write one self-contained HTML file (no server needed) and exit")
    p.add_argument("--no-browser", action="store_true", help="do not open a browser tab, only print the URL")
    p.add_argument("--no-play", action="store_true", help="do not start the animation when the page opens")
    p.set_defaults(func=_cmd_view)


def _cmd_view(args: argparse.Namespace) -> int:

    from crtraj.core.fileio import read_json
    from crtraj.viz.view import Visualizer

    result = read_json(args.result)
    play = False if args.no_play else None
    if args.html:
        vis = Visualizer.for_result(result, play=play)
        path = vis.save_html(args.html)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); open it in any browser, no server needed")
        return 0
    return _serve(result, str(args.result), not args.no_browser, play)


def _serve(result: dict, label: str, open_browser: bool, play: bool | None = None) -> int:
    """Serve a result in the meshcat view on 127.0.0.1 until Ctrl-C; returns 0."""
    import time

    from crtraj.viz.view import Visualizer

    try:  # Ctrl-C is the normal way out, whenever it comes; leaving the block stops the server
        with Visualizer.for_result(result, server=True, play=play) as vis:
            # for_result has validated the result, so its waypoints exist
            what = f"{result.get('kind', 'plan')}, {len(result['waypoints'])} waypoints"
            print(f"serving {label} ({what}) at {vis.url}", flush=True)
            if open_browser:
                vis.open()
            print("press Ctrl-C to stop", flush=True)
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        print("stopped", flush=True)
    return 0


# --------------------------------------------------------------------- stream
def _add_stream(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stream",
        help="stream a planned trajectory to the robot's servos (UDP, serial or a dry-run file)",
        description="Convert the result's waypoint actuation q(t) to servo angles and stage positions "
        "([robot.actuators]), interpolate it at a fixed rate and send time-stamped set-points. Every frame is "
        "checked against the position, velocity and acceleration limits before it leaves; a violation is "
        "refused, never clamped. A watchdog holds when telemetry stops. Every run is recorded as JSON lines.",
    )
    p.add_argument("result", help="result JSON written by crtraj plan or crtraj replan")
    dest = p.add_mutually_exclusive_group(required=True)
    dest.add_argument("--udp", metavar="HOST:PORT", help="device address (e.g. 127.0.0.1:9870 for crtraj sim-device)")
    dest.add_argument("--serial", metavar="DEV", help="serial port (e.g. /dev/ttyUSB0), COBS-framed frames")
    dest.add_argument("--dry-run", metavar="FILE", help="write the frames to FILE instead of a device (no waiting)")
    p.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    p.add_argument("--rate", type=float, default=None, help="set-points per second (default 100)")
    p.add_argument("--watchdog", type=float, default=None, help="hold after this long without telemetry, s (0.1)")
    p.add_argument("--robot", help="robot TOML whose [robot.actuators] to use (default: the result's robot)")
    p.add_argument("--problem", help="problem TOML whose [stream] section sets the defaults")
    p.add_argument(
        "--time-scale", type=float, default=1.0, help="play the trajectory this many times slower (0.001..1000)"
    )
    p.add_argument(
        "--approach",
        action="store_true",
        help="first move from the device's position to the trajectory start (straight line in actuator space, "
        "not collision checked)",
    )
    p.add_argument("--log", help="run record (JSON lines; default out/stream/<result>-<time>.jsonl)")
    p.set_defaults(func=_cmd_stream)


def _cmd_stream(args: argparse.Namespace) -> int:
    import dataclasses
    import time

    from crtraj.core.fields import Table
    from crtraj.core.fileio import read_json
    from crtraj.hardware.setpoints import SetpointPath, check_time_scale
    from crtraj.hardware.stream import Streamer, StreamOptions
    from crtraj.hardware.transport import Transport, parse_hostport
    from crtraj.io.problem import Problem, load_robot
    from crtraj.model.robot import Robot

    check_time_scale(args.time_scale)
    result = read_json(args.result)
    if not isinstance(result, dict) or not isinstance(result.get("robot"), dict):
        raise InputError(f"{args.result}: robot: missing (is this a crtraj plan/replan result?)")
    robot = Robot.from_table(Table(result["robot"], "robot"))
    source = robot
    if args.robot:
        source = load_robot(args.robot)
        if source.actuators is None:
            raise InputError(f"{args.robot}: robot.actuators: missing; add a [robot.actuators] table")
    if source.actuators is None:
        raise InputError(
            "robot.actuators: the result's robot has no [robot.actuators]; pass --robot problems/robots/cdsr2.toml"
        )
    actuators = Actuators.from_robot(source).for_robot(robot)
    opts = Problem.load(args.problem).options(StreamOptions, "stream") if args.problem else StreamOptions()
    over = {k: v for k, v in (("rate", args.rate), ("watchdog", args.watchdog)) if v is not None}
    opts = dataclasses.replace(opts, **over)
    check_replay_time_scale(result, args.time_scale)
    path = SetpointPath.from_result(result, actuators).scaled(args.time_scale)
    log = args.log or Path("out") / "stream" / f"{Path(args.result).stem}-{time.strftime('%Y%m%d-%H%M%S')}.jsonl"
    _refuse_overwriting_input(args.result, ("--log", log), ("--dry-run", args.dry_run))
    frames = None
    if args.udp is not None:
        host, port = parse_hostport(args.udp, "--udp")
        target = f"udp://{host}:{port}"
    elif args.serial:
        target = f"serial://{args.serial}?baud={args.baud}"
    else:
        # the frames go to a temporary file that replaces FILE only when the stream completes:
        # a refused or failed dry run leaves FILE as it was
        frames = StagedFile(check_output_file(args.dry_run, "--dry-run"))
        target = f"file://{frames.path.resolve()}"
    with frames or contextlib.nullcontext():
        transport = Transport.open(target, baud=args.baud)
        to = f"file://{Path(args.dry_run).resolve()}" if frames is not None else transport.description
        n = round(path.duration * opts.rate) + 1
        print(
            f"streaming {args.result} ({len(path.t)} waypoints, {path.duration:.2f} s, ~{n} set-points at "
            f"{opts.rate:g} Hz) to {to}",
            flush=True,
        )
        rep = Streamer(transport, actuators, opts, log).run_path(path, approach=args.approach)
        if frames is not None and rep.ok:
            frames.commit()
    dev = ", ".join(f"{k} {v}" for k, v in rep.device.items())
    fe = "" if rep.final_error is None else f", final error {rep.final_error:.3g}"
    print(f"{rep.status}: {rep.message}")
    print(
        f"  {rep.frames} frames ({rep.moves} move, {rep.holds} hold, {rep.estops} e-stop) in {rep.duration:.2f} s; "
        f"telemetry {rep.telemetry} ({rep.telemetry_errors} bad){fe}"
    )
    if dev:
        print(f"  device: {dev}")
    if rep.late_ticks:
        print(f"  {rep.late_ticks} ticks late (max {rep.max_lateness * 1000:.1f} ms)")
    print(f"  log: {rep.log}")
    if args.dry_run and rep.ok:
        print(f"  frames: {args.dry_run} (COBS + 0x00 delimited, see docs/protocol.md)")
    elif args.dry_run:
        print(f"  frames: none written ({args.dry_run} left as it was: the stream did not complete)")
    return 0 if rep.ok else 1


def _refuse_overwriting_input(result: str, *outputs: tuple[str, Any]) -> None:
    """An output path that is the input result (or an earlier output) would destroy it: refuse, one line."""
    seen = {"RESULT": Path(result)}
    for flag, out in outputs:
        if out is None:
            continue
        for name, other in seen.items():
            try:
                same = os.path.samefile(out, other) if Path(out).exists() and other.exists() else False
            except OSError:
                same = False
            if same or Path(out).resolve() == other.resolve():
                raise InputError(f"{flag}: {out} is the same file as {name}; choose another file")
        seen[flag] = Path(out)


# ----------------------------------------------------------------- sim-device
def _add_sim_device(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim-device",
        help="run a simulated servo controller on 127.0.0.1 that speaks the stream protocol",
        description="A device for testing crtraj stream without hardware: checks CRC and sequence numbers, "
        "models each servo as a first-order lag, enforces the actuator limits itself, sends telemetry, and "
        "injects faults on request. Runs until Ctrl-C or --duration.",
    )
    p.add_argument("--udp", metavar="127.0.0.1:PORT", required=True, help="address to listen on (port 0: any)")
    p.add_argument("--robot", help="robot TOML with [robot.actuators] (default: problems/robots/cdsr2.toml)")
    p.add_argument("--tau", type=float, default=0.03, help="servo time constant, s (default 0.03)")
    p.add_argument("--telemetry-rate", type=float, default=100.0, help="telemetry frames per second (100)")
    p.add_argument("--drop", type=float, default=0.0, help="probability of dropping each datagram (both ways)")
    p.add_argument("--corrupt", type=float, default=0.0, help="probability of flipping bits in each datagram")
    p.add_argument("--delay", type=float, default=0.0, help="extra latency of incoming frames, s")
    p.add_argument("--disconnect-after", type=float, default=0.0, help="go silent and deaf after this many s")
    p.add_argument("--disconnect-for", type=float, default=0.0, help="... for this many s (0: never disconnect)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault generator")
    p.add_argument("--duration", type=float, default=None, help="stop after this many s (default: until Ctrl-C)")
    p.set_defaults(func=_cmd_sim_device)


def _cmd_sim_device(args: argparse.Namespace) -> int:
    from crtraj.hardware.sim_device import Faults, SimDevice
    from crtraj.hardware.transport import parse_hostport
    from crtraj.io.problem import load_robot

    host, port = parse_hostport(args.udp, "--udp")
    robot = load_robot(_resolve_robot(args.robot))
    if robot.actuators is None:
        raise InputError(f"{_resolve_robot(args.robot)}: robot.actuators: missing; add a [robot.actuators] table")
    faults = Faults(args.drop, args.corrupt, args.delay, args.disconnect_after, args.disconnect_for)
    actuators = Actuators.from_robot(robot)
    dev = SimDevice(
        actuators, port, host=host, tau=args.tau, telemetry_rate=args.telemetry_rate, faults=faults, seed=args.seed
    )
    print(
        f"sim-device listening on {dev.url} ({actuators.n} actuators: {', '.join(actuators.names)}; "
        f"tau {args.tau:g} s)",
        flush=True,
    )
    try:
        dev.serve(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        st = dev.state()
        dev.stop()
    counts = ", ".join(f"{k} {st[k]}" for k in ("received", "applied", "crc_errors", "missed", "stale", "refused"))
    print(f"sim-device stopped: {counts}", flush=True)
    return 0


# ----------------------------------------------------------------------- plan
def _add_plan(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        help="plan a collision-free motion from the task's start to its goal (paper simulation 1)",
        description="Plan the problem's task among its scene's obstacles and write a result JSON (per waypoint: "
        "time, tip, configuration, cable lengths, backbone points, obstacles; the search tree). Planners: "
        "cspace (default: safe goal IK + RRT-Connect in configuration space), rrt and rrtstar (the paper's "
        "Algorithm 1 over tip positions with the safety-constrained steer).",
    )
    p.add_argument("problem", help="problem TOML (e.g. problems/paper_static.toml)")
    p.add_argument("--planner", choices=("cspace", "rrt", "rrtstar"), default=None, help="default: [planner] algorithm")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the problem's seed)")
    p.add_argument("--time-limit", type=float, default=None, help="planning time budget in s (default: [planner])")
    p.add_argument("--out", default=None, help="result JSON (default: out/plan-<name>.json)")
    p.add_argument(
        "--html", default=None, help="also write the standalone 3-D view to this HTML file (successful plans only)"
    )
    p.add_argument(
        "--overwrite-failed",
        action="store_true",
        help="let a failed plan replace a successful result at --out (default: it is written beside it, "
        "as NAME.failed.json)",
    )
    p.add_argument("--view", action="store_true", help="afterwards, serve the 3-D view on 127.0.0.1 until Ctrl-C")
    p.add_argument("--no-browser", action="store_true", help="with --view: only print the URL")
    p.set_defaults(func=_cmd_plan)


def _cmd_plan(args: argparse.Namespace) -> int:
    import math

    from crtraj.app.plan import plan_problem
    from crtraj.io.problem import Problem

    if args.seed is not None and args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.time_limit is not None and not (math.isfinite(args.time_limit) and args.time_limit > 0):
        raise InputError(f"--time-limit: must be a number > 0 (s), got {args.time_limit}")
    problem = Problem.load(args.problem)
    out = Path(args.out) if args.out else Path("out") / f"plan-{problem.name}.json"
    check_output_file(out, "--out")  # before the (possibly long) plan, not after it
    if args.html:
        check_output_file(args.html, "--html")
        if Path(args.html).resolve() == out.resolve():
            raise InputError(f"--html: {args.html} is the same file as --out; choose another file")
    run = plan_problem(problem, algorithm=args.planner, seed=args.seed, time_limit=args.time_limit)
    r = run.result
    doc = run.document()
    # a failed plan never replaces a successful one unless asked: it goes beside it
    dest = out
    if not r.is_success() and not args.overwrite_failed and is_successful_result(out):
        dest = failed_sibling(out)
    with contextlib.ExitStack() as stack:
        staged = [stack.enter_context(StagedFile(dest))]
        staged[0].write((json.dumps(doc, indent=1, allow_nan=False) + "\n").encode("utf-8"))
        if args.html and r.is_success():
            from crtraj.viz.view import Visualizer

            vis = Visualizer.for_result(doc)
            try:
                html = vis.static_html()
            finally:
                vis.close()
            staged.append(stack.enter_context(StagedFile(args.html)))
            staged[1].write(html.encode("utf-8"))
        for f in staged:  # both complete before either replaces anything
            f.commit()
    print(f"{problem.name}: {r.status} with {r.planner} (seed {r.seed}) in {r.timings.get('total', 0.0) * 1e3:.1f} ms")
    print(f"  {r.message}")
    if r.has_path:
        print(
            f"  tip path {r.length:.1f} mm over {r.duration:.2f} s, {len(r.t)} waypoints, "
            f"min clearance {r.min_clearance:.2f} mm (beyond D_sf {run.scene.safety_distance:g} mm), "
            f"goal error {r.goal_error:.3f} mm"
        )
    if run.timing is not None and r.has_path:
        tm = run.timing
        print(
            f"  executed {tm['executed_duration_s']:.2f} s ({tm.get('outcome', '')}); largest actuator velocity "
            f"{tm['max_velocity_fraction']:.2f}, acceleration {tm['max_acceleration_fraction']:.2f} of the limits"
        )
    steps = ", ".join(f"{k} {v * 1e3:.1f}" for k, v in r.timings.items() if k != "total")
    print(f"  time (ms): {steps}; setup {run.setup_time * 1e3:.0f} ms")
    if dest != out:
        print(f"  wrote {dest} (failed; {out} holds a successful plan and was kept: --overwrite-failed replaces it)")
    else:
        print(f"  wrote {dest}")
    if args.html:
        print(f"  wrote {args.html}" if r.is_success() else f"  no HTML written: the plan failed ({r.status})")
    if r.is_success() and args.view:
        _serve(doc, str(out), not args.no_browser)
    elif args.view:
        print(f"  not viewed: the plan failed ({r.status})")
    if not r.is_success():
        print(f"crtraj: plan failed: {r.status}: {r.message} (result in {dest})", file=sys.stderr)
    return 0 if r.is_success() else 1


# --------------------------------------------------------------------- replan
def _add_replan(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replan",
        help="run the receding-horizon replanner in closed loop among moving obstacles (paper simulation 2)",
        description="Simulate the robot from the task's start to its goal among the scene's moving, breathing "
        "obstacles: a horizon NLP (the [replan] section) re-solved every step from the measured configuration ([loop]: "
        "duration, reference timing, verification), "
        "a reference path re-planned when needed, the tracking controller and servo model ([tracking]), and "
        "every applied move verified densely in time. Writes run.json, run.npz, run.png (body-obstacle "
        "distance and tip error over time) and run.html (standalone 3-D replay) into --out.",
    )
    p.add_argument("problem", help="problem TOML (e.g. problems/paper_dynamic.toml)")
    p.add_argument("--out", help="output folder (default out/replan, or out/replan-no-safety with --no-safety)")
    p.add_argument("--seed", type=int, default=None, help="random seed of the planner (default: the problem's)")
    p.add_argument(
        "--no-safety",
        action="store_true",
        help="switch the collision-free terms off (NLP constraints, move verification, obstacles in the reference "
        "planner), as in the paper's Fig. 4(b): the body then runs into the obstacles",
    )
    p.add_argument("--no-html", action="store_true", help="do not write run.html")
    p.add_argument(
        "--overwrite-failed",
        action="store_true",
        help="let a failed run replace a successful one in --out (default: it is written beside it, as OUT.failed)",
    )
    p.add_argument(
        "--feed",
        metavar="udp://127.0.0.1:PORT",
        help="take the obstacle states live from a UDP JSON feed (crtraj.world.feed; ids = the scene's obstacle names) "
        "and run in real time, predicting each obstacle at constant velocity",
    )
    p.add_argument("--feed-max-age", type=float, default=0.2, help="with --feed: hold when a state is older, s (0.2)")
    p.add_argument(
        "--stream",
        metavar="udp://HOST:PORT",
        help="drive a device ([robot.actuators] in the robot file, [stream] section). Without --feed: after the "
        "simulation, stream the verified run (as crtraj stream does). With --feed: live, while the loop runs - "
        "the run starts where the device is, each step's verified motion is streamed as it is chosen (one "
        "[stream] prebuffer, at least one replan step, ahead of the device; the feed is predicted that far "
        "ahead), the device's telemetry is the measured configuration, a held step or a stale feed holds the "
        "device, an unsafe step e-stops it, Ctrl-C holds it; the device then settles at the run's final "
        "actuation",
    )
    p.add_argument(
        "--approach",
        action="store_true",
        help="with --stream: first move from the device's position to the run's start (not collision checked); "
        "with --feed and --stream: start the live run from the device's position even when it is not the task's "
        "start (every move from there is verified; without it such a device is refused)",
    )
    p.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        help="with --stream, without --feed: play the run this many times slower, 0.001..1000 (the device's "
        "acceleration limits may need it)",
    )
    p.add_argument("--view", action="store_true", help="afterwards, serve the 3-D replay on 127.0.0.1 until Ctrl-C")
    p.add_argument("--no-browser", action="store_true", help="with --view: only print the URL")
    p.add_argument("--quiet", action="store_true", help="print only the summary line")
    p.set_defaults(func=_cmd_replan)


def _cmd_replan(args: argparse.Namespace) -> int:
    req = ReplanRequest(
        problem=Path(args.problem),
        out=Path(args.out) if args.out else None,
        seed=args.seed,
        safety=not args.no_safety,
        html=not args.no_html,
        overwrite_failed=args.overwrite_failed,
        feed=args.feed,
        feed_max_age=args.feed_max_age,
        stream=args.stream,
        approach=args.approach,
        time_scale=args.time_scale,
        quiet=args.quiet,
    )
    view = (lambda result: _serve(result, "the run", not args.no_browser)) if args.view else None
    return run_replan(req, view=view)


# ---------------------------------------------------------------------- bench
def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="run the paper's Table I benchmark against the paper and OMPL",
        description="table1: RRT, RRT* (the paper's Algorithm 1), crtraj's configuration-space planner and "
        "OMPL's RRTstar and RRTConnect on the same random dynamic scenes (paper sec. IV-B) with the same "
        "validity checker and time budget; every success is re-verified densely. Writes DIR/table1.md "
        "(the paper's layout, with the paper's numbers), DIR/runs.csv (every run) and DIR/scenarios.json.",
    )
    p.add_argument("table", choices=["table1"], help="which benchmark (table1: the paper's Table I)")
    p.add_argument(
        "--workers", type=int, default=None, help="worker processes (default: CPU count; 0 = run in this process)"
    )
    p.add_argument("--scenarios", type=int, default=100, help="scenarios per obstacle count (default 100)")
    p.add_argument("--counts", default="1,3,5,7", help="obstacle counts, comma-separated (default 1,3,5,7)")
    p.add_argument(
        "--planners",
        default=None,
        help="comma-separated subset of rrt,rrtstar,cspace,ompl-rrtstar,ompl-rrtconnect (default: all)",
    )
    p.add_argument("--time-limit", type=float, default=5.0, help="wall-time budget per run, s (default 5)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scenarios and runs (default 0)")
    p.add_argument("--out", default="out/table1", help="output folder (default: out/table1)")
    p.add_argument(
        "--dask",
        metavar="ADDRESS",
        default=None,
        help="run on a Dask distributed scheduler (e.g. tcp://127.0.0.1:8786) instead of processes",
    )
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument("--planner-config", default=None, help="TOML file with a [planner] table shared by all planners")
    p.add_argument(
        "--verify-margin",
        type=float,
        default=0.0,
        help="clearance (mm) the dense check demands from the sphere surfaces (default 0: no contact)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(args: argparse.Namespace) -> int:
    from crtraj.app.bench import run_table1

    return run_table1(args)


# Subcommands register themselves here in display order.
_COMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    _add_export,
    _add_view,
    _add_stream,
    _add_sim_device,
    _add_plan,
    _add_replan,
    _add_bench,
)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``crtraj: error: ...``, exit 2) like every other crtraj error;
    subcommand parsers inherit it. `--help` still prints the usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"crtraj: error: {_one_line(message)} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="crtraj",
        description="Safety-constrained motion planning for cable-driven continuum robots.",
    )
    parser.add_argument("--version", action="version", version=f"crtraj {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(sub)
    return parser


def _one_line(exc: BaseException, width: int = 1000) -> str:
    """An error message as exactly one line: a message quoting a file name or value with a newline or
    control character in it must not spill onto a second line."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in " ".join(str(exc).splitlines()))
    return text if len(text) <= width else text[: width - 3] + "..."


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"crtraj: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except TransportError as exc:  # the device or port, not the input: a run-time failure
        print(f"crtraj: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("crtraj: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
