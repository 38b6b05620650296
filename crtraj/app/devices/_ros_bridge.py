"""Use case: run a problem's closed loop on a robot in a ROS 2 graph (`crtraj ros-bridge`).

The bridge (`crtraj.hardware.ros`) starts its own rclpy context on the problem's ``[ros]`` domain,
takes the robot's measured actuator positions from sensor_msgs/JointState, the live obstacles from
SPHERE markers (visualization_msgs/MarkerArray) and from the UDP JSON feed on 127.0.0.1, runs the
replanner in real time against them, and publishes every step's verified motion as a
trajectory_msgs/JointTrajectory and the body and obstacles as markers for RViz. A stale obstacle
feed holds the robot; a step that fails the verification is not published. The run's files are
written as `crtraj replan` writes them (staged; a failed run never replaces a successful one).
Units: mm, rad, s.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from crtraj.app.replan import UnsolvableTaskError
from crtraj.app.run_output import write_run_files
from crtraj.control.loop import CallableClock, ClosedLoop, RunStatus
from crtraj.core.errors import InputError
from crtraj.core.fileio import (
    StagedDir,
    check_output_dir,
    check_output_file,
    check_outputs_not_inputs,
    failed_sibling,
    is_successful_result,
)
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.ros import (
    VERIFY_SUBSTEPS,
    JtcParameters,
    McapRecorder,
    RosDevice,
    RosNode,
    RosOptions,
    check_parameters,
    detect_distro,
    parameter_names,
)
from crtraj.hardware.verify import FrameVerifier
from crtraj.io.problem import Problem
from crtraj.io.run_files import RUN_FILES
from crtraj.world.feed import ObstacleFeed
from crtraj.world.scene import Scene

log = logging.getLogger(__name__)
PARAMETER_TIMEOUT = 2.0  # s to wait for the controller's parameter service
PARAMETER_ANSWERS = 5.0  # s more for its answers, once found (a loaded graph answers slowly; no loop runs yet)


@dataclass(frozen=True)
class RosBridgeRequest:
    """One `crtraj ros-bridge` run. problem: problem TOML (its ``[ros]`` section configures the
    bridge). out: run folder (default out/ros-bridge). seed: overrides the problem's. html: write
    run.html. overwrite_failed: a failed run may replace a successful one in out. quiet: print only
    the summary lines. record: an MCAP file to log the messages sent and received to."""

    problem: Path
    out: Path | None = None
    seed: int | None = None
    html: bool = True
    overwrite_failed: bool = False
    quiet: bool = False
    record: Path | None = None


def _await_robot(node: RosNode, feed: ObstacleFeed, ros: RosOptions) -> JtcParameters:
    """Block until the robot's first joint state, a subscriber of the trajectory topic and a fresh state of
    every expected obstacle have arrived; `InputError` naming the field after ``ros.start_timeout``
    wall-clock seconds. Then the controller's parameters (`_controller_parameters`)."""
    if node.wait_joint_state(-math.inf, ros.start_timeout) is None:
        if node.seen_names is not None:
            missing = [j for j in node.names if j not in node.seen_names]
            raise InputError(
                f"ros.joints: the robot's joint states name {', '.join(node.seen_names[:20])}, not "
                f"{', '.join(missing)}; map crtraj's actuators to the robot's joints with [ros.joints]"
            )
        raise InputError(
            f"ros.joint_state_topic: no sensor_msgs/JointState naming {', '.join(node.names)} on "
            f"{ros.joint_state_topic} within {ros.start_timeout:g} s"
        )
    end = time.monotonic() + ros.start_timeout
    while feed.latest().stale and time.monotonic() < end:
        feed.wait_for(feed.datagrams + 1, min(0.1, max(end - time.monotonic(), 0.0)))
    st = feed.latest()
    if st.stale:
        raise InputError(f"ros.obstacle_topic: no obstacle states within {ros.start_timeout:g} s ({st.reason})")
    if not node.wait_subscribers(ros.start_timeout):
        raise InputError(
            f"ros.controller: nothing subscribes to {ros.trajectory_topic_name} within {ros.start_timeout:g} s "
            f"(is {ros.controller} loaded and active?)"
        )
    return _controller_parameters(node, ros)


def _controller_parameters(node: RosNode, ros: RosOptions) -> JtcParameters:
    """The controller's parameters through ``/<controller>/get_parameters`` (`check_parameters`, one line naming the
    parameter on a refusal); when the service does not answer, a warning that nothing was checked and the model of
    ``ros.distro`` (Humble for "auto") with its defaults."""
    wait = min(ros.start_timeout, PARAMETER_TIMEOUT)
    values = node.get_parameters(ros.controller, parameter_names(node.names), wait, PARAMETER_ANSWERS)
    if values is None:
        params, why = check_parameters(ros.controller, {}, node.names, distro=ros.distro, update_rate=ros.update_rate)
        log.warning(
            "ros: /%s/get_parameters did not answer within %g s: the controller's parameters are NOT checked; the "
            "bridge assumes %s's defaults (set ros.distro when that is not the robot's release)",
            ros.controller,
            wait,
            params.distro,
        )
    else:
        params, why = check_parameters(
            ros.controller, values, node.names, distro=ros.distro, update_rate=ros.update_rate
        )
        if detect_distro(values) is None:
            log.warning(
                "ros: %s declares none of allow_trajectory_replacement, interpolate_from_desired_state and "
                "open_loop_control (is it a joint_trajectory_controller?): its release is unknown; the bridge "
                "assumes %s (ros.distro)",
                ros.controller,
                params.distro,
            )
    scaling = f"/{ros.controller}/speed_scaling_input"
    if not why and params.distro != "humble" and node.node.count_publishers(scaling):
        why = (
            f"ros.controller: something publishes on {scaling}, which changes {ros.controller}'s speed scaling while "
            "it runs (the trajectory would not run as verified); stop that publisher"
        )
    if why:
        raise InputError(why)
    log.info("ros: %s (%s, lookahead %g s) parameters checked: %s", ros.controller, params.distro, params.lookahead,
             values)  # fmt: skip
    return params


def _recorder(req: RosBridgeRequest, problem: Problem, acts: Actuators, ros: RosOptions) -> McapRecorder | None:
    """The MCAP recorder of ``--record`` (None without it), after the checks that need no ROS graph: the
    file is not an input, and every actuator in ``[ros.joints]`` is one of the robot's."""
    unknown = [a for a, _ in ros.joints if a not in acts.names]
    if unknown:
        raise InputError(f"ros.joints.{unknown[0]}: not an actuator of the robot ({', '.join(acts.names)})")
    if req.record is None:
        return None
    robot = problem.raw.get("robot")
    robot_file = Path(req.problem).parent / robot if isinstance(robot, str) else None
    check_outputs_not_inputs({"--record": req.record, "--out": req.out}, {"problem": req.problem, "robot": robot_file})
    check_output_file(req.record, "--record")
    return McapRecorder(req.record)


def _plan_first(loop: Any, node: RosNode, acts: Actuators) -> None:
    """Plan the first reference path from where the robot is, among the obstacles as they are now, before
    the loop's clock starts: in the first step the planner would take longer than ``ros.lead``. (Every
    step still checks the reference against the obstacles of its time and replans when it is blocked.)"""
    st = node.joint_state()
    if st is not None:
        loop.plan_first_reference(acts.actuation(st[0]))


def run_ros_bridge(
    req: RosBridgeRequest,
    *,
    clock: Callable[[], float] | None = None,
    sleep: Callable[[float], None] | None = None,
    ready: Callable[[RosNode, ObstacleFeed], None] | None = None,
) -> int:
    """Run `req` as ``crtraj ros-bridge`` does; returns the exit code (0 the goal was reached safely,
    1 not, 130 Ctrl-C: the robot was held). clock, sleep: the bridge's time (s) and pacing (default:
    the ROS clock, i.e. the system time, and `time.sleep`); a virtual clock makes the run independent
    of the machine's speed.
    ready: called once the node and the feed are up (tests start the robot's side there)."""
    if req.seed is not None and req.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {req.seed}")
    out = req.out if req.out is not None else Path("out") / "ros-bridge"
    check_outputs_not_inputs({"--out": out}, {"PROBLEM": req.problem})
    check_output_dir(out, "--out", RUN_FILES)
    problem = Problem.load(req.problem)
    ros = problem.options(RosOptions, "ros")
    if problem.robot.actuators is None:
        raise InputError("robot.actuators: ros-bridge needs a [robot.actuators] table in the robot file")
    acts = Actuators.from_robot(problem.robot)
    recorder = _recorder(req, problem, acts, ros)
    ids = [o.name for o in Scene.from_table(problem.section("scene")).obstacles]
    feed = ObstacleFeed(ros.udp_feed_port, max_age=ros.max_age, expected=ids, clock=clock or time.monotonic)
    with contextlib.ExitStack() as stack:
        stack.callback(feed.close)
        if recorder is not None:
            stack.callback(recorder.discard)  # after a commit: nothing left to drop
        node = stack.enter_context(RosNode(ros, acts, feed, recorder=recorder))
        print(
            f"ros-bridge: domain {node.domain_id} ({ros.discovery} discovery); joint states on "
            f"{ros.joint_state_topic}, obstacles ({', '.join(ids)}) on {ros.obstacle_topic} and "
            f"udp://127.0.0.1:{feed.address[1]}; "
            f"publishing {ros.trajectory_topic_name} and {ros.markers_topic}",
            flush=True,
        )
        if ready is not None:
            ready(node, feed)
        controller = _await_robot(node, feed, ros)
        parts = _Parts(stack, node, feed, acts, ros, controller, recorder)
        return _run(req, problem, out, parts, _Pacing(clock, sleep))


@dataclass(frozen=True)
class _Pacing:
    """The bridge's time (s) and pacing; None: the ROS clock (the system time) and `time.sleep`."""

    clock: Callable[[], float] | None = None
    sleep: Callable[[float], None] | None = None


@dataclass(frozen=True)
class _Parts:
    """What the bridge has set up before the loop: the exit stack, the node, the feed, the actuators, the
    ``[ros]`` options, the controller's parameters and the MCAP recorder (or None)."""

    stack: contextlib.ExitStack
    node: RosNode
    feed: ObstacleFeed
    acts: Actuators
    ros: RosOptions
    controller: JtcParameters
    recorder: McapRecorder | None


def _run(req: RosBridgeRequest, problem: Problem, out: Path, parts: _Parts, pacing: _Pacing) -> int:
    """The loop against the live robot, from where it is now; its files staged and renamed into `out`
    (or OUT.failed), the MCAP log committed; the exit code."""
    node, acts, ros = parts.node, parts.acts, parts.ros
    seed = problem.seed if req.seed is None else req.seed
    try:
        # the run starts where the robot is (its newest joint state), not at the task's start
        here = node.joint_state()
        x_robot = None if here is None else problem.robot.config(acts.actuation(here[0]))
        kw_clock = {} if pacing.clock is None else {"clock": CallableClock(pacing.clock, pacing.sleep or time.sleep)}
        loop = ClosedLoop.from_problem(
            problem, seed=seed, feed=parts.feed, lead=ros.lead, start_config=x_robot, **kw_clock
        )
    except UnsolvableTaskError as exc:
        print(f"{exc.status}: {exc}; no run, nothing written to {out}")
        print(f"crtraj: ros-bridge failed: {exc.status}: {exc}", file=sys.stderr)
        return 1
    dt = loop.options.dt
    spacing = dt / (ros.points_per_step * VERIFY_SUBSTEPS)  # the executed curve is checked this densely
    verifier = FrameVerifier(problem.robot, acts, loop.scene, spacing, model=loop.model)
    kw: dict[str, Any] = {} if pacing.clock is None else {"clock": pacing.clock, "sleep": pacing.sleep or time.sleep}
    kw.update(lead=ros.lead, controller=parts.controller, arrival_margin=ros.arrival_margin, state_lag=ros.state_lag)
    device = RosDevice(node, acts, loop.model, loop.servo, dt, verifier, lambda: loop.scene_now, **kw)
    _plan_first(loop, node, acts)
    stage = parts.stack.enter_context(StagedDir(out, RUN_FILES))
    run = loop.run(device=device)
    ok = run.is_success() and not device.problem()
    staged = write_run_files(run, loop, stage.path, problem=problem, seed=seed, html=req.html)
    dest = out
    if not ok and not req.overwrite_failed and is_successful_result(out):
        dest = failed_sibling(out)
    dest = stage.commit(dest)
    if parts.recorder is not None:
        parts.recorder.commit()
    _print_summary(run, device, staged, dest, req.quiet)
    if run.status is RunStatus.INTERRUPTED:
        return 130
    return 0 if ok else 1


def _print_summary(run: Any, device: RosDevice, staged: dict[str, Any], dest: Path, quiet: bool) -> None:
    """The run's summary line, the bridge's counters, and (not quiet) the limit fractions and file paths;
    one stderr line when the run failed."""
    print(run.summary_line())
    d = device.describe()
    r = d["ros"]
    print(
        f"  ros: {d['moves']} steps published, {d['holds']} holds, {d['refused_steps']} refused before sending "
        f"({d['late_refused']} too late); "
        f"{r['joint_states']} joint states, {r['marker_arrays']} marker arrays, rejected {r['rejected'] or 'none'}"
    )
    if not quiet:
        print(f"  {run.limits_line()}")
        for key in ("json", "npz", "png", "html"):
            if key in staged:
                print(f"  {key:4s} {dest / Path(staged[key]).name}")
    if not (run.is_success() and not device.problem()):
        why = device.problem() or f"{run.status}: {run.message}"
        print(f"crtraj: ros-bridge failed: {why} (run in {dest})", file=sys.stderr)


def ros_bridge_command(args: Any) -> int:
    """The `crtraj ros-bridge` use case: the parsed command line as a `RosBridgeRequest`."""
    req = RosBridgeRequest(
        problem=Path(args.problem),
        out=Path(args.out) if args.out else None,
        seed=args.seed,
        html=not args.no_html,
        overwrite_failed=args.overwrite_failed,
        quiet=args.quiet,
        record=Path(args.record) if getattr(args, "record", None) else None,
    )
    return run_ros_bridge(req)
