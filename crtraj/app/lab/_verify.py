"""Use case: re-check a plan or a run against its obstacles with the Cosserat rod (`crtraj verify --model cosserat`).

Every frame of the result (its waypoints, and `substeps` - 1 configurations linearly between each pair,
at linearly interpolated times) is shaped twice: by PCC, and by Cosserat-rod statics driven in the robot
file's actuation mode (`crtraj.model.cosserat.RodDrive`, ``[robot.mechanics] actuation``: the commanded
cable lengths of position-controlled servos, or the tendon tensions that hold that PCC bending on a
weightless rod), with the robot's weight unless ``gravity`` is off. Both shapes are sampled at the rod's
integration nodes (`[robot.mechanics] steps` per segment) and offset by the base translation; each node
is the centre of the body's cross-section (radius ``robot.body_radius``), as in the planner's collision
check (`crtraj.world.margin`). Obstacles are taken at each frame's time (moving, breathing) from the
result's scene: its spheres, and every other shape (boxes, capsules, cylinders, half spaces, meshes, point
clouds) through the verifiers' exact distance (`crtraj.world.geometry.exact_min_clearance`, brute force on
the shape's triangles or points, independent of the planner's grid). Clearance of a node: its distance to
the obstacle's surface (``|p - c(t)| - R(t)`` for a sphere) ``- body_radius - D_sf`` (mm); >= 0 keeps D_sf,
< -D_sf is contact (the body inside the obstacle).

Reported: each model's minimum clearance with where (frame, time, arc length along the backbone,
obstacle), the largest PCC-to-rod node distance, the clearance the mechanics take away (largest
per-frame PCC minus rod clearance) and the extra D_sf this result needs (minus the rod's minimum
clearance, when negative). A task with a tip direction goal (``goal_direction``, ``goal_cone``) also gets the
last frame's tip tangent angle to the direction under each model; outside the cone under PCC fails the check
(under the rod: with ``--strict``). The rod solves run compiled and warm-started frame to frame
(`crtraj.model.cosserat._statics`), to `VERIFY_TOLERANCE`; the actuation mode is printed with the figures.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crtraj.core.errors import InputError
from crtraj.io.problem import Problem, load_robot
from crtraj.io.results import Result, read_result
from crtraj.model.cosserat import RodDrive, robot_rod
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot
from crtraj.planning.goal import TipGoal, tip_tangents
from crtraj.world import margin
from crtraj.world.geometry import MovingShape, exact_distance, exact_min_clearance
from crtraj.world.scene import Scene

log = logging.getLogger(__name__)

MAX_SUBSTEPS = 100
# Shooting tolerance of the verification's rod solves (N); tighter [robot.mechanics] tolerances are kept. The
# solves stop as soon as the tip residual is within it (no polish below, issue 31: verify within ten times the
# planning time): on the sim-1/sim-2 plans (tension mode) the per-frame clearances then lie within 0.004 mm of
# the polished solves' and within 0.003 mm of a cold 1e-11 N solve on the frames checked, below the 0.01 mm reported.
VERIFY_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Closest:
    """Where a model's body comes closest: clearance (mm), frame index, time (s), node index, arc length
    along the undeformed backbone (mm) and obstacle index."""

    clearance: float
    frame: int
    t: float
    node: int
    arc: float
    obstacle: int
    name: str = ""  # how the text names the obstacle ("shape 2 (box)"); "obstacle K" (a sphere) when empty

    def text(self) -> str:
        return (
            f"{self.clearance:.2f} mm at t {self.t:.2f} s (frame {self.frame}), {self.arc:.0f} mm along the "
            f"backbone, {self.name or f'obstacle {self.obstacle}'}"
        )


@dataclass(frozen=True)
class Verification:
    """Per frame (N,): times t (s), clearance under PCC and under the rod (mm; NaN where the rod failed),
        largest node distance between the two shapes (mm). pcc, rod: the closest approach of each. failed:
        frames whose rod solve did not converge. safety_distance: the D_sf checked (mm). gravity: the rod carried
        its weight. actuation: the rod's actuation mode ("cable_length" or "tension"). seconds, cpu_seconds: wall
    and process CPU time of the check (the CPU time moves far less with other jobs' load). goal_cone,
    pcc_goal_angle, rod_goal_angle (rad): a direction goal's cone and the last frame's tip tangent angle to its
    direction under each model (NaN without a direction goal)."""

    t: np.ndarray
    pcc_clearance: np.ndarray
    rod_clearance: np.ndarray
    discrepancy: np.ndarray
    pcc: Closest
    rod: Closest | None
    failed: int
    safety_distance: float
    gravity: bool
    actuation: str
    seconds: float
    cpu_seconds: float
    goal_cone: float = float("nan")  # rad: the task's direction cone (NaN: no direction goal)
    pcc_goal_angle: float = float("nan")  # rad: the last frame's PCC tip tangent to the goal direction
    rod_goal_angle: float = float("nan")  # rad: the same under the rod (NaN where its solve failed)

    @property
    def has_direction(self) -> bool:
        return bool(np.isfinite(self.goal_cone))

    @property
    def holds(self) -> bool:
        """D_sf holds under the rod at every frame (and every rod solve converged)."""
        return self.failed == 0 and self.rod is not None and self.rod.clearance >= 0.0

    @property
    def contact(self) -> bool:
        """The rod's body enters an obstacle at some frame."""
        return self.rod is not None and self.rod.clearance < -self.safety_distance

    @property
    def clearance_loss(self) -> float:
        """Largest per-frame PCC clearance minus rod clearance (mm): what the mechanics take away."""
        d = self.pcc_clearance - self.rod_clearance
        return float(np.nanmax(d)) if np.any(np.isfinite(d)) else float("nan")

    @property
    def extra_margin(self) -> float:
        """Extra D_sf (mm) the result needs for D_sf to hold under the rod: max(0, -rod minimum)."""
        return float("nan") if self.rod is None else max(0.0, -self.rod.clearance)


def frames(t: np.ndarray, x: np.ndarray, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """Times (N',) and configurations (N', nx) of the waypoints and `substeps` - 1 linear in-betweens."""
    if len(t) < 2 or substeps == 1:
        return t.copy(), x.copy()
    s = np.arange(substeps) / substeps
    tt = (t[:-1, None] + s * np.diff(t)[:, None]).ravel()
    xx = (x[:-1, None, :] + s[None, :, None] * np.diff(x, axis=0)[:, None, :]).reshape(-1, x.shape[1])
    return np.append(tt, t[-1]), np.vstack([xx, x[-1:]])


def pcc_nodes_batch(model: Model, x: np.ndarray, steps: int) -> np.ndarray:
    """PCC backbone at the rod's nodes for every configuration (N, n_segments steps + 1, 3) mm, world
    frame (base translation included); `crtraj.model.cosserat.pcc_nodes` for many at once."""
    n_seg, n = model.robot.n_segments, len(x)
    fracs = np.linspace(0.0, 1.0, steps + 1)
    f = model.segment_point_function().map(n * len(fracs))
    out = np.asarray(f(np.repeat(x, len(fracs), axis=0).T, np.tile(fracs, n)))  # (3, n_seg * n * F)
    per = out.reshape(3, n, len(fracs), n_seg).transpose(1, 3, 2, 0)  # (n, seg, frac, 3)
    rows = [per[:, :1, 0]] + [per[:, k, 1:] for k in range(n_seg)]
    return np.concatenate(rows, axis=1)


def _sphere_clearances(nodes: np.ndarray, t: np.ndarray, scene: Scene, d_sf: float, body: float) -> np.ndarray:
    """Clearance (N, P, M) mm of every node to every sphere obstacle at its frame's time (NaN nodes: NaN)."""
    centers, radii = scene.states(t)  # (N, M, 3), (N, M)
    dist = np.linalg.norm(nodes[:, :, None, :] - centers[:, None, :, :], axis=-1) - radii[:, None, :]
    return margin.clearance(dist, d_sf, body)


def _shape_closest(
    ms: MovingShape, k: int, nodes: np.ndarray, t: np.ndarray, origin: float, c: np.ndarray, arcs: np.ndarray
) -> Closest:
    """Where the nodes come closest to shape k, given its per-frame clearance c (N,): the node of the worst
    frame, by the exact distance of that frame's nodes."""
    i = int(np.nanargmin(c))
    j = int(np.argmin(exact_distance(ms, nodes[i], float(t[i]) + origin)))
    return Closest(float(c[i]), i, float(t[i]), j, float(arcs[j]), k, f"shape {k} ({ms.shape.kind})")


def model_clearance(
    nodes: np.ndarray, t: np.ndarray, scene: Scene, d_sf: float, body: float, arcs: np.ndarray
) -> tuple[np.ndarray, Closest | None]:
    """(per-frame clearance (N,) mm, the closest approach) of body nodes (N, P, 3), frame i at time t[i] (s, the
    scene's clock), to every obstacle of `scene`: the spheres in closed form, every other shape (box, capsule,
    cylinder, half space, mesh, point cloud) by the verifiers' exact distance
    (`crtraj.world.geometry.exact_min_clearance`, independent of the planner's). Frames with NaN nodes (a failed
    rod solve) get NaN; +inf and a closest approach at frame 0 when there is no obstacle; None when every
    frame is NaN."""
    ok = np.all(np.isfinite(nodes), axis=(1, 2))
    per = np.where(ok, np.inf, np.nan)
    found: list[Closest] = []
    if scene.n_obstacles:
        c = _sphere_clearances(nodes, t, scene, d_sf, body)
        per = np.fmin(per, c.min(axis=(1, 2)))  # NaN stays NaN on failed frames (their c is NaN too)
        if ok.any():
            i, j, k = np.unravel_index(np.nanargmin(c), c.shape)
            found.append(Closest(float(c[i, j, k]), int(i), float(t[i]), int(j), float(arcs[j]), int(k)))
    for k, ms in enumerate(scene.shapes):
        if not ok.any():
            break
        c = np.full(len(t), np.nan)
        c[ok] = margin.clearance(exact_min_clearance(ms, nodes[ok], t[ok] + scene.time_origin), d_sf, body)
        per = np.fmin(per, c)
        found.append(_shape_closest(ms, k, nodes, t, scene.time_origin, c, arcs))
    if not ok.any():
        return per, None
    if not found:
        return per, Closest(float("inf"), 0, float(t[0]), 0, 0.0, 0)
    return per, min(found, key=lambda f: f.clearance)


def verify_cosserat(
    result: Result,
    robot: Robot,
    *,
    gravity: bool = True,
    substeps: int = 1,
    safety_distance: float | None = None,
    drive: RodDrive | None = None,
) -> Verification:
    """Re-check `result` with the Cosserat rod of `robot` (which carries [robot.mechanics]), in its actuation
    mode; drive: the rod to use instead (its own mode and gravity); see the module."""
    if result.scene is None:
        raise InputError(f"{result.source or 'result'}: records no scene; nothing to verify against")
    if not 1 <= substeps <= MAX_SUBSTEPS:
        raise InputError(f"--substeps: must be in [1, {MAX_SUBSTEPS}], got {substeps}")
    d_sf = result.scene.safety_distance if safety_distance is None else float(safety_distance)
    if not (np.isfinite(d_sf) and d_sf >= 0.0):
        raise InputError(f"--safety-distance: must be a finite number >= 0 mm, got {d_sf}")
    result.check_robot(robot, "the robot to verify with", "give --robot the robot file the result was planned with")
    start, cpu = time.perf_counter(), time.process_time()
    if drive is None:
        mech = Mechanics.from_robot(robot)
        mech = mech.with_(tolerance=max(mech.tolerance, VERIFY_TOLERANCE))
        # each solve stops as soon as its residual is within the tolerance (no polish below it)
        drive = robot_rod(robot, mech=mech, gravity=gravity, polish=1.0)
    t, x = frames(result.t, result.x, substeps)
    steps = drive.mech.steps
    arcs = np.concatenate([[0.0]] + [s.length * np.arange(1, steps + 1) / steps for s in robot.segments])
    arcs[1:] += np.repeat(np.cumsum([0.0] + [s.length for s in robot.segments[:-1]]), steps)
    pcc = pcc_nodes_batch(Model(robot), x, steps)
    nodes, failed = drive.nodes(x)
    per_pcc, pcc_closest = model_clearance(pcc, t, result.scene, d_sf, robot.body_radius, arcs)
    per_rod, rod_closest = model_clearance(nodes, t, result.scene, d_sf, robot.body_radius, arcs)  # NaN: failed
    assert pcc_closest is not None  # PCC's nodes are always finite
    angles = _goal_angles(result, robot, x[-1], nodes[-1])
    return Verification(
        t,
        per_pcc,
        per_rod,
        np.linalg.norm(pcc - nodes, axis=-1).max(axis=1),
        pcc_closest,
        rod_closest,
        int(failed.sum()),
        d_sf,
        drive.gravity,
        drive.actuation,
        time.perf_counter() - start,
        time.process_time() - cpu,
        *angles,
    )


def end_tangent(nodes: np.ndarray) -> np.ndarray:
    """Unit tangent at the last of equally spaced backbone nodes (..., P, 3), P >= 3: the second-order backward
    difference 3 p[-1] - 4 p[-2] + p[-3] (error of order h^2 times the curvature squared), normalised."""
    d = 3.0 * nodes[..., -1, :] - 4.0 * nodes[..., -2, :] + nodes[..., -3, :]
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _goal_angles(result: Result, robot: Robot, x_end: np.ndarray, rod_end: np.ndarray) -> tuple[float, float, float]:
    """(cone, PCC tip tangent angle, rod tip tangent angle) in rad at the last frame, for a result whose task has a
    direction goal; NaNs otherwise. PCC's tangent is its tip frame's z axis, the rod's the backward difference of
    its last nodes (`end_tangent`; the last segment's nodes are equally spaced)."""
    nan = float("nan")
    if result.goal_direction is None or result.goal_cone is None or result.goal is None:
        return nan, nan, nan
    goal = TipGoal.of(result.goal, result.goal_direction, result.goal_cone, prefix="task.")
    pcc = float(goal.angles(tip_tangents(Model(robot), x_end[None]))[0])
    rod = float(goal.angles(end_tangent(rod_end))) if np.all(np.isfinite(rod_end)) else nan
    return float(goal.cone or nan), pcc, rod


def planning_seconds(result: Result) -> float | None:
    """How long making the result took (s): a plan's setup plus planning, a run's planner time; None if unrecorded."""
    timing = result.data.get("timing") or {}
    keys = ("setup_s", "total_s") if result.kind == "plan" else ("planner_s",)
    vals = [timing.get(k) for k in keys]
    if any(not isinstance(v, int | float) or not np.isfinite(v) for v in vals):
        return None
    return float(sum(vals))


def _robot_for(args: argparse.Namespace, result: Result) -> Robot:
    """--robot, or the robot file of the problem the result names (its [robot.mechanics] is needed)."""
    if args.robot is not None:
        robot, who = load_robot(args.robot), f"--robot {args.robot}"
    else:
        path = (result.data.get("problem") or {}).get("path")
        if not path or not Path(path).is_file():
            raise InputError("--robot: the result names no readable problem file; give the robot TOML with --robot")
        robot, who = Problem.load(path).robot, f"the robot of {path}"
    result.check_robot(robot, who, "give --robot the robot file the result was planned with")
    return robot


def verify_command(args: argparse.Namespace) -> int:
    """`crtraj verify RESULT --model cosserat` (arguments from `crtraj.cli`); returns the exit code."""
    result = read_result(args.result)
    robot = _robot_for(args, result)
    v = verify_cosserat(
        result, robot, gravity=not args.no_gravity, substeps=args.substeps, safety_distance=args.safety_distance
    )
    n_wp = len(result.t)
    print(
        f"{args.result}: {result.kind}, {len(v.t)} frames ({n_wp} waypoints, {args.substeps} per interval), "
        f"Cosserat rod (actuation {v.actuation}) {'with' if v.gravity else 'without'} gravity, "
        f"D_sf {v.safety_distance:g} mm, "
        f"body radius {robot.body_radius:g} mm"
    )
    print(f"  PCC:      min clearance {v.pcc.text()}: D_sf {'holds' if v.pcc.clearance >= 0 else 'does not hold'}")
    if v.rod is not None:
        verdict = "holds" if v.rod.clearance >= 0 else ("CONTACT" if v.contact else "does not hold (no contact)")
        print(f"  Cosserat: min clearance {v.rod.text()}: D_sf {verdict}")
    print(
        f"  largest PCC-to-rod node distance {np.nanmax(v.discrepancy):.2f} mm; clearance lost to the mechanics "
        f"{v.clearance_loss:.2f} mm; extra D_sf this result needs {v.extra_margin:.2f} mm"
    )
    if v.failed:
        print(f"  rod solves that did not converge: {v.failed} of {len(v.t)} frames (not verified)")
    if v.has_direction:
        cone = np.degrees(v.goal_cone)
        print(
            f"  goal direction: tip tangent at the goal {np.degrees(v.pcc_goal_angle):.2f} deg (PCC), "
            f"{np.degrees(v.rod_goal_angle):.2f} deg (Cosserat) from goal_direction; cone {cone:g} deg"
        )
    took = planning_seconds(result)
    ratio = ""
    if took is not None and took > 0:
        ratio = f" ({v.seconds / took:.1f} x, {v.cpu_seconds / took:.1f} x the {took:.3f} s it took to make)"
    print(f"  verified in {v.seconds:.3f} s wall, {v.cpu_seconds:.3f} s CPU{ratio}")
    why = _failure(v, args.strict)
    if why is not None:
        print(f"crtraj: verify failed: {why}", file=sys.stderr)
        return 1
    return 0


def _failure(v: Verification, strict: bool) -> str | None:
    """Why `crtraj verify` exits 1 (one line with the fix), or None: rod contact, rod solves that did not
    converge, a direction goal's final tip tangent outside its cone under PCC, or (strict) D_sf broken or the
    tangent outside the cone under the rod."""
    more = f"re-plan with [scene] safety_distance at least {v.extra_margin:.2f} mm larger"
    cone = np.degrees(v.goal_cone)
    if v.contact and v.rod is not None:
        return f"CONTACT: under the Cosserat rod the body touches an obstacle ({v.rod.text()}); {more}"
    if v.failed:
        return (
            f"{v.failed} of {len(v.t)} rod solves did not converge, those frames are not verified; check "
            "[robot.mechanics] in the robot file (moduli, tolerance, max_iter)"
        )
    if v.has_direction and not v.pcc_goal_angle <= v.goal_cone:
        return (
            f"goal_cone: the final tip tangent is {np.degrees(v.pcc_goal_angle):.2f} deg from goal_direction under "
            f"PCC, outside the {cone:g} deg cone; re-plan the task"
        )
    if strict and not v.holds:
        where = "" if v.rod is None else f" ({v.rod.text()})"
        return f"--strict: D_sf does not hold under the Cosserat rod{where}; {more}"
    if strict and v.has_direction and not v.rod_goal_angle <= v.goal_cone:
        return (
            f"--strict: goal_cone: under the Cosserat rod the final tip tangent is {np.degrees(v.rod_goal_angle):.2f} "
            f"deg from goal_direction, outside the {cone:g} deg cone; re-plan with a narrower goal_cone"
        )
    return None
