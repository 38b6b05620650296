"""The ``crtraj`` command.

This package holds the argument parsers (the calibration and mechanics commands in
`crtraj.cli.lab`, the commands that talk to a device or simulate one in `crtraj.cli.devices`); each
command's work is a use case in `crtraj.app` (`_USE_CASES`) that calls the library, prints a short summary and
returns an exit code. One rule for every command: user input errors (malformed
files, flags, output paths; `InputError`) print one line ``crtraj: error: ...``
and exit 2, before any long work; a readable result that admission refuses to
send to a device (`AdmissionError`: failed, colliding, ``--no-safety``, another
robot, ...) prints one such line and exits 1; a well-formed task that cannot be
solved (invalid_start, invalid_goal, timeout, collision, ...) exits 1, prints
its status and one stderr line ``crtraj: <command> failed: <status>: ...``. Outputs are staged and renamed
into place (`crtraj.core.fileio`); a failed result never replaces a successful one
at the same --out unless --overwrite-failed: it goes beside it (NAME.failed).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from crtraj import __version__
from crtraj.cli.devices import (
    add_feed_replay,
    add_home,
    add_ros_bridge,
    add_sim_device,
    add_sim_dynamixel,
    add_stream,
)
from crtraj.cli.lab import add_calibrate, add_model, add_record, add_verify
from crtraj.cli.paths import DEFAULT_ROBOT
from crtraj.core import interrupt
from crtraj.core.errors import AdmissionError, InputError
from crtraj.core.flags import strict_flag_types
from crtraj.core.logs import configure_logging
from crtraj.hardware.transport import TransportError

__all__ = ["build_parser", "main"]

# Every command's work is a use case in crtraj.app, named here as "module:function" and imported
# only when its command runs (`_use_case`): importing them all at start-up would load CasADi,
# SciPy, matplotlib and meshcat for every command, even `crtraj --help` (seconds, not 0.2 s).
_USE_CASES = {
    "export": "crtraj.app.export:export_command",
    "view": "crtraj.app.view:view_command",
    "serve": "crtraj.app.view:serve",
    "stream": "crtraj.app.devices:stream_command",
    "sim-device": "crtraj.app.devices:sim_device_command",
    "feed-replay": "crtraj.app.devices:feed_replay_command",
    "sim-dynamixel": "crtraj.app.devices:sim_dynamixel_command",
    "home": "crtraj.app.devices:home_command",
    "plan": "crtraj.app.plan:plan_command",
    "replan": "crtraj.app.replan:replan_command",
    "bench": "crtraj.app.bench:bench_command",
    "record": "crtraj.app.lab:record_command",
    "calibrate": "crtraj.app.lab:calibrate_command",
    "build": "crtraj.app.build:build_command",
    "ros-bridge": "crtraj.app.devices:ros_bridge_command",
    "model-compare": "crtraj.app.lab:model_compare_command",
    "verify": "crtraj.app.lab:verify_command",
}


def _use_case(name: str) -> Callable[..., Any]:
    """The use-case function of command `name` (`_USE_CASES`), imported now."""
    module, func = _USE_CASES[name].split(":")
    return getattr(importlib.import_module(module), func)


# --------------------------------------------------------------------- export
def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write the symbolic model as .casadi files, C source and a shared library",
        description="Export every model function (FK, backbone, Jacobians, cable maps, limits) "
        "as CasADi .casadi files, generated C, a compiled library and manifest.json.",
    )
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument("--out", default="out/export", help="output folder (default: out/export)")
    p.add_argument(
        "--points", type=int, default=None, help="backbone points, 2..1000 (default: robot.collision_points)"
    )
    p.add_argument(
        "--batch", type=int, default=1024, help="configurations per backbone_map call, 1..1000000 (default 1024)"
    )
    p.add_argument("--no-compile", action="store_true", help="write C source only, do not compile")
    p.set_defaults(use_case="export")


# ---------------------------------------------------------------------- build
def _add_build(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "build",
        help="build a robot's compiled collision-check kernels ahead of time (or list/clear the build cache)",
        description="Generate and compile the C kernels every command would otherwise build on first use, into "
        "the build cache ($CRTRAJ_CACHE_DIR, else the user cache directory). Kernels are keyed by the robot's "
        "kinematics, the check points, CasADi, Python, the platform and the C compiler, and reused by every "
        "command. Without a C compiler crtraj runs interpreted (exit 1 here).",
    )
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument(
        "--check-points",
        type=int,
        action="append",
        metavar="N",
        help="also build the kernel for N backbone check points, 2..200 (repeatable; crtraj's defaults are always "
        "built)",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument("--list", action="store_true", help="list the cache's entries (and whether each verifies)")
    g.add_argument("--clear", action="store_true", help="remove every entry crtraj made (nothing else is touched)")
    p.set_defaults(use_case="build")


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
    p.add_argument("compare", nargs="?", default=None, help="a second result of the same robot, drawn as a ghost")
    p.add_argument("--html", metavar="FILE", help="write one self-contained HTML file (no server needed) and exit")
    p.add_argument("--png", metavar="FILE", help="write a picture of the page at --at (headless Chromium) and exit")
    p.add_argument("--mp4", metavar="FILE", help="write a video of the run (headless Chromium and ffmpeg) and exit")
    p.add_argument("--at", type=float, default=None, help="time (s) of the --png picture (default: closest approach)")
    p.add_argument("--size", default="1280x800", help="WIDTHxHEIGHT in pixels of --png/--mp4 (default 1280x800)")
    p.add_argument("--fps", type=float, default=10.0, help="frames per second of --mp4 (default 10)")
    p.add_argument("--no-browser", action="store_true", help="do not open a browser tab, only print the URL")
    p.add_argument("--no-play", action="store_true", help="do not start the animation when the page opens")
    p.set_defaults(use_case="view")


# --------------------------------------------------------------------- stream
# ----------------------------------------------------------------- sim-device
# ---------------------------------------------------------------- feed-replay
# -------------------------------------------------------------- sim-dynamixel
# ----------------------------------------------------------------------- home
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
    p.set_defaults(use_case="plan")


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
    _add_replan_live(p)
    p.add_argument(
        "--view",
        action="store_true",
        help="serve the live 3-D page on 127.0.0.1 as the loop runs (up to 30 Hz), then its replay until Ctrl-C",
    )
    p.add_argument("--no-browser", action="store_true", help="with --view: only print the URL")
    p.add_argument("--quiet", action="store_true", help="print only the summary line")
    p.add_argument(
        "--true-robot",
        metavar="FILE",
        help="simulation: a robot file with the robot's real parameters (e.g. perturbed); a simulated motion-capture "
        "tip marker films it and the run reports the measured tip error; with --plant: the rod's robot file",
    )
    p.add_argument(
        "--tip-feedback",
        action="store_true",
        help="use the motion-capture tip as the loop's measurement: it corrects the remaining model error "
        "(needs --mocap-port, --true-robot or --plant)",
    )
    p.add_argument(
        "--plant",
        metavar="MODEL",
        help="simulation: the robot is a Cosserat rod (cosserat: with the robot file's gravity; cosserat-weightless); "
        "the loop still plans with PCC, the rod's shape is judged against the obstacles and its tip is measured",
    )
    p.add_argument(
        "--mocap-port",
        type=int,
        metavar="PORT",
        help="live runs (--feed, --stream): the capture's tip marker as UDP JSON on 127.0.0.1:PORT "
        '({"marker": "tip", "position": [x, y, z]} in mm, capture frame; the robot file\'s [calibration] maps it)',
    )
    p.set_defaults(use_case="replan")


def _add_replan_live(p: argparse.ArgumentParser) -> None:
    """The options of `crtraj replan` that connect it to the world: a live feed, a device, the approach."""
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
        help="drive a device ([robot.actuators] in the robot file, [stream] section): udp://HOST:PORT, "
        "serial://DEV?baud=N or dynamixel:///dev/ttyUSB0?baud=N (Dynamixel servos, ids in the robot file). "
        "Without --feed: after the simulation, stream the verified run (as crtraj stream does). "
        "With --feed: live, while the loop runs - "
        "the run starts where the device is, each step's verified motion is streamed as it is chosen (one "
        "[stream] prebuffer, at least one replan step, ahead of the device; the feed is predicted that far "
        "ahead), the device's telemetry is the measured configuration, a held step or a stale feed holds the "
        "device, an unsafe step e-stops it, Ctrl-C holds it; the device then settles at the run's final "
        "actuation",
    )
    p.add_argument(
        "--approach",
        action="store_true",
        help="with --stream: first move from the device's position to the run's start (planned and verified); "
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


# ----------------------------------------------------------------- ros-bridge
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
    p.add_argument(
        "table",
        choices=["table1", "suite", "modes"],
        help="which benchmark (table1: the paper's Table I; suite: the held-out dynamic suite, crtraj.bench.suite, "
        "run in this process: --counts, --workers, --dask, --planner-config and --verify-margin are table1's; "
        "modes: report finished table1 runs in both checking modes)",
    )
    p.add_argument(
        "--workers", type=int, default=None, help="worker processes (default: CPU count; 0 = run in this process)"
    )
    p.add_argument(
        "--scenarios", type=int, default=None, help="scenarios per obstacle count (default 100); suite: in all (20)"
    )
    p.add_argument("--counts", default="1,3,5,7", help="obstacle counts, comma-separated (default 1,3,5,7)")
    p.add_argument(
        "--planners",
        default=None,
        help="comma-separated subset of rrt,rrtstar,cspace,ompl-rrtstar,ompl-rrtconnect (default: all)",
    )
    p.add_argument("--time-limit", type=float, default=None, help="wall-time budget per planner run, s (default 5)")
    p.add_argument(
        "--replan-duration",
        type=float,
        default=30.0,
        help="suite: simulated time within which the closed-loop replanner must arrive, s (default 30)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the scenarios and runs (default 0)")
    p.add_argument("--out", default=None, help="output folder (default: out/table1, or out/suite)")
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
        default=None,
        help="clearance (mm) the dense check demands from the sphere surfaces (default: the scene's D_sf)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--scenes", choices=["default", "paper"], default="default", help="scene bounds (paper: mean speed U(0, 15))"
    )
    p.add_argument("--cpu-budget", action="store_true", help="time limit counts CPU time (rrt, rrtstar, cspace)")
    p.add_argument("--runs", default=None, help="modes: runs.csv file(s) to report, comma-separated")
    p.add_argument("--note", default=None, help="modes: a line added to the report's header (e.g. the load)")
    p.set_defaults(use_case="bench")


# Subcommands register themselves here in display order.
_COMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (
    _add_export,
    _add_view,
    add_stream,
    add_sim_device,
    add_feed_replay,
    add_sim_dynamixel,
    add_home,
    _add_plan,
    _add_replan,
    add_ros_bridge,
    _add_bench,
    add_record,
    add_calibrate,
    _add_build,
    add_model,
    add_verify,
)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (``crtraj: error: ...``, exit 2) like every other crtraj error;
    subcommand parsers inherit it. `--help` still prints the usage."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"crtraj: error: {_one_line(message)} (see {self.prog} --help)\n")


def _add_talk_flags(p: argparse.ArgumentParser, top: bool) -> None:
    """The global flags -v/--verbose and -q. A command's copies leave the value before the command alone
    unless given (SUPPRESS), so they may stand on either side of the command name."""
    talk = p.add_mutually_exclusive_group()
    more, less = (0, False) if top else (argparse.SUPPRESS, argparse.SUPPRESS)
    talk.add_argument("-v", "--verbose", action="count", default=more, help="more on stderr (-v: info, -vv: debug)")
    talk.add_argument("-q", dest="quiet_log", action="store_true", default=less, help="only errors on stderr")


def _subparsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every command's parser below `parser` (``model`` and ``model compare`` alike), each once."""
    out: list[argparse.ArgumentParser] = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for p in dict.fromkeys(action.choices.values()):
                out += [p, *_subparsers(p)]
    return out


def build_parser() -> argparse.ArgumentParser:
    """The ``crtraj`` parser: global flags (``--version``, ``-v``, ``-q``) and one subparser per command."""
    parser = _Parser(
        prog="crtraj",
        description="Safety-constrained motion planning for cable-driven continuum robots.",
    )
    parser.add_argument("--version", action="version", version=f"crtraj {__version__}")
    _add_talk_flags(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(sub)
    for p in _subparsers(parser):  # `crtraj plan -v` as well as `crtraj -v plan`
        _add_talk_flags(p, top=False)
    strict_flag_types(parser, empty_allowed=frozenset({"note"}))  # a blank --note line is meaningful
    return parser


def _one_line(exc: BaseException, width: int = 1000) -> str:
    """An error message as exactly one line: a message quoting a file name or value with a newline or
    control character in it must not spill onto a second line."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in " ".join(str(exc).splitlines()))
    return text if len(text) <= width else text[: width - 3] + "..."


def main(argv: Sequence[str] | None = None) -> int:
    """The ``crtraj`` command: its exit code. Ctrl-C and SIGTERM have one handler for the whole command
    (`crtraj.core.interrupt`): exit 130 or 143, one stderr line, nothing replaced, no temporary file left.
    argv: the arguments (None: this process's, and the process ends with the command)."""
    with interrupt.policy(last=argv is None):
        try:
            return _main(argv)
        finally:
            interrupt.hold()  # the command is over: a late signal cuts no cleanup short
            interrupt.remove_temporaries()  # the temporary files an interruption left


def _stopped() -> int:
    """The end of a stopped command: one stderr line, the signal's exit code (SIGINT when none was seen: a
    KeyboardInterrupt raised without one)."""
    interrupt.hold()
    signum = interrupt.requested() or signal.SIGINT
    print(interrupt.message(signum), file=sys.stderr)
    return interrupt.exit_code(signum)


def _main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.verbose and args.quiet_log:  # one on each side of the command: their group cannot see both
        parser.error("argument -q: not allowed with argument -v/--verbose")
    configure_logging(args.verbose, args.quiet_log)
    if getattr(args, "use_case", None) is None and getattr(args, "func", None) is None:
        parser.print_help()
        return 2
    try:
        func = args.func if getattr(args, "func", None) is not None else _use_case(args.use_case)
        code = int(func(args) or 0)
        interrupt.check()  # a stop that came as the command ended, or that a library swallowed
        return code
    except AdmissionError as exc:  # a readable result that may not drive a device: refused, not an input error
        print(f"crtraj: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except InputError as exc:
        print(f"crtraj: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except TransportError as exc:  # the device or port, not the input: a run-time failure
        print(f"crtraj: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except BaseException as exc:
        # a stop is any exception once a signal came (what native code made of the KeyboardInterrupt: a
        # SystemError, a solver's RuntimeError) and a KeyboardInterrupt without one
        if interrupt.requested() or isinstance(exc, KeyboardInterrupt):
            return _stopped()
        raise


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
