"""Use case: run a problem's closed loop and write the run (`crtraj replan`).

The loop comes from `crtraj.control.loop.ClosedLoop.from_problem` (robot, scene, task and the
``[replan]``, ``[loop]``, ``[tracking]``, ``[planner]``, ``[steer]``, ``[feed]`` sections).
`run_replan` is the whole command: admission checks, an optional live obstacle feed and live device,
the run, its files (staged, so a failed run never replaces a successful one), the summary, and an
optional stream of the verified run afterwards. Units: mm, rad, s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.app.devices import plan_approach
from crtraj.app.plant_sim import attach_plant, make_plant, plant_lines, plant_verdict
from crtraj.app.run_output import write_run_files
from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import ClosedLoop, ReplanRun, RunStatus, UnsolvableTaskError
from crtraj.control.rod_plant import RodPlant
from crtraj.core.errors import InputError
from crtraj.core.fileio import StagedDir, check_output_dir, failed_sibling, is_successful_result
from crtraj.core.lazy import lazy_module
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import admit, check_stream_safety
from crtraj.hardware.dynamixel import homing_command, parse_url, read_stop, state_path
from crtraj.hardware.link import DeviceLink
from crtraj.hardware.mocap import MocapTip, SimulatedMocap
from crtraj.hardware.setpoints import check_time_scale
from crtraj.hardware.stream import Streamer, StreamError, StreamOptions
from crtraj.hardware.transport import parse_hostport
from crtraj.hardware.verify import FrameVerifier
from crtraj.io.calibration_data import read_calibration
from crtraj.io.problem import Problem, load_robot
from crtraj.io.results import read_result
from crtraj.io.run_files import RUN_FILES
from crtraj.model.kinematics import Model
from crtraj.planning.body import model_record
from crtraj.planning.goal import tip_tangents
from crtraj.world.feed import ObstacleFeed
from crtraj.world.scene import Scene

# the 3-D view (meshcat, zmq: about 0.2 s to import) loads only for --view
view_module = lazy_module("crtraj.app.view")


# --------------------------------------------------------------- the command
@dataclass(frozen=True)
class ReplanRequest:
    """One `crtraj replan` run.

    problem: problem TOML. out: run folder (default out/replan, or out/replan-no-safety without
    safety). seed: overrides the problem's. safety: false drops the collision-free terms. html: write
    run.html. overwrite_failed: a failed run may replace a successful one in out. feed: a UDP obstacle
    feed address (udp://127.0.0.1:PORT) to run live in real time; feed_max_age: s after which a feed
    state is stale. stream: a device address: live with a feed, else the verified run is streamed
    afterwards. approach: the device may start away from the task's start. time_scale: replay slow-down
    (streamed afterwards only). quiet: print only the summary line. true_robot: a robot file whose
    parameters differ from the problem's (a simulation: a motion-capture tip marker films this robot,
    `crtraj.hardware.mocap.SimulatedMocap`, and the run reports its measured tip error; with plant: the
    rod's robot file). tip_feedback: the
    loop corrects its model's error with that measured tip. mocap_port: listen on 127.0.0.1:PORT for the live
    capture's tip marker (`crtraj.hardware.mocap.MocapTip`, through the robot file's calibrated capture frame;
    live runs only: with feed and stream). plant: "cosserat" (or "cosserat-weightless") simulates the robot
    with the Cosserat rod (`crtraj.app.plant_sim`): its shape is judged against the obstacles and its tip
    is the loop's tip measurement. model: the body the loop keeps D_sf from, "pcc" or "rod" (None: the
    problem's ``[planner] model``; `crtraj.planning.body`).
    """

    problem: Path
    out: Path | None = None
    seed: int | None = None
    safety: bool = True
    html: bool = True
    overwrite_failed: bool = False
    feed: str | None = None
    feed_max_age: float = 0.2
    stream: str | None = None
    approach: bool = False
    time_scale: float = 1.0
    quiet: bool = False
    true_robot: Path | None = None
    tip_feedback: bool = False
    mocap_port: int | None = None
    plant: str | None = None
    model: str | None = None


@dataclass(frozen=True)
class _Written:
    """A finished run and where it went."""

    run: ReplanRun
    loop: ClosedLoop
    link: DeviceLink | None
    ok: bool  # reached the goal without breaking D_sf (also without the safety terms), and a live stream completed
    dest: Path
    paths: dict[str, Any]
    plant: RodPlant | None = None  # the simulated plant (--plant)
    streamed: bool = True  # False: --stream of the finished run did not complete


def run_replan(req: ReplanRequest, *, view: Callable[[dict[str, Any]], None] | None = None, watch: Any = None) -> int:
    """Run `req` as ``crtraj replan`` does, printing its progress and summary; returns the exit code
    (0 success, 1 failed or unsolvable, 130 interrupted). Bad input raises `InputError` before any long
    work. view: called with the result document afterwards (e.g. to serve the 3-D replay). watch: a live view
    (`crtraj.app.view.LiveSession`): ``watch.start(loop)`` gives the loop's observer, ``watch.stop()`` ends it."""
    check_time_scale(req.time_scale)
    if req.seed is not None and req.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {req.seed}")
    if req.stream:
        check_stream_safety(req.safety)
    if req.tip_feedback and req.true_robot is None and req.mocap_port is None and req.plant is None:
        raise InputError(
            "--tip-feedback: needs a tip measurement: --mocap-port (live), --true-robot or --plant (simulated)"
        )
    if req.plant is not None and (req.stream or req.feed or req.mocap_port is not None):
        raise InputError("--plant: a simulation; it cannot be combined with --stream, --feed or --mocap-port")
    if req.true_robot is not None and (req.stream or req.feed or req.mocap_port is not None):
        raise InputError("--true-robot: a simulation; it cannot be combined with --stream, --feed or --mocap-port")
    if req.mocap_port is not None and not (req.stream and req.feed):
        raise InputError("--mocap-port: a live run only (with --feed and --stream): the capture films the real robot")
    out = req.out if req.out is not None else Path("out") / ("replan" if req.safety else "replan-no-safety")
    check_output_dir(out, "--out", RUN_FILES)  # before the (possibly long) run, not after it
    problem = Problem.load(req.problem)
    seed = problem.seed if req.seed is None else req.seed
    t0 = time.perf_counter()
    feed = _open_feed(req.feed, req.feed_max_age, problem) if req.feed else None

    def summary_then_stream(done: _Written, staged: dict[str, Any]) -> bool:
        """The summary, then (--stream of a simulated run) its stream from the staged files: before the run's
        folder replaces `out`, so a stream stopped by Ctrl-C or SIGTERM leaves the earlier run in place."""
        _print_summary(req, done, out, t0)
        if done.link is not None or not req.stream:
            return True
        if not done.ok:  # a run that failed or broke the safety distance never reaches a device
            print("  not streamed: the run did not reach the goal safely", flush=True)
            return True
        return _stream_run(req, problem, staged, done.dest)

    done = _run_and_write(req, problem, seed, feed, out, watch, then=summary_then_stream)
    if done is None:
        return 1
    if view is not None:
        view(done.paths["result"])
    return _exit_code(done, done.streamed)


def _tip_sensor(req: ReplanRequest, problem: Problem) -> SimulatedMocap | MocapTip | RodPlant | None:
    """The live capture's tip (--mocap-port), the simulated motion capture of --true-robot, the simulated
    plant (--plant: the tip of its shape), or None."""
    if req.plant is not None:
        return make_plant(req.plant, problem, load_robot(req.true_robot) if req.true_robot else None)
    if req.mocap_port is not None:
        ref = problem.raw.get("robot")
        rec = read_calibration(problem.path.parent / ref) if isinstance(ref, str) and problem.path else None
        if rec is None:
            raise InputError(
                "--mocap-port: the robot file has no [calibration] capture frame; run crtraj calibrate first"
            )
        return MocapTip(rec.capture, port=req.mocap_port)
    if req.true_robot is None:
        return None
    if problem.robot.actuators is None:
        raise InputError(
            "--true-robot: the problem's robot has no [robot.actuators] to turn its plan into servo values"
        )
    return SimulatedMocap(load_robot(req.true_robot), Actuators.from_robot(problem.robot), seed=problem.seed)


def _open_feed(address: str, max_age: float, problem: Problem) -> ObstacleFeed:
    """Listen for the scene's obstacles on 127.0.0.1 (`ObstacleFeed`); the obstacle names are the ids."""
    host, port = parse_hostport(address.removeprefix("udp://"), "--feed")
    if host not in ("127.0.0.1", "localhost"):
        raise InputError(f"--feed: the feed listens on 127.0.0.1 only, got host {host!r}")
    ids = [o.name for o in Scene.from_table(problem.section("scene")).obstacles]
    feed = ObstacleFeed(port, max_age=max_age, expected=ids)
    print(f"listening for obstacle states ({', '.join(ids)}) on udp://127.0.0.1:{feed.address[1]}", flush=True)
    return feed


def _run_and_write(  # long: the run's resources (stage, stream, feed, live view) share one exit stack
    req: ReplanRequest,
    problem: Problem,
    seed: int,
    feed: Any,
    out: Path,
    watch: Any = None,
    then: Callable[[_Written, dict[str, Any]], bool] | None = None,
) -> _Written | None:
    """Build the loop, run it (live with a feed and a device) and write its files; None when the task
    is unsolvable (said on stdout and stderr, nothing written). `then(done, staged)`: called with the run and
    its staged (not yet committed) files before they replace `out`; its answer is `_Written.streamed`."""
    live = feed is not None and bool(req.stream)
    link = streamer = None  # bound before anything can fail: the `finally` below reads both
    sensor = _tip_sensor(req, problem)
    with contextlib.ExitStack() as stack:
        try:
            lead, sopts = _live_stream_options(problem) if live else (0.0, None)
            # every file of the run, a live stream's log too, goes into a temporary sibling folder that
            # replaces `out` as a whole at the end: a kill never leaves a mix of old and new files
            stage = stack.enter_context(StagedDir(out, RUN_FILES))
            streamer = _connect_live(req.stream or "", problem, sopts, stage.path) if live else None
            if streamer is not None:
                stack.callback(streamer.close)  # closed on any way out (a no-op once the run closed it)
            # with --approach the live run starts where the device is: its own verified motion is the approach
            x_dev = _device_config(problem, streamer) if streamer is not None and req.approach else None
            try:
                loop = ClosedLoop.from_problem(
                    problem,
                    safety=req.safety,
                    seed=seed,
                    feed=feed,
                    lead=lead,
                    start_config=x_dev,
                    tip_sensor=stack.enter_context(contextlib.closing(sensor)) if sensor else None,
                    tip_feedback=req.tip_feedback,
                    body=req.model,
                )
            except UnsolvableTaskError as exc:
                print(f"{exc.status}: {exc}; no run, nothing written to {out}")
                print(f"crtraj: replan failed: {exc.status}: {exc}", file=sys.stderr)
                return None
            if streamer is not None:
                link = _live_link(streamer, req.approach, problem, loop, sopts)
            if not req.quiet:
                _print_header(problem, seed, loop, live_obstacles=feed is not None)
            if watch is not None:
                stack.callback(watch.stop)  # the feed stops (and says what it dropped) however the run ends
            if isinstance(sensor, RodPlant):
                attach_plant(sensor, loop)
            device = sensor if isinstance(sensor, RodPlant) else link
            run = loop.run(device=device, observer=watch.start(loop) if watch is not None else None)
        finally:
            if streamer is not None:
                streamer.close()  # a no-op after a normal run: the run closed it
            if feed is not None:
                feed.close()
        ok = run.is_success()  # reached the goal safely, --no-safety or not
        if isinstance(sensor, RodPlant):
            ok = ok and not plant_verdict(sensor)  # and safely by the plant's shape
        if link is not None:
            ok = ok and link.report.ok
        staged = write_run_files(run, loop, stage.path, problem=problem, seed=seed, html=req.html)
        # a failed run never replaces a successful one unless asked: it goes beside it (NAME.failed)
        dest = out
        if not ok and not req.overwrite_failed and is_successful_result(out):
            dest = failed_sibling(out)
        paths = {k: (v if k == "result" else dest / Path(v).name) for k, v in staged.items()}
        done = _Written(run, loop, link, ok, dest, paths, sensor if isinstance(sensor, RodPlant) else None)
        try:
            streamed = then(done, staged) if then is not None else True
        except Exception:  # a device refused or failed: the run is kept (a stop is no Exception: it is not)
            stage.commit(dest)
            raise
        stage.commit(dest)  # raises Interrupted after a stop: the earlier run stays
    return dataclasses.replace(done, streamed=streamed)


def _print_header(problem: Problem, seed: int, loop: ClosedLoop, *, live_obstacles: bool) -> None:
    o, d = loop.options, loop.describe_nlp()
    print(
        f"replanning '{problem.name}' (seed {seed}, {'with' if o.safety else 'WITHOUT'} collision-free "
        f"terms{', live obstacles, real time' if live_obstacles else ''}): horizon {o.horizon} x "
        f"{o.dt:g} s, {d['solver']}, {d['variables']} variables, {d['constraints']} constraints",
        flush=True,
    )


def _print_summary(req: ReplanRequest, done: _Written, out: Path, t0: float) -> None:
    """The summary line, the live stream's line, and (not quiet) the actuator limit fractions, step counts and
    file paths."""
    run, link, dest = done.run, done.link, done.dest
    line = run.summary_line()
    if dest != out:
        line += f"; failed run written to {dest} ({out} holds a successful run, kept: --overwrite-failed replaces it)"
    print(line)
    if not req.quiet:
        print(f"  {run.limits_line()}")
    aim = direction_line(done.loop, run)
    if aim:
        print(f"  {aim}")
    if done.plant is not None:
        for text in plant_lines(done.plant, run, model_record(done.loop.model)["kind"]):
            print(f"  {text}")
    elif run.measured_tip is not None:
        print(f"  {measured_tip_line(run, req.tip_feedback)}")
    if link is not None:
        rep = link.report
        fe = "" if rep.final_error is None else f", final error {rep.final_error:.3g}"
        print(
            f"  live stream {rep.status}: {rep.message}; {rep.frames} frames ({rep.moves} move, {rep.holds} hold, "
            f"{rep.estops} e-stop){fe}; {link.restarts} restarts; log {dest / 'stream.jsonl'}"
        )
    if not req.quiet:
        counts = ", ".join(f"{k} {v}" for k, v in run.summary()["status_counts"].items())
        print(f"  steps: {counts}; wall time {time.perf_counter() - t0:.2f} s")
        for key in ("json", "npz", "png", "html"):
            if key in done.paths:
                print(f"  {key:4s} {done.paths[key]}")


def direction_line(loop: ClosedLoop, run: ReplanRun) -> str:
    """'goal direction: final tip tangent 3.10 deg from goal_direction (cone 10 deg): within' for a task with a
    direction goal (the loop holds the goal only with the tangent within the cone); '' otherwise."""
    goal = loop.config.tip_goal
    if goal.cone is None:
        return ""
    angle = float(goal.angles(tip_tangents(loop.model, run.x[-1:]))[0])
    inside = "within" if angle <= goal.cone else "OUTSIDE"
    return (
        f"goal direction: final tip tangent {math.degrees(angle):.2f} deg from goal_direction "
        f"(cone {goal.cone_deg:g} deg): {inside}"
    )


def measured_tip_line(run: ReplanRun, feedback: bool) -> str:
    """The tip error as the motion capture measures it (the true robot's tip, not the model's)."""
    err = np.linalg.norm(run.measured_tip - run.goal, axis=1)
    final = float(np.nanmean(err[-10:]))  # the last ten readings: the capture noise averages out
    how = "with" if feedback else "without"
    return (
        f"measured tip (simulated motion capture of --true-robot), {how} tip feedback: final error {final:.2f} mm "
        f"to the goal (mean of the last 10 readings) (the model's own tip: {float(run.goal_error[-1]):.2f} mm)"
    )


def _exit_code(done: _Written, streamed: bool) -> int:
    """0 when the run reached the goal safely (and any stream completed), 130 interrupted, else 1 with
    one stderr line saying why."""
    run, link, dest = done.run, done.link, done.dest
    if run.status is RunStatus.INTERRUPTED:
        return 130
    if not done.ok:
        why = f"{run.status}: {run.message}"
        if run.reached and run.safety_violations:
            why = f"unsafe: {run.safety_violations} steps closer than D_sf, {run.collisions} touching an obstacle"
        elif done.plant is not None and plant_verdict(done.plant):
            why = plant_verdict(done.plant)
        elif link is not None and run.reached:
            why = f"live stream {link.report.status}: {link.report.message}"
        print(f"crtraj: replan failed: {why} (run in {dest})", file=sys.stderr)
    elif not streamed:
        print(f"crtraj: replan: the run succeeded (in {dest}) but the stream did not complete", file=sys.stderr)
    return 0 if done.ok and streamed else 1


# ------------------------------------------------------------------ devices
def _live_stream_options(problem: Problem) -> tuple[float, StreamOptions]:
    """(lead s, StreamOptions) of a live stream: the [stream] prebuffer, at least one replan step."""
    sopts = problem.options(StreamOptions, "stream")
    lead = max(sopts.prebuffer, problem.options(ReplanOptions, "replan").dt)
    return lead, dataclasses.replace(sopts, prebuffer=lead)


def _stream_target(address: str) -> str:
    return address if "://" in address else f"udp://{address}"


def _actuators(problem: Problem) -> Actuators:
    if problem.robot.actuators is None:
        raise InputError("robot.actuators: --stream needs a [robot.actuators] table in the robot file")
    return Actuators.from_robot(problem.robot)


def _link_options(target: str, problem: Problem) -> dict[str, Any]:
    """A Dynamixel link's keywords: the homing state file beside the problem's robot file (none for an inline
    robot: its multi-turn actuators are then refused), the command that homes it, and ``[robot.stop]``."""
    if not target.startswith("dynamixel://"):
        return {}
    ref = problem.raw.get("robot")
    robot_file = problem.path.parent / ref if isinstance(ref, str) and problem.path is not None else None
    return {
        "homing": state_path(robot_file) if robot_file is not None else None,
        "home_command": homing_command(robot_file, parse_url(target)[0]),
        "stop_torque": read_stop(problem.robot).torque,
        "bus_watchdog": read_stop(problem.robot).bus_watchdog,
    }


def _connect_live(address: str, problem: Problem, sopts: Any, out: Path) -> Streamer:
    """Connect to the device for a live run and start its stream (its log in out/stream.jsonl)."""
    target = _stream_target(address)
    link = _link_options(target, problem)
    streamer = Streamer.open(target, _actuators(problem), sopts, out / "stream.jsonl", link=link)
    try:
        streamer.start()
    except StreamError as exc:
        streamer.close()
        raise InputError(f"--stream: {exc}") from None
    except BaseException:
        streamer.close()
        raise
    return streamer


def _device_config(problem: Problem, streamer: Streamer) -> np.ndarray:
    """The configuration (rad, mm) the device's actuators are at now (eq. 4 inverted)."""
    return problem.robot.config(streamer.actuators.actuation(streamer.position))


def _live_link(streamer: Streamer, approach: bool, problem: Problem, loop: ClosedLoop, sopts: Any) -> DeviceLink:
    """The loop's `DeviceLink` to a started device; refuse a device that is not at the task's start
    unless approach (the run then starts where the device is)."""
    acts = streamer.actuators
    try:
        # each step's frames are verified as sent against the scene snapshot the loop checked the step with
        verifier = FrameVerifier(problem.robot, acts, loop.scene, sopts.dt, model=Model(problem.robot))
        link = DeviceLink(
            streamer,
            loop.servo,
            loop.options.dt,
            lead=sopts.prebuffer,
            verifier=verifier,
            scene_now=lambda: loop.scene_now,
        )
        here = streamer.position
        start = acts.command(loop.start_command())
        d = np.abs(here - start)
        i = int(np.argmax(d))
        tol = sopts.settle_tolerance
        if d[i] > tol and not approach:
            u = acts.units[i]
            raise InputError(
                f"--stream: the device's {acts.names[i]} is at {here[i]:.4g} {u}, the task starts at {start[i]:.4g} "
                f"{u} ({d[i]:.3g} {u} apart, more than stream.settle_tolerance {tol:g}); move the robot to the "
                "start, or pass --approach to start the run from where the device is"
            )
    except BaseException:
        streamer.close()
        raise
    print(f"streaming live to {streamer.transport.description} ({sopts.prebuffer:g} s ahead)", flush=True)
    return link


def _stream_run(req: ReplanRequest, problem: Problem, paths: dict[str, Any], dest: Path) -> bool:
    """Stream a finished run's actuation (its waypoints' q) to the device; True when the stream completed.
    paths: the run's staged files (the log is written beside them); dest: the folder they go to."""
    actuators = _actuators(problem)
    target = _stream_target(req.stream or "")
    opts = problem.options(StreamOptions, "stream")
    log = Path(paths["json"]).parent / "stream.jsonl"
    # the run's motion is admitted like any result (the refusals live in the library, not in the CLI)
    motion = admit(
        read_result(paths["result"]).motion_record(),
        actuators,
        robot=problem.robot,
        time_scale=req.time_scale,
        rate=opts.rate,
    )
    print(f"streaming the run ({motion.path.duration:.2f} s) to {target}", flush=True)
    streamer = Streamer.open(target, actuators, opts, log, link=_link_options(target, problem))
    rep = streamer.run_path(motion, approach=req.approach, plan_approach=plan_approach)
    print(f"  stream {rep.status}: {rep.message}; {rep.frames} frames; log {dest / log.name}")
    return rep.ok


def replan_command(args: Any) -> int:
    """The `crtraj replan` use case: the parsed command line as a `ReplanRequest`, then `run_replan`."""
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
        true_robot=Path(args.true_robot) if getattr(args, "true_robot", None) else None,
        tip_feedback=bool(getattr(args, "tip_feedback", False)),
        mocap_port=getattr(args, "mocap_port", None),
        plant=getattr(args, "plant", None),
        model=getattr(args, "model", None),
    )
    if not args.view:
        return run_replan(req)
    live = view_module.LiveSession(open_browser=not args.no_browser)  # the loop feeds it as it runs
    try:
        return run_replan(req, view=live.serve, watch=live)
    finally:
        live.close()
