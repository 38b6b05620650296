"""The result schema: one versioned document for plans and replan runs, written and validated here.

`crtraj plan` writes a plan document (`plan_document`), `crtraj replan` a run
document (`run_document`); both start with the same header (`header`). Every
reader (the view, the streamer's use case, the command line) goes through
`read_result`, which validates the document and returns a typed `Result`:
one-line `InputError` naming the bad field otherwise. The schema is described
in docs/architecture.md, section "Result schema". Units: mm, rad, s.

Versions: ``schema`` is `SCHEMA_VERSION`. A document without ``schema`` was
written before the field existed and is read as version 1 (the same fields).
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj import __version__
from crtraj.control.loop import ClosedLoop, ReplanRun
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, Table, check_array, check_float
from crtraj.core.fileio import read_json, to_jsonable
from crtraj.hardware.admission import MotionRecord
from crtraj.model.identity import robot_difference
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.planning.result import PlanResult
from crtraj.world.scene import MAX_OBSTACLES, Scene

SCHEMA_VERSION = 1
KINDS = ("plan", "replan")
# Largest document read: each waypoint is an animation frame of a view and a row of set-points
# (a 60 s replan run has a few thousand), each tree edge a line segment.
MAX_WAYPOINTS = 100_000
MAX_EDGES = 1_000_000
# backbone points recorded per waypoint of a run document
RUN_BACKBONE_POINTS = 21
# Most executed-actuation samples read (`executed.q`: one per control period; 5.5 h at 100 Hz).
MAX_EXECUTED = 2_000_000


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
    return {
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
    }


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
        backbone = model.points(r.configs)
        centers, radii = scene.states(r.t)
        for k in range(len(r.t)):
            waypoints.append(
                {
                    "t": float(r.t[k]),
                    "tip": r.tips[k],
                    "x": r.configs[k],
                    "q": r.cables[k],
                    "backbone": backbone[k],
                    "obstacles": {"centers": centers[k].reshape(-1, 3), "radii": radii[k].reshape(-1)},
                }
            )
    info = {"name": problem.name, "path": None if problem.path is None else str(problem.path), "seed": r.seed}
    doc = header("plan", problem=info, robot=model.robot, scene=scene, task=problem.require_task().to_dict(),
                 options=options)  # fmt: skip
    doc |= {
        "status": str(r.status),
        "success": r.is_success(),
        "message": r.message,
        "timing": {**{f"{k}_s": v for k, v in r.timings.items()}, "setup_s": setup_time},
        "summary": r.summary(),
        "waypoints": waypoints,
        "tree": {"edges": r.tree_edges},
    }
    if r.raw_configs is not None and len(r.raw_configs):
        doc["raw_path"] = {"t": r.raw_t, "x": r.raw_configs, "tip": model.tip_position(r.raw_configs)}
    if r.goal_configs is not None and len(r.goal_configs):
        doc["goal_configs"] = r.goal_configs
    return to_jsonable(doc)


def _run_waypoints(run: ReplanRun, model: Model) -> list[dict[str, Any]]:
    bb = model.points(run.x, RUN_BACKBONE_POINTS)
    wps = []
    for k in range(len(run.t)):
        w: dict[str, Any] = {
            "t": float(run.t[k]),
            "tip": run.tip[k],
            "x": run.x[k],
            "q": run.q[k],
            "q_command": run.q_command[k],
            "backbone": bb[k],
            "obstacles": {"centers": run.centers[k], "radii": run.radii[k]},
            "clearance": float(run.clearance[k]),
            "tip_error": float(run.tip_error[k]),
        }
        if k:  # the step that ended at t[k]
            w["status"] = run.step_status[k - 1]
            w["solver_status"] = run.solver_status[k - 1]
            w["nlp_time"] = float(run.nlp_time[k - 1])
            w["iteration_time"] = float(run.iter_time[k - 1])
        wps.append(w)
    return wps


def run_document(run: ReplanRun, loop: ClosedLoop, problem: Any = None, seed: int | None = None) -> dict[str, Any]:
    """A closed-loop run (kind "replan") as plain JSON data; problem: the `Problem` it ran, if any."""
    task: dict[str, Any] = {"start": run.tip[0], "goal": run.goal, "goal_tolerance": loop.goal_tolerance}
    if problem is not None and problem.task is not None:
        task = problem.task.to_dict()
    options: dict[str, Any] = {"replan": loop.options.to_dict(), "tracking": loop.tracking_options.to_dict()}
    options.update({k: v.to_dict() if hasattr(v, "to_dict") else v for k, v in loop.extra_options.items()})
    info = {
        "name": getattr(problem, "name", "replan"),
        "path": str(problem.path) if getattr(problem, "path", None) is not None else None,
        "seed": problem.seed if seed is None and problem is not None else seed,
    }
    summary = run.summary()
    doc = header("replan", problem=info, robot=loop.model.robot, scene=loop.scene, task=task, options=options)
    doc |= {
        "status": str(run.status),
        "success": run.is_success(),
        "message": run.message,
        "timing": {
            "setup_s": run.setup_time,
            "wall_s": run.wall_time,
            "median_iteration_s": summary["median_iteration_s"],
            "p90_iteration_s": summary["p90_iteration_s"],
            "planner_s": float(np.sum(run.plan_time)),
            "nlp_s": float(np.sum(run.nlp_time)),
        },
        "summary": summary,
        "nlp": run.nlp,
        "waypoints": _run_waypoints(run, loop.model),
    }
    if len(run.executed):
        # what a device is sent (`crtraj.hardware.setpoints.SetpointPath.from_executed`)
        doc["executed"] = {"t0": float(run.t[0]), "dt": run.control_dt, "q": run.executed}
    if run.feed:
        doc["feed"] = run.feed  # the live feed: counters, options, every rejected or clamped message
    if run.device:
        doc["stream"] = run.device  # the live device stream (`DeviceLink.describe`)
    if len(run.tree_edges):
        doc["tree"] = {"edges": run.tree_edges}
    refs = [{"step": int(k), "t": float(run.t[k]), "tip": tips} for k, tips in run.reference_tips]
    if refs:
        doc["reference"] = {"tip": refs[-1]["tip"]}
        doc["references"] = refs
    return to_jsonable(doc)


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
    control period, or None. source: the file it came from ("" for in-memory
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
    source: str = ""
    data: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def duration(self) -> float:
        """s from the first waypoint to the last."""
        return float(self.t[-1] - self.t[0])

    def check_robot(self, robot: Robot, who: str) -> None:
        """Refuse (one line) when this result was made for another robot than `robot`, which `who` uses."""
        diff = robot_difference(robot, self.robot)
        if diff is not None:
            raise InputError(
                f"robot: the result was made for robot '{self.robot.name}' ({self.robot.n_segments} segments, "
                f"lengths {[s.length for s in self.robot.segments]} mm, coupling {self.robot.coupling:g}), "
                f"but {who} '{robot.name}' ({diff})"
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


def _field(d: Any, key: str, where: str) -> Any:
    if not isinstance(d, Mapping):
        raise InputError(f"{where or 'result'}: expected an object, got {type(d).__name__}")
    if key not in d:
        raise InputError(f"{where + '.' if where else ''}{key}: missing (required)")
    return d[key]


def _obstacles(obs: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """Centres (m, 3) and radii (m,) of one waypoint's obstacles (mm)."""
    if not obs:
        return np.zeros((0, 3)), np.zeros(0)
    centers = _field(obs, "centers", where)
    radii = _field(obs, "radii", where)
    if isinstance(centers, list) and not centers:
        c = np.zeros((0, 3))
    else:
        c = check_array(centers, f"{where}.centers", (None, 3), limit=MAX_LENGTH)
    if c.shape[0] > MAX_OBSTACLES:
        raise InputError(f"{where}.centers: at most {MAX_OBSTACLES} obstacles, got {c.shape[0]}")
    r = check_array(radii, f"{where}.radii", (c.shape[0],), limit=MAX_LENGTH)
    if np.any(r < 0):
        raise InputError(f"{where}.radii: must be >= 0, got {r.min():g}")
    return c, r


def _actuation(q: Any, where: str, nq: int) -> np.ndarray:
    """One waypoint's actuation (nq,) mm; NaN is written as null by `to_jsonable` and refused here."""
    if not isinstance(q, list) or len(q) != nq:
        got = len(q) if isinstance(q, list) else type(q).__name__
        raise InputError(f"{where}: expected {nq} values (3 cables per segment, then z), got {got}")
    for i, v in enumerate(q):
        if v is None:
            raise InputError(f"{where}[{i}]: must be finite, got null/NaN")
        check_float(v, f"{where}[{i}]", limit=MAX_LENGTH)
    return np.asarray(q, dtype=float)


def _waypoints(wps: Any, nx: int, nq: int) -> tuple[np.ndarray, ...]:
    """(t, x, tip, q or None, centers, radii) of the waypoint list; errors name waypoints[k].field."""
    if not isinstance(wps, list) or not wps:
        raise InputError("waypoints: expected a non-empty list of waypoints")
    if len(wps) > MAX_WAYPOINTS:
        raise InputError(f"waypoints: at most {MAX_WAYPOINTS} are read, got {len(wps)}")
    n = len(wps)
    t, x, tip = np.empty(n), np.empty((n, nx)), np.full((n, 3), np.nan)
    has_q = isinstance(wps[0], Mapping) and wps[0].get("q") is not None
    q = np.empty((n, nq)) if has_q else None
    centers: list[np.ndarray] = []
    radii: list[np.ndarray] = []
    for i, w in enumerate(wps):
        where = f"waypoints[{i}]"
        t[i] = check_float(_field(w, "t", where), f"{where}.t", limit=MAX_TIME)
        if i and t[i] < t[i - 1]:
            raise InputError(f"{where}.t: time goes backwards ({t[i]:g} s after {t[i - 1]:g} s)")
        x[i] = check_array(_field(w, "x", where), f"{where}.x", (nx,), limit=MAX_LENGTH)
        if w.get("tip") is not None:
            tip[i] = check_array(w["tip"], f"{where}.tip", (3,), limit=MAX_LENGTH)
        if q is not None:
            q[i] = _actuation(_field(w, "q", where), f"{where}.q", nq)
        c, r = _obstacles(w.get("obstacles"), f"{where}.obstacles")
        if centers and c.shape[0] != centers[0].shape[0]:
            raise InputError(f"{where}.obstacles: {c.shape[0]} obstacles, but waypoints[0] has {centers[0].shape[0]}")
        centers.append(c)
        radii.append(r)
    return t, x, tip, q, np.stack(centers), np.stack(radii)


def _extras(doc: Mapping[str, Any]) -> dict[str, Any]:
    """Task tips, the tracked reference path and the planner tree (each optional)."""
    out: dict[str, Any] = {"start": None, "goal": None, "reference": None, "edges": None}
    task = doc.get("task") or {}
    if isinstance(task, Mapping):
        for key in ("start", "goal"):
            if task.get(key) is not None:
                out[key] = check_array(task[key], f"task.{key}", (3,), limit=MAX_LENGTH)
    ref = doc.get("reference")
    if ref:
        reference = check_array(_field(ref, "tip", "reference"), "reference.tip", (None, 3), limit=MAX_LENGTH)
        if reference.shape[0] > MAX_WAYPOINTS:
            raise InputError(f"reference.tip: at most {MAX_WAYPOINTS} points are read, got {reference.shape[0]}")
        out["reference"] = reference
    tree = doc.get("tree")
    if tree:
        raw_edges = _field(tree, "edges", "tree")
        if not isinstance(raw_edges, list):
            raise InputError("tree.edges: expected a list of [[x, y, z], [x, y, z]] pairs (mm)")
        if len(raw_edges) > MAX_EDGES:
            raise InputError(f"tree.edges: at most {MAX_EDGES} are read, got {len(raw_edges)}")
        if raw_edges:
            out["edges"] = check_array(raw_edges, "tree.edges", (None, 2, 3), limit=MAX_LENGTH)
    return out


def _executed(doc: Mapping[str, Any], nq: int) -> tuple[float, float, np.ndarray] | None:
    """A run's optional executed actuation: (t0 s, dt s, q (M, nq) mm), or None."""
    ex = doc.get("executed")
    if ex is None:
        return None
    t0 = check_float(_field(ex, "t0", "executed"), "executed.t0", limit=MAX_TIME)
    dt = check_float(_field(ex, "dt", "executed"), "executed.dt", gt=0.0, le=10.0)
    raw = _field(ex, "q", "executed")
    if not isinstance(raw, list) or not raw:
        raise InputError("executed.q: expected a non-empty list of actuation rows (mm)")
    if len(raw) > MAX_EXECUTED:
        raise InputError(f"executed.q: at most {MAX_EXECUTED} rows are read, got {len(raw)}")
    return t0, dt, check_array(raw, "executed.q", (None, nq), limit=MAX_LENGTH)


def _kind_and_schema(doc: Mapping[str, Any]) -> tuple[str, int]:
    schema = doc.get("schema", 1)  # documents written before the field existed are version 1
    if isinstance(schema, bool) or not isinstance(schema, int) or schema != SCHEMA_VERSION:
        raise InputError(f"schema: unsupported version {schema!r} (this crtraj reads version {SCHEMA_VERSION})")
    kind = doc.get("kind", "plan") if "schema" not in doc else _field(doc, "kind", "")
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
        doc = read_json(src)
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
    robot = Robot.from_table(Table(_field(doc, "robot", ""), "robot"))
    raw_scene = doc.get("scene")
    if raw_scene is not None and not isinstance(raw_scene, Mapping):
        raise InputError(f"scene: expected an object, got {type(raw_scene).__name__}")
    scene = Scene.from_table(Table(raw_scene, "scene")) if raw_scene is not None else None
    workspace = None
    if isinstance(raw_scene, Mapping) and "workspace" in raw_scene and scene is not None:
        workspace = (np.array(scene.workspace_lo), np.array(scene.workspace_hi))
    t, x, tip, q, centers, radii = _waypoints(_field(doc, "waypoints", ""), robot.nx, robot.nq)
    return Result(
        kind=kind, schema=schema, robot=robot, scene=scene, **_verdict(doc, kind), t=t, x=x, tip=tip, q=q,
        centers=centers, radii=radii, **_extras(doc), workspace=workspace, executed=_executed(doc, robot.nq),
        source=source, data=doc,
    )  # fmt: skip
