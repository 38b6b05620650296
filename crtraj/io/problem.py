"""Problem files (TOML): robot, task, scene and per-module options.

A problem file names its robot (a path relative to the file, or an inline
``[robot]`` table) and holds the sections ``[task]``, ``[scene]``,
``[steer]``, ``[planner]``, ``[replan]``, ``[loop]``, ``[tracking]``, ``[stream]``.
Each section is read by the module that owns it, through `Problem.options`,
so a section's schema lives next to the code that uses it. Unknown top-level
sections and unknown keys are errors that name the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_SEED, Table, check_name
from crtraj.core.fileio import read_toml
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import read_homing, read_stop
from crtraj.io.calibration_data import CalibrationRecord
from crtraj.model.mechanics import Mechanics
from crtraj.model.rate_limits import RateLimits
from crtraj.model.robot import Robot
from crtraj.planning.goal import TipGoal

SECTIONS = (
    "name",
    "description",
    "robot",
    "seed",
    "task",
    "scene",
    "steer",
    "planner",
    "replan",
    "loop",
    "tracking",
    "stream",
    "feed",
    "view",
    "ros",
)

T = TypeVar("T")

MAX_DESCRIPTION = 10_000


def _file_name(ref: str, key: str) -> str:
    """A file reference from a problem file: non-empty, no NUL byte, of a sane length."""
    if not ref or "\0" in ref or len(ref) > 4096:
        raise InputError(f"{key}: expected a file name (relative to the problem file), got {ref[:60]!r}")
    return ref


def _shape_files_resolved(data: dict[str, Any], base: Path) -> dict[str, Any]:
    """`data` with each ``[[scene.shape]] file`` made relative to `base` (the problem file's folder) when it
    is a relative path, so the scene reads the same file wherever it is asked from."""
    scene = data.get("scene")
    shapes = scene.get("shape") if isinstance(scene, dict) else None
    if not isinstance(shapes, list):
        return data
    out = []
    for st in shapes:
        ref = st.get("file") if isinstance(st, dict) else None
        if isinstance(ref, str) and ref and not Path(ref).is_absolute():
            st = {**st, "file": str(base / _file_name(ref, "scene.shape.file"))}
        out.append(st)
    return {**data, "scene": {**scene, "shape": out}}


class _FromTable(Protocol[T]):  # pragma: no cover - typing only
    @classmethod
    def from_table(cls, t: Table) -> T: ...


def load_robot(path: str | Path) -> Robot:
    """Read a robot file (a TOML file with a ``[robot]`` table)."""
    data = read_toml(path)
    top = Table(data, "")
    for key in top.keys():
        if key not in ("robot", "calibration"):
            raise InputError(f"{key}: unknown key in robot file {path} (expected a [robot] table)")
    if not top.has("robot"):
        raise InputError(f"robot: missing; {path} needs a [robot] table")
    robot = _checked(Robot.from_table(top.table("robot")))
    if top.has("calibration"):  # written by crtraj calibrate; checked here, read by its users
        CalibrationRecord.from_table(top.table("calibration"))
    top.finish()
    return robot


def _checked(robot: Robot) -> Robot:
    """`robot`, after parsing its ``[robot.actuators]`` once so a bad key is a one-line error at load time."""
    if robot.actuators is not None:
        acts = Actuators.from_robot(robot)
        read_homing(robot, acts)
    read_stop(robot)
    if robot.mechanics is not None:  # [robot.mechanics]: checked at load time like the actuators
        Mechanics.from_robot(robot)
    return robot


# The keys of ``[task]`` (key, type, default, unit, meaning): `Task.from_table` reads exactly these, and the
# generated problem-file reference lists them (docs/hooks/references.py).
TASK_KEYS = (
    ("start", "array of 3 floats", "", "mm", "start tip position (a safe configuration is found by IK)"),
    ("goal", "array of 3 floats", "", "mm", "goal tip position"),
    ("goal_tolerance", "float", "1.0", "mm", "how close the tip must end to the goal, > 0"),
    ("start_config", "array of nx floats (optional)", "", "rad/mm", "start configuration instead of IK"),
    (
        "goal_direction",
        "array of 3 floats (optional)",
        "",
        "-",
        "direction the tip tangent must point along at the goal (any non-zero length; needs goal_cone)",
    ),
    (
        "goal_cone",
        "float (optional)",
        "",
        "deg",
        "largest angle between the tip tangent and goal_direction at the goal, in (0, 180]",
    ),
)


@dataclass(frozen=True)
class Task:
    """Start and goal tip positions (mm); an optional start configuration overrides IK. goal_direction (3,)
    (unit) with goal_cone (deg): the tip tangent at the goal must lie within the cone
    (`crtraj.planning.goal.TipGoal`)."""

    start: np.ndarray
    goal: np.ndarray
    start_config: np.ndarray | None = None
    goal_tolerance: float = 1.0  # mm
    goal_direction: np.ndarray | None = None  # unit vector
    goal_cone: float | None = None  # deg

    @classmethod
    def from_table(cls, t: Table, nx: int) -> Task:
        start = np.array(t.vec("start", 3, limit=MAX_LENGTH))
        goal = np.array(t.vec("goal", 3, limit=MAX_LENGTH))
        sc = t.vec("start_config", nx, None, limit=MAX_LENGTH)
        tol = t.float("goal_tolerance", 1.0, gt=0.0, limit=MAX_LENGTH)
        direction = t.vec("goal_direction", 3, None, limit=MAX_LENGTH)
        cone = t.float("goal_cone", None, gt=0.0, le=180.0)
        t.finish()
        tip = TipGoal.of(goal, direction, cone, prefix="task.")
        return cls(start, goal, None if sc is None else np.array(sc), tol, tip.direction, cone)

    def tip_goal(self) -> TipGoal:
        """The goal as planners take it: the position with its direction cone, when the task has one."""
        return TipGoal.of(self.goal, self.goal_direction, self.goal_cone, prefix="task.")

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"start": self.start, "goal": self.goal, "goal_tolerance": self.goal_tolerance}
        if self.start_config is not None:
            d["start_config"] = self.start_config
        if self.goal_direction is not None:
            d["goal_direction"] = self.goal_direction
            d["goal_cone"] = self.goal_cone
        return d


@dataclass(frozen=True)
class Problem:
    """A parsed problem file. Sections other than robot and task stay as tables
    until a module asks for them with `options(SomeOptions)`."""

    name: str
    robot: Robot
    task: Task | None
    seed: int
    path: Path | None = None
    description: str = ""
    raw: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @classmethod
    def load(cls, path: str | Path) -> Problem:
        """Read and validate a problem file."""
        p = Path(path)
        return cls.from_dict(read_toml(p), p)

    @classmethod
    def from_dict(cls, data: dict[str, Any], path: Path | None = None) -> Problem:
        top = Table(data, "")
        for key in top.keys():
            if key not in SECTIONS:
                raise InputError(f"{key}: unknown section (known: {', '.join(SECTIONS)})")
        robot_ref = top.raw("robot")
        if isinstance(robot_ref, str):
            base = path.parent if path is not None else Path.cwd()
            robot = load_robot(base / _file_name(robot_ref, "robot"))
        else:
            robot = _checked(Robot.from_table(Table(robot_ref, "robot")))
        task = None
        if top.has("task"):
            task = Task.from_table(top.table("task"), robot.nx)
        seed = top.int("seed", 0, ge=0, le=MAX_SEED)
        name = check_name(top.str("name", path.stem if path is not None else "problem"), "name")
        desc = top.str("description", "", max_len=MAX_DESCRIPTION)
        for key in SECTIONS:
            top.raw(key, None)  # sections are validated by their owners
        top.finish()
        data = _shape_files_resolved(data, path.parent if path is not None else Path.cwd())
        prob = cls(name, robot, task, seed, path, desc, dict(data))
        return prob

    def section(self, name: str) -> Table:
        """The raw table of section `name` (empty when absent)."""
        if name not in SECTIONS:
            raise InputError(f"{name}: unknown section")
        return Table(self.raw.get(name, {}), name)

    def options(self, cls: type[_FromTable[T]], section: str) -> T:
        """Parse section `section` with ``cls.from_table`` (validates unknown keys)."""
        return cls.from_table(self.section(section))

    def require_task(self) -> Task:
        if self.task is None:
            raise InputError("task: missing; add [task] with start and goal (mm)")
        return self.task

    def rate_limits(self) -> RateLimits | None:
        """The robot's actuator speed and acceleration limits as limits on configuration motion (None
        without a ``[robot.actuators]`` table): the closed loop keeps its NLP, set-points and reference
        within ``replan.limit_fraction`` of them, so a run can be streamed as it is."""
        if self.robot.actuators is None:
            return None
        return Actuators.from_robot(self.robot).rate_limits(self.robot)
