"""The result schema: one versioned document for plans and replan runs, written and validated here.

`crtraj plan` writes a plan document (`plan_document`), `crtraj replan` a run
document (`run_document`); both start with the same header (`header`). Every
reader (the view, the streamer's use case, the command line) goes through
`read_result`, which validates the document and returns a typed `Result`:
one-line `InputError` naming the bad field otherwise. Every field is declared
once in `crtraj.io.run_schema` (key, unit, shape, meaning, its writer's getter and
its reader's check); the docs table comes from there too. Units: mm, rad, s.

Versions: ``schema`` is `SCHEMA_VERSION`. A document without ``schema`` was
written before the field existed and is read as version 1 (the same fields).
"""

from __future__ import annotations

import datetime
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj import __version__
from crtraj.control.loop import ReplanRun
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import read_json, to_jsonable
from crtraj.hardware.admission import MotionRecord
from crtraj.io import run_schema as rs
from crtraj.model.identity import robot_mismatch
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.planning.result import PlanResult
from crtraj.world.scene import Scene

SCHEMA_VERSION = 1
KINDS = ("plan", "replan")
MAX_WAYPOINTS, MAX_EDGES, MAX_EXECUTED = rs.MAX_WAYPOINTS, rs.MAX_EDGES, rs.MAX_EXECUTED
# backbone points recorded per waypoint of a run document
RUN_BACKBONE_POINTS = 21


# ------------------------------------------------------------------ writing
def header(
    kind: str,
    *,
    problem: Mapping[str, Any],
    robot: Robot,
    scene: Scene,
    task: Mapping[str, Any],
    options: Mapping[str, Any],
) -> dict[str, Any]:
    """The fields every result document starts with: kind, schema, versions, creation time (UTC),
    problem ``{name, path, seed}``, robot, scene, task and the options that made it."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    return rs.compose(
        rs.HEADER,
        {
            "kind": kind,
            "schema": SCHEMA_VERSION,
            "crtraj_version": __version__,
            "casadi_version": ca.__version__,
            "numpy_version": np.__version__,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "problem": dict(problem),
            "robot": robot.to_dict(),
            "scene": scene.to_dict(),
            "task": dict(task),
            "options": dict(options),
        },
    )


@dataclass(frozen=True)
class _PlanSource:
    """What a plan's waypoint fields are read from: the result, its backbone points and obstacle states."""

    result: PlanResult
    backbone: np.ndarray
    centers: np.ndarray
    radii: np.ndarray

    def obstacles(self, k: int) -> dict[str, np.ndarray]:
        return {"centers": self.centers[k].reshape(-1, 3), "radii": self.radii[k].reshape(-1)}


@dataclass(frozen=True)
class _RunSource:
    """What a run's waypoint fields are read from: the run record and its backbone points."""

    run: ReplanRun
    backbone: np.ndarray

    def obstacles(self, k: int) -> dict[str, np.ndarray]:
        return {"centers": self.run.centers[k], "radii": self.run.radii[k]}


def plan_document(
    problem: Any,
    model: Model,
    scene: Scene,
    result: PlanResult,
    options: Mapping[str, Any],
    setup_time: float,
) -> dict[str, Any]:
    """A plan (kind "plan") as plain JSON data: per waypoint t, tip, x, q, backbone and obstacles.

    problem: the `crtraj.io.problem.Problem` planned. options: the options used,
    by section (``{"planner": ..., "steer": ...}``). setup_time: s.
    """
    r = result
    waypoints = []
    if len(r.t):
        centers, radii = scene.states(r.t)
        src = _PlanSource(r, model.points(r.configs), centers, radii)
        waypoints = [rs.write_fields(rs.PLAN_WAYPOINT, src, k) for k in range(len(r.t))]
    info = {"name": problem.name, "path": None if problem.path is None else str(problem.path), "seed": r.seed}
    doc = header("plan", problem=info, robot=model.robot, scene=scene, task=problem.require_task().to_dict(),
                 options=options)  # fmt: skip
    raw = None
    if r.raw_configs is not None and len(r.raw_configs):
        raw = {"t": r.raw_t, "x": r.raw_configs, "tip": model.tip_position(r.raw_configs)}
    goal_configs = r.goal_configs if r.goal_configs is not None and len(r.goal_configs) else None
    timing = {**{f"{k}_s": v for k, v in r.timings.items()}, "setup_s": setup_time}
    doc |= rs.compose(rs.VERDICT, _verdict_values(r.status, r.is_success(), r.message, r.summary(), timing))
    doc |= rs.compose(
        rs.PLAN_BODY,
        {"waypoints": waypoints, "tree": {"edges": r.tree_edges}, "raw_path": raw, "goal_configs": goal_configs},
    )
    return to_jsonable(doc)


def _verdict_values(status: Any, success: bool, message: str, summary: Any, timing: Any) -> dict[str, Any]:
    return {"status": str(status), "success": success, "message": message, "timing": timing, "summary": summary}


@dataclass(frozen=True)
class RunContext:
    """Plain data a run document records beside the run: the robot model (for the backbone points), the
    scene, the task's goal tolerance (mm), and the option sections by name (objects with ``to_dict``)."""

    model: Model
    scene: Scene
    goal_tolerance: float
    options: Mapping[str, Any]


def run_document(run: ReplanRun, context: RunContext, problem: Any = None, seed: int | None = None) -> dict[str, Any]:
    """A closed-loop run (kind "replan") as plain JSON data; problem: the `Problem` it ran, if any."""
    task: dict[str, Any] = {"start": run.tip[0], "goal": run.goal, "goal_tolerance": context.goal_tolerance}
    if problem is not None and problem.task is not None:
        task = problem.task.to_dict()
    options = {k: v.to_dict() if hasattr(v, "to_dict") else v for k, v in context.options.items()}
    info = {
        "name": getattr(problem, "name", "replan"),
        "path": str(problem.path) if getattr(problem, "path", None) is not None else None,
        "seed": problem.seed if seed is None and problem is not None else seed,
    }
    summary = run.summary()
    doc = header("replan", problem=info, robot=context.model.robot, scene=context.scene, task=task, options=options)
    timing = {
        "setup_s": run.setup_time,
        "wall_s": run.wall_time,
        "median_iteration_s": summary["median_iteration_s"],
        "p90_iteration_s": summary["p90_iteration_s"],
        "planner_s": float(np.sum(run.plan_time)),
        "nlp_s": float(np.sum(run.nlp_time)),
    }
    doc |= rs.compose(rs.VERDICT, _verdict_values(run.status, run.is_success(), run.message, summary, timing))
    src = _RunSource(run, context.model.points(run.x, RUN_BACKBONE_POINTS))
    plant = _plant(run.device, summary)
    refs = [{"step": int(k), "t": float(run.t[k]), "tip": tips} for k, tips in run.reference_tips]
    body = {
        "nlp": run.nlp,
        "waypoints": [rs.write_fields(rs.RUN_WAYPOINT, src, k, first=k == 0) for k in range(len(run.t))],
        # what a device is sent (`crtraj.hardware.setpoints.SetpointPath.from_executed`)
        "executed": {"t0": float(run.t[0]), "dt": run.control_dt, "q": run.executed} if len(run.executed) else None,
        "feed": run.feed or None,  # the live feed: counters, options, every rejected or clamped message
        "stream": None if plant else run.device or None,  # the live device stream (`DeviceLink.describe`)
        "plant": plant,  # a simulated plant (`crtraj.control.rod_plant.RodPlant.describe`)
        "tree": {"edges": run.tree_edges} if len(run.tree_edges) else None,
        "reference": {"tip": refs[-1]["tip"]} if refs else None,
        "references": refs or None,
    }
    doc |= rs.compose(rs.RUN_BODY, body)
    return to_jsonable(doc)


def _plant(device: dict[str, Any], summary: dict[str, Any]) -> dict[str, Any] | None:
    """A simulated plant's report (`rs.PLANT`) with PCC's own view of the run beside it; None for a
    live device or none."""
    if not device or device.get("kind") != "plant":
        return None
    keys = ("final_tip_error_mm", "min_clearance_mm", "collisions", "safety_violations", "reached_goal")
    return rs.compose(rs.PLANT, {**device, "pcc": {k: summary[k] for k in keys}})


# ------------------------------------------------------------------ reading
@dataclass(frozen=True)
class Result:
    """A validated result document (mm, s). Build it with `read_result`.

    kind: "plan" or "replan". schema: its schema version. robot, scene (None
    when the document has none). status, success, message: its verdict.
    safety: False for a run made without the collision-free terms.
    collisions, safety_violations: steps that touched an obstacle / came
    closer than D_sf (from the summary). t (N,) non-decreasing; x (N, nx);
    tip (N, 3) with NaN rows where the document gives none; q (N, nq) or None
    when no waypoint records the actuation; centers (N, m, 3), radii (N, m):
    obstacle states per waypoint. start, goal: task tips or None. reference
    (M, 3): the planned path a run tracked, or None. edges (E, 2, 3): planner
    tree, or None. workspace: (lo, hi) when the scene records one. executed:
    a run's actual actuation (t0 s, period s, q (M, nq) mm), one sample per
    control period, or None. goal_direction (3,) unit and goal_cone (deg): the
    task's tip direction goal, or None. source: the file it came from ("" for in-memory
    data). data: the document itself.
    """

    kind: str
    schema: int
    robot: Robot
    scene: Scene | None
    status: str
    success: bool
    message: str
    safety: bool
    collisions: int
    safety_violations: int
    t: np.ndarray
    x: np.ndarray
    tip: np.ndarray
    q: np.ndarray | None
    centers: np.ndarray
    radii: np.ndarray
    start: np.ndarray | None
    goal: np.ndarray | None
    reference: np.ndarray | None
    edges: np.ndarray | None
    workspace: tuple[np.ndarray, np.ndarray] | None
    executed: tuple[float, float, np.ndarray] | None = None
    goal_direction: np.ndarray | None = None
    goal_cone: float | None = None
    source: str = ""
    data: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def duration(self) -> float:
        """s from the first waypoint to the last."""
        return float(self.t[-1] - self.t[0])

    def check_robot(self, robot: Robot, who: str, fix: str) -> None:
        """Refuse (one line) when this result was made for another robot than `robot`, which `who` (a phrase:
        "--robot cdsr2.toml") names; the line gives both robots' value of the first field that differs, and
        `fix`, what to change."""
        diff = robot_mismatch(robot, self.robot)
        if diff is not None:
            field, theirs, ours = diff
            raise InputError(
                f"robot: {self.source or 'the result'} was made for robot '{self.robot.name}' ({field} {theirs}), "
                f"but {who} is robot '{robot.name}' ({field} {ours}); {fix}"
            )

    def motion_record(self) -> MotionRecord:
        """What `crtraj.hardware.admission.admit` needs to admit or refuse this result: the waypoints'
        actuation, or a run's executed actuation (one sample per control period) when it records one."""
        t, q, period = self.t, self.q, None
        if self.executed is not None:
            t0, period, q = self.executed
            t = t0 + period * np.arange(len(q))
        return MotionRecord(
            source=self.source,
            kind=self.kind,
            status=self.status,
            success=self.success,
            safety=self.safety,
            collisions=self.collisions,
            safety_violations=self.safety_violations,
            robot=self.robot,
            scene=self.scene,
            t=t,
            q=q,
            period=period,
        )


def _waypoints(wps: Any, nx: int, nq: int) -> tuple[np.ndarray, ...]:
    """(t, x, tip, q or None, centers, radii) of the waypoint list; errors name waypoints[k].field."""
    if not isinstance(wps, list) or not wps:
        raise InputError("waypoints: expected a non-empty list of waypoints")
    if len(wps) > MAX_WAYPOINTS:
        raise InputError(f"waypoints: at most {MAX_WAYPOINTS} are read, got {len(wps)}")
    n, dims = len(wps), {"nx": nx, "nq": nq}
    t, x, tip = np.empty(n), np.empty((n, nx)), np.full((n, 3), np.nan)
    has_q = isinstance(wps[0], Mapping) and wps[0].get("q") is not None
    q = np.empty((n, nq)) if has_q else None
    centers: list[np.ndarray] = []
    radii: list[np.ndarray] = []
    for i, w in enumerate(wps):
        where = f"waypoints[{i}]"
        v = rs.read_fields(w, rs.PLAN_WAYPOINT, where, dims)  # the fields every waypoint shares
        t[i], x[i] = v["t"], v["x"]
        if i and t[i] < t[i - 1]:
            raise InputError(f"{where}.t: time goes backwards ({t[i]:g} s after {t[i - 1]:g} s)")
        if "tip" in v:
            tip[i] = v["tip"]
        if q is not None:
            if "q" not in v:
                raise rs.missing("q", where)
            q[i] = v["q"]
        c, r = v.get("obstacles", (np.zeros((0, 3)), np.zeros(0)))
        if centers and c.shape[0] != centers[0].shape[0]:
            raise InputError(f"{where}.obstacles: {c.shape[0]} obstacles, but waypoints[0] has {centers[0].shape[0]}")
        centers.append(c)
        radii.append(r)
    return t, x, tip, q, np.stack(centers), np.stack(radii)


def _extras(doc: Mapping[str, Any]) -> dict[str, Any]:
    """Task tips, the tracked reference path and the planner tree (each optional)."""
    out: dict[str, Any] = {"start": None, "goal": None, "reference": None, "edges": None}
    out |= {"goal_direction": None, "goal_cone": None}
    task = doc.get("task") or {}
    if isinstance(task, Mapping):
        out.update(rs.read_fields(task, rs.TASK, "task", {}))
    ref = doc.get("reference")
    if ref:
        out["reference"] = rs.read_fields(ref, rs.REFERENCE, "reference", {})["tip"]
    tree = doc.get("tree")
    if tree:
        out["edges"] = rs.read_fields(tree, rs.TREE, "tree", {})["edges"]
    return out


def _executed(doc: Mapping[str, Any], nq: int) -> tuple[float, float, np.ndarray] | None:
    """A run's optional executed actuation: (t0 s, dt s, q (M, nq) mm), or None."""
    ex = doc.get("executed")
    if ex is None:
        return None
    v = rs.read_fields(ex, rs.EXECUTED, "executed", {"nq": nq})
    return v["t0"], v["dt"], v["q"]


def _kind_and_schema(doc: Mapping[str, Any]) -> tuple[str, int]:
    schema = doc.get("schema", 1)  # documents written before the field existed are version 1
    if isinstance(schema, bool) or not isinstance(schema, int) or schema != SCHEMA_VERSION:
        raise InputError(f"schema: unsupported version {schema!r} (this crtraj reads version {SCHEMA_VERSION})")
    kind = doc.get("kind", "plan") if "schema" not in doc else rs.field_of(doc, "kind", "")
    if kind not in KINDS:
        raise InputError(f"kind: must be plan or replan, got {kind!r}")
    return kind, schema


def _verdict(doc: Mapping[str, Any], kind: str) -> dict[str, Any]:
    """status, success, message, safety, collisions and safety_violations of a document."""
    success = doc.get("success", False)
    if not isinstance(success, bool):
        raise InputError(f"success: expected true or false, got {success!r}")
    summary = doc.get("summary") or {}
    if not isinstance(summary, Mapping):
        raise InputError(f"summary: expected an object, got {type(summary).__name__}")
    counts = {}
    for key in ("collisions", "safety_violations"):
        v = summary.get(key, 0)
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise InputError(f"summary.{key}: expected a count >= 0, got {v!r}")
        counts[key] = v
    if kind == "plan":
        # a plan records its smallest clearance beyond D_sf; below zero it breaks the safety distance
        clear = summary.get("min_clearance_mm")
        if isinstance(clear, (int, float)) and not isinstance(clear, bool) and math.isfinite(clear) and clear < 0:
            counts["safety_violations"] = max(counts["safety_violations"], 1)
    safety = summary.get("safety", True)
    replan = (doc.get("options") or {}).get("replan") if isinstance(doc.get("options"), Mapping) else None
    if isinstance(replan, Mapping) and replan.get("safety") is False:
        safety = False
    if not isinstance(safety, bool):
        raise InputError(f"summary.safety: expected true or false, got {safety!r}")
    status, message = doc.get("status", "unknown"), doc.get("message", "")
    return {"status": str(status)[:200], "success": success, "message": str(message)[:2000], "safety": safety,
            **counts}  # fmt: skip


def shape_files_moved(doc: Any, move: Any) -> Any:
    """A copy of the result document `doc` whose ``scene.shape`` data files (a mesh's, a cloud's) are
    ``move(file)``, for each relative one (`relative_shape_files` wrote them so); `doc` itself when it has none."""
    scene = doc.get("scene") if isinstance(doc, Mapping) else None
    shapes = scene.get("shape") if isinstance(scene, Mapping) else None
    if not isinstance(shapes, list) or not any(
        isinstance(s, Mapping) and isinstance(s.get("file"), str) for s in shapes
    ):
        return doc
    out = []
    for st in shapes:
        f = st.get("file") if isinstance(st, Mapping) else None
        out.append({**st, "file": move(f)} if isinstance(f, str) and f and not Path(f).is_absolute() else st)
    return {**doc, "scene": {**scene, "shape": out}}


def relative_shape_files(doc: Mapping[str, Any], folder: str | Path) -> Any:
    """A copy of the result document `doc` to be written into `folder`, its shapes' data files given relative to
    that folder (so the result moves with its folder and the data beside it); `read_result` of the file makes
    them absolute again."""
    base = Path(folder).resolve()

    def rel(f: str) -> str:
        return Path(os.path.relpath(Path(f).resolve(), base)).as_posix()

    scene = doc.get("scene")
    shapes = scene.get("shape") if isinstance(scene, Mapping) else None
    if not isinstance(shapes, list):
        return doc
    out = [{**st, "file": rel(st["file"])} if isinstance(st.get("file"), str) and st["file"] else st for st in shapes]
    return {**doc, "scene": {**scene, "shape": out}}


def read_result(src: Mapping[str, Any] | str | Path | Result) -> Result:
    """Read and validate a result document: a file path, its parsed JSON, or a `Result` (returned as is).

    Raises `InputError` with one line naming the field (prefixed with the file
    name for a file) when the document does not follow the schema.
    """
    if isinstance(src, Result):
        return src
    source = ""
    doc: Any = src
    if not isinstance(src, Mapping):
        source = str(src)
        doc = shape_files_moved(read_json(src), lambda f: str(Path(src).parent / f))
    try:
        return _parse(doc, source)
    except InputError as exc:
        if source and not str(exc).startswith(source):
            raise InputError(f"{source}: {exc}") from None
        raise


def _parse(doc: Any, source: str) -> Result:
    if not isinstance(doc, Mapping):
        raise InputError(f"result: expected a JSON object (a crtraj plan/replan result), got {type(doc).__name__}")
    kind, schema = _kind_and_schema(doc)
    robot = Robot.from_table(Table(rs.field_of(doc, "robot", ""), "robot"))
    raw_scene = doc.get("scene")
    if raw_scene is not None and not isinstance(raw_scene, Mapping):
        raise InputError(f"scene: expected an object, got {type(raw_scene).__name__}")
    scene = Scene.from_table(Table(raw_scene, "scene")) if raw_scene is not None else None
    workspace = None
    if isinstance(raw_scene, Mapping) and "workspace" in raw_scene and scene is not None:
        workspace = (np.array(scene.workspace_lo), np.array(scene.workspace_hi))
    t, x, tip, q, centers, radii = _waypoints(rs.field_of(doc, "waypoints", ""), robot.nx, robot.nq)
    return Result(
        kind=kind, schema=schema, robot=robot, scene=scene, **_verdict(doc, kind), t=t, x=x, tip=tip, q=q,
        centers=centers, radii=radii, **_extras(doc), workspace=workspace, executed=_executed(doc, robot.nq),
        source=source, data=doc,
    )  # fmt: skip
