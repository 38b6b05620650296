"""The result files' schema, declared once: every field of a plan or run document (``plan.json``,
``run.json``) and of a run's arrays (``run.npz``), with its key, unit, shape or type and meaning.

From these declarations come the writers (`crtraj.io.results.plan_document`, `run_document` and
`crtraj.io.run_files.save_npz` take each field's value from its getter, in the declared order), the
readers (`crtraj.io.results.read_result` and `crtraj.io.run_files.read_npz` validate each field with its
reader: a missing or malformed field is one `InputError` naming its key) and the documentation table
(`schema_table_markdown`). Units: mm, rad, s; non-finite numbers are written as JSON ``null``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, check_array, check_float
from crtraj.world.scene import MAX_OBSTACLES

# Largest document read: each waypoint is an animation frame of a view and a row of set-points
# (a 60 s replan run has a few thousand), each tree edge a line segment.
MAX_WAYPOINTS = 100_000
MAX_EDGES = 1_000_000
# Most executed-actuation samples read (`executed.q`: one per control period; 5.5 h at 100 Hz).
MAX_EXECUTED = 2_000_000

# the sizes a field's shape names: nx configuration, nq actuation, m obstacles, P backbone points,
# K steps of a run, S verification samples, E tree edges
Dims = Mapping[str, int]


@dataclass(frozen=True)
class Field:
    """One field of a result file.

    key: its name in the file. unit: "mm", "s", "rad/mm" (a configuration), "" (none). shape: its shape
    (array) or JSON type. description: what it means. required: a reader refuses a file without it.
    get: the writer's value of the field from its source (None: written by the caller, e.g. a header
    field). read: the reader's check of a raw value (raw, where, dims) -> value, raising a one-line
    `InputError` naming `where` (None: not read back). step: a run waypoint's field that only the
    waypoints after the first carry (the step that ended there).
    """

    key: str
    unit: str
    shape: str
    description: str
    required: bool = False
    get: Callable[..., Any] | None = None
    read: Callable[[Any, str, Dims], Any] | None = None
    step: bool = False


def missing(key: str, where: str) -> InputError:
    """The one-line error of a required field that is not there."""
    return InputError(f"{where + '.' if where else ''}{key}: missing (required)")


def field_of(d: Any, key: str, where: str) -> Any:
    """d[key] of the object d at `where`; one-line `InputError` when d is no object or lacks the key."""
    if not isinstance(d, Mapping):
        raise InputError(f"{where or 'result'}: expected an object, got {type(d).__name__}")
    if key not in d:
        raise missing(key, where)
    return d[key]


def read_fields(d: Any, fields: tuple[Field, ...], where: str, dims: Dims) -> dict[str, Any]:
    """The values of every readable field of object `d` (at `where`), by key: a required one that is
    missing raises, an optional one that is missing or null is left out."""
    if not isinstance(d, Mapping):
        raise InputError(f"{where or 'result'}: expected an object, got {type(d).__name__}")
    out: dict[str, Any] = {}
    for f in fields:
        if f.read is None:
            continue
        name = f"{where}.{f.key}" if where else f.key
        if d.get(f.key) is None:
            if f.required:
                raise missing(f.key, where)
            continue
        out[f.key] = f.read(d[f.key], name, dims)
    return out


def write_fields(fields: tuple[Field, ...], *source: Any, first: bool = False) -> dict[str, Any]:
    """The object of `fields` in their order, each from its getter applied to `source`; a step field is
    left out of the first waypoint (`first`)."""
    return {f.key: f.get(*source) for f in fields if f.get is not None and not (f.step and first)}


def compose(fields: tuple[Field, ...], values: Mapping[str, Any]) -> dict[str, Any]:
    """The object of `values` in the order of `fields`; an optional field whose value is None is left
    out. A key the schema does not describe, or a missing required one, is a writer's bug (ValueError)."""
    unknown = set(values) - {f.key for f in fields}
    if unknown:
        raise ValueError(f"not in the result schema: {sorted(unknown)}")
    out: dict[str, Any] = {}
    for f in fields:
        v = values.get(f.key)
        if v is None and f.required:
            raise ValueError(f"{f.key}: required by the result schema")
        if v is not None:
            out[f.key] = v
    return out


# ------------------------------------------------------------------ readers of one value
def read_time(v: Any, where: str, dims: Dims) -> float:
    return check_float(v, where, limit=MAX_TIME)


def read_direction(v: Any, where: str, dims: Dims) -> np.ndarray:
    a = check_array(v, where, (3,))
    if abs(float(np.linalg.norm(a)) - 1.0) > 1e-6:
        raise InputError(f"{where}: expected a unit vector, got length {float(np.linalg.norm(a)):g}")
    return a


def read_cone(v: Any, where: str, dims: Dims) -> float:
    return check_float(v, where, gt=0.0, le=180.0)


def read_config(v: Any, where: str, dims: Dims) -> np.ndarray:
    return check_array(v, where, (dims["nx"],), limit=MAX_LENGTH)


def read_point(v: Any, where: str, dims: Dims) -> np.ndarray:
    return check_array(v, where, (3,), limit=MAX_LENGTH)


def read_actuation(q: Any, where: str, dims: Dims) -> np.ndarray:
    """One actuation (nq,) mm; NaN is written as null by `to_jsonable` and refused here."""
    nq = dims["nq"]
    if not isinstance(q, list) or len(q) != nq:
        got = len(q) if isinstance(q, list) else type(q).__name__
        raise InputError(f"{where}: expected {nq} values (3 cables per segment, then z), got {got}")
    for i, v in enumerate(q):
        if v is None:
            raise InputError(f"{where}[{i}]: must be finite, got null/NaN")
        check_float(v, f"{where}[{i}]", limit=MAX_LENGTH)
    return np.asarray(q, dtype=float)


def read_obstacles(obs: Any, where: str, dims: Dims) -> tuple[np.ndarray, np.ndarray]:
    """Centres (m, 3) and radii (m,) of one waypoint's obstacles (mm)."""
    if not obs:
        return np.zeros((0, 3)), np.zeros(0)
    centers = field_of(obs, "centers", where)
    radii = field_of(obs, "radii", where)
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


def read_polyline(v: Any, where: str, dims: Dims) -> np.ndarray:
    pts = check_array(v, where, (None, 3), limit=MAX_LENGTH)
    if pts.shape[0] > MAX_WAYPOINTS:
        raise InputError(f"{where}: at most {MAX_WAYPOINTS} points are read, got {pts.shape[0]}")
    return pts


def read_edges(raw: Any, where: str, dims: Dims) -> np.ndarray | None:
    if not isinstance(raw, list):
        raise InputError(f"{where}: expected a list of [[x, y, z], [x, y, z]] pairs (mm)")
    if len(raw) > MAX_EDGES:
        raise InputError(f"{where}: at most {MAX_EDGES} are read, got {len(raw)}")
    return check_array(raw, where, (None, 2, 3), limit=MAX_LENGTH) if raw else None


def read_period(v: Any, where: str, dims: Dims) -> float:
    return check_float(v, where, gt=0.0, le=10.0)


def read_executed_q(raw: Any, where: str, dims: Dims) -> np.ndarray:
    if not isinstance(raw, list) or not raw:
        raise InputError(f"{where}: expected a non-empty list of actuation rows (mm)")
    if len(raw) > MAX_EXECUTED:
        raise InputError(f"{where}: at most {MAX_EXECUTED} rows are read, got {len(raw)}")
    return check_array(raw, where, (None, dims["nq"]), limit=MAX_LENGTH)


def _step(name: str, cast: Callable[[Any], Any]) -> Callable[[Any, int], Any]:
    """The getter of a run's per-step array `name` at waypoint k (the step that ended at t[k])."""
    return lambda src, k: cast(getattr(src.run, name)[k - 1])


def _at(name: str, cast: Callable[[Any], Any] = lambda v: v) -> Callable[[Any, int], Any]:
    """The getter of a run's per-time array `name` at waypoint k."""
    return lambda src, k: cast(getattr(src.run, name)[k])


# ------------------------------------------------------------------ the documents
CONFIG = "rad/mm"  # a configuration: bending vectors (rad) per segment, then z (mm)

HEADER = (
    Field("kind", "", "string", '"plan" or "replan" (required when `schema` is present)'),
    Field("schema", "", "int", "schema version (`crtraj.io.results.SCHEMA_VERSION`)"),
    Field("crtraj_version", "", "string", "the crtraj that wrote it"),
    Field("casadi_version", "", "string", "the CasADi that wrote it"),
    Field("numpy_version", "", "string", "the numpy that wrote it"),
    Field("created", "", "string", "UTC time of writing, ISO 8601, seconds"),
    Field("problem", "", "object", "`{name, path, seed}` of the problem file (path null for one built in Python)"),
    Field("robot", "", "object", "the robot, as the `[robot]` table of a robot file", required=True),
    Field("scene", "", "object", "the scene, as the `[scene]` table (obstacles with their time functions)"),
    Field("task", "mm", "object", "the task, as the `[task]` table (`start`, `goal`, `goal_tolerance`, ...)"),
    Field("options", "", "object", "the options that made it, by section (`planner`, `steer`; `replan`, ...)"),
)

VERDICT = (
    Field("status", "", "string", "the planner's or the loop's status word"),
    Field("success", "", "bool", "reached the goal safely"),
    Field("message", "", "string", "why it ended so"),
    Field("timing", "s", "object", "times of the parts (`*_s`)"),
    Field("summary", "", "object", "headline figures (`safety`, `collisions`, `safety_violations`, ...)"),
)

TASK = (
    Field("start", "mm", "(3,)", "start tip", read=read_point),
    Field("goal", "mm", "(3,)", "goal tip", read=read_point),
    Field("goal_direction", "", "(3,)", "unit direction the tip tangent keeps at the goal", read=read_direction),
    Field("goal_cone", "deg", "float", "largest angle of the tip tangent to `goal_direction`", read=read_cone),
)

# a plan's `summary` figures of a direction goal (`crtraj.planning.result.PlanResult.summary`)
SUMMARY = (
    Field("goal_error_mm", "mm", "float", "final tip to the goal"),
    Field("goal_angle_deg", "deg", "float", "final tip tangent to `task.goal_direction` (a direction goal only)"),
)

OBSTACLES = (
    Field("centers", "mm", "(m, 3)", "obstacle centres at the waypoint's t"),
    Field("radii", "mm", "(m,)", "obstacle radii at the waypoint's t"),
)

PLAN_WAYPOINT = (
    Field("t", "s", "float", "time, non-decreasing", True, lambda s, k: float(s.result.t[k]), read_time),
    Field("tip", "mm", "(3,)", "tip position", get=lambda s, k: s.result.tips[k], read=read_point),
    Field("x", CONFIG, "(nx,)", "configuration", True, lambda s, k: s.result.configs[k], read_config),
    Field(
        "q",
        "mm",
        "(nq,)",
        "actuation: 3 cable lengths per segment, then z",
        get=lambda s, k: s.result.cables[k],
        read=read_actuation,
    ),
    Field("backbone", "mm", "(P, 3)", "points along the body", get=lambda s, k: s.backbone[k]),
    Field(
        "obstacles",
        "mm",
        "object",
        "`centers`, `radii` (same m at every waypoint)",
        get=lambda s, k: s.obstacles(k),
        read=read_obstacles,
    ),
)

RUN_WAYPOINT = (
    Field("t", "s", "float", "time, non-decreasing", True, _at("t", float), read_time),
    Field("tip", "mm", "(3,)", "actual tip position", get=_at("tip"), read=read_point),
    Field("x", CONFIG, "(nx,)", "actual configuration", True, _at("x"), read_config),
    Field(
        "q", "mm", "(nq,)", "actual actuation: 3 cable lengths per segment, then z", get=_at("q"), read=read_actuation
    ),
    Field("q_command", "mm", "(nq,)", "the actuation set-point in force at t", get=_at("q_command")),
    Field("backbone", "mm", "(P, 3)", "points along the body (21)", get=lambda s, k: s.backbone[k]),
    Field(
        "obstacles",
        "mm",
        "object",
        "`centers`, `radii` (same m at every waypoint)",
        get=lambda s, k: s.obstacles(k),
        read=read_obstacles,
    ),
    Field(
        "clearance",
        "mm",
        "float",
        "sampled body clearance minus D_sf over the step ending at t",
        get=_at("clearance", float),
    ),
    Field("tip_error", "mm", "float", "actual tip to the planned tip", get=_at("tip_error", float)),
    Field(
        "status",
        "",
        "string",
        "the step's `StepStatus` (from the second waypoint on)",
        get=_step("step_status", str),
        step=True,
    ),
    Field(
        "solver_status",
        "",
        "string",
        "the horizon solver's own status text",
        get=_step("solver_status", str),
        step=True,
    ),
    Field("nlp_time", "s", "float", "the step's NLP solve", get=_step("nlp_time", float), step=True),
    Field(
        "iteration_time",
        "s",
        "float",
        "the step's whole iteration (source `iter_time`)",
        get=_step("iter_time", float),
        step=True,
    ),
)

EXECUTED = (
    Field("t0", "s", "float", "time of the first row", True, read=read_time),
    Field("dt", "s", "float", "control period between rows", True, read=read_period),
    Field("q", "mm", "(M, nq)", "actual actuation at the end of every control period", True, read=read_executed_q),
)

PLAN_BODY = (
    Field("waypoints", "", "list", "the plan's waypoints (below), non-empty, at most 100 000", required=True),
    Field("tree", "mm", "object", "`edges` (E, 2, 3): the planner tree as pairs of tip points"),
    Field("raw_path", "", "object", "`t` (s), `x`, `tip` (mm) of the path before smoothing"),
    Field("goal_configs", CONFIG, "(G, nx)", "goal configurations the planner found"),
    Field("retime", "", "object", "how `crtraj plan` timed the path for the actuators (`crtraj.app.plan`)"),
)

RUN_BODY = (
    Field("nlp", "", "object", "the horizon NLP's description (solver, sizes, deadline)"),
    Field("waypoints", "", "list", "the run's waypoints (below), one per recorded time", required=True),
    Field("executed", "s, mm", "object", "`t0`, `dt`, `q`: what a device is sent (`crtraj.control.executed`)"),
    Field("feed", "", "object", "a live obstacle feed's counters, options and rejected messages"),
    Field("stream", "", "object", "a live device stream's report (`DeviceLink.describe`)"),
    Field("plant", "", "object", "the simulated plant of `crtraj replan --plant cosserat` (below)"),
    Field("tree", "mm", "object", "`edges` (E, 2, 3): the last reference planner's tree"),
    Field("reference", "mm", "object", "`tip` (M, 3): the last reference path tracked"),
    Field("references", "", "list", "every reference path: `step`, `t` (s), `tip` (M, 3) mm"),
)

# `crtraj.control.rod_plant.RodPlant.describe`, plus PCC's own view of the same run
PLANT = (
    Field("kind", "", "string", '"plant"', True),
    Field("model", "", "string", '"cosserat": the Cosserat rod (`crtraj.model.cosserat._drive`)', True),
    Field("actuation", "", "string", '`[robot.mechanics]` actuation the rod ran in: "cable_length" or "tension"'),
    Field("gravity", "", "bool", "the rod carried its weight (`[robot.mechanics]` gravity)", True),
    Field("pretension_n", "N", "float", "tendon tension at the straight pose"),
    Field("tip_noise_mm", "mm", "float", "standard deviation per axis of the plant's tip readings"),
    Field("periods", "", "int", "control periods the plant was judged at"),
    Field("final_tip_error_mm", "mm", "float", "the rod's tip to the goal at the end", True),
    Field("min_clearance_mm", "mm", "float", "smallest clearance (minus D_sf) of the rod's body", True),
    Field("collisions", "", "int", "control periods the rod's body touched an obstacle", True),
    Field("safety_violations", "", "int", "control periods the rod's body came closer than D_sf", True),
    Field("failed_solves", "", "int", "control periods whose rod solve did not converge (no shape)"),
    Field("failure", "", "string", "why the plant stopped the run ('' when it did not)"),
    Field("holds", "", "int", "steps the loop held the servos"),
    Field("estop", "", "string", "why the loop e-stopped the plant ('' when it did not)"),
    Field("solves", "", "int", "rod solves"),
    Field("median_solve_s", "s", "float", "median wall time of one rod solve (cable-length mode, warm-started)"),
    Field("t", "s", "(M,)", "times: 0, then the end of every control period"),
    Field("q", "mm", "(M, nq)", "the plant's actuation at those times"),
    Field("tip", "mm", "(M, 3)", "the rod's tip at those times"),
    Field("clearance", "mm", "(M,)", "the rod's clearance (minus D_sf) at those times, null where the solve failed"),
    Field("pcc", "mm", "object", "PCC's own view of the run: `final_tip_error_mm`, `min_clearance_mm`, ..."),
)

REFERENCE = (Field("tip", "mm", "(M, 3)", "tip polyline of the reference path", True, read=read_polyline),)
TREE = (Field("edges", "mm", "(E, 2, 3)", "planner tree edges as pairs of tip points", True, read=read_edges),)


# ------------------------------------------------------------------ run.npz
def _strings(name: str) -> Callable[[Any], np.ndarray]:
    return lambda run: np.array(getattr(run, name), dtype=str)


def _array(name: str) -> Callable[[Any], np.ndarray]:
    return lambda run: np.asarray(getattr(run, name))


# (key, unit, shape, description, source attribute of `ReplanRun`); the arrays `save_npz` writes, in order
_NPZ = (
    ("t", "s", "(K+1,)", "recorded times", "t"),
    ("x", CONFIG, "(K+1, nx)", "actual configurations", "x"),
    ("q", "mm", "(K+1, nq)", "actual actuation", "q"),
    ("q_command", "mm", "(K+1, nq)", "actuation set-point in force at t", "q_command"),
    ("tip", "mm", "(K+1, 3)", "actual tip", "tip"),
    ("backbone", "mm", "(K+1, 41, 3)", "points along the body", "backbone"),
    ("centers", "mm", "(K+1, m, 3)", "obstacle centres", "centers"),
    ("radii", "mm", "(K+1, m)", "obstacle radii", "radii"),
    ("clearance", "mm", "(K+1,)", "sampled body clearance minus D_sf over the step ending at t", "clearance"),
    ("distance", "mm", "(K+1,)", "the same without D_sf (< 0: touching)", "distance"),
    ("clearance_bound", "mm", "(K+1,)", "the conservative bound the decision used", "clearance_bound"),
    ("planned", CONFIG, "(K+1, nx)", "configuration the NLP planned for t", "planned"),
    ("tip_error", "mm", "(K+1,)", "actual tip to planned tip", "tip_error"),
    ("goal_error", "mm", "(K+1,)", "actual tip to goal", "goal_error"),
    ("nlp_time", "s", "(K,)", "NLP solve per step", "nlp_time"),
    ("plan_time", "s", "(K,)", "reference planner time charged per step", "plan_time"),
    ("iter_time", "s", "(K,)", "whole iteration per step (run.json: `iteration_time`)", "iter_time"),
    ("iterations", "", "(K,)", "NLP iterations per step", "iterations"),
    ("replanned", "", "(K,)", "a reference path was adopted in the step", "replanned"),
    ("dense_t", "s", "(S,)", "times of every verification sample", "dense_t"),
    ("dense_x", CONFIG, "(S, nx)", "configurations of every verification sample", "dense_x"),
    ("commands", "mm", "(K n_sub, nq)", "set-point of every tracking period", "commands"),
    ("control_dt", "s", "()", "tracking period", "control_dt"),
    ("executed", "mm", "(K n_sub + 1, nq)", "actual actuation at the end of every tracking period", "executed"),
    ("tree_edges", "mm", "(E, 2, 3)", "last reference planner tree", "tree_edges"),
    ("goal", "mm", "(3,)", "goal tip", "goal"),
)
NPZ = (
    *(Field(k, u, s, d, True, _array(a)) for k, u, s, d, a in _NPZ),
    Field("status", "", "(K,) str", "step status per step (source `step_status`)", True, _strings("step_status")),
    Field("solver_status", "", "(K,) str", "solver status text per step", True, _strings("solver_status")),
    Field("reason", "", "(K,) str", "why the reference was replanned or asked for", True, _strings("reason")),
    Field("reference_{i}_tip", "mm", "(M, 3)", "tip polyline of the i-th reference path used"),
    Field("reference_{i}_step", "", "()", "step the i-th reference path started at"),
)

TABLES = (
    ("Header (plan.json and run.json, in this order)", HEADER),
    ("Verdict and figures (both)", VERDICT),
    ("Task (`task`, both: the keys read back)", TASK),
    ("Plan summary figures (plan.json `summary`, a selection)", SUMMARY),
    ("Plan body (plan.json)", PLAN_BODY),
    ("Plan waypoint (plan.json `waypoints[k]`)", PLAN_WAYPOINT),
    ("Run body (run.json)", RUN_BODY),
    ("Run waypoint (run.json `waypoints[k]`)", RUN_WAYPOINT),
    ("Waypoint obstacles (`waypoints[k].obstacles`)", OBSTACLES),
    ("Executed actuation (run.json `executed`)", EXECUTED),
    ("Simulated plant (run.json `plant`)", PLANT),
    ("Arrays (run.npz)", NPZ),
)


def schema_table_markdown() -> str:
    """The schema as Markdown tables, one per part of the files (for the docs)."""
    out: list[str] = []
    for title, fields in TABLES:
        out += [f"**{title}**", "", "| key | unit | shape / type | required | meaning |", "| --- " * 5 + "|"]
        for f in fields:
            desc = f.description.replace("|", "\\|")
            out.append(f"| `{f.key}` | {f.unit or '-'} | {f.shape} | {'yes' if f.required else 'no'} | {desc} |")
        out.append("")
    return "\n".join(out)
