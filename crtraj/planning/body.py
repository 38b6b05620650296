"""Which body a plan keeps clear: ``[planner] model = "pcc" | "rod"`` (and ``--model`` of plan and replan).

"pcc" is the robot file's PCC `Model`. "rod" is `crtraj.model.cosserat.RodModel`: the body the Cosserat rod
takes under the robot file's ``[robot.mechanics]`` (its actuation mode, gravity), as a polynomial correction
of PCC fitted to the rod's surrogate, so every consumer of the Model (checker, safe IK, steer and horizon NLPs)
sees that body with exact derivatives. Its measured error is paid for in the margin: the planner keeps
D_sf + `RodModel.planning_margin` from the obstacles (`planning_scene`), so D_sf holds on the rod itself.

Units: mm.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any

from crtraj.core.errors import InputError
from crtraj.model.cosserat import RodModel, RodModelOptions, load_rod_model
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot
from crtraj.planning.options import MODELS
from crtraj.world.scene import Scene

log = logging.getLogger(__name__)


def planning_model(
    robot: Robot,
    kind: str,
    *,
    options: RodModelOptions | None = None,
    cache_dir: str | Path | None = None,
) -> Model:
    """The `Model` of body `kind` ("pcc" or "rod") for `robot`; options, cache_dir: the rod model's
    (`load_rod_model`). `InputError` (one line) for an unknown kind or "rod" on a robot file without
    ``[robot.mechanics]``."""
    if kind not in MODELS:
        raise InputError(f"--model: unknown model {kind!r} (choose from {', '.join(MODELS)})")
    if kind == "pcc":
        return Model(robot)
    if robot.mechanics is None:
        raise InputError(
            f"--model rod: robot {robot.name!r} has no [robot.mechanics] table (the rod's material, section and "
            "gravity); add one or plan with --model pcc"
        )
    model = load_rod_model(robot, options, cache_dir=cache_dir)
    log.info("planning for the rod's body (%s); D_sf grows by %.3f mm", model.error.text(), model.planning_margin)
    return model


def margin_of(model: Model) -> float:
    """mm a plan of `model` keeps beyond D_sf to cover the model's error against the rod (0 for PCC)."""
    return model.planning_margin if isinstance(model, RodModel) else 0.0


def planning_scene(scene: Scene, model: Model) -> Scene:
    """`scene` with D_sf grown by `margin_of(model)`: what the planner keeps clear (the result records the
    problem's own scene and D_sf)."""
    extra = margin_of(model)
    return scene if extra == 0.0 else replace(scene, safety_distance=scene.safety_distance + extra)


def model_record(model: Model) -> dict[str, Any]:
    """The body a result was planned for, as recorded in its options: {"kind": "pcc"} or the rod model's
    identity, measured error and margin (`RodModel.describe`) and the ``[robot.mechanics]`` values it was made
    under ("mechanics": the robot table a result records carries none; `body_mismatch` compares them)."""
    if not isinstance(model, RodModel):
        return {"kind": "pcc"}
    return model.describe() | {"mechanics": _plain(Mechanics.from_robot(model.robot).to_dict())}


def _plain(d: Mapping[str, Any]) -> dict[str, Any]:
    """`d` as JSON gives it back (tuples as lists), so a recorded table compares equal to a fresh one."""
    return json.loads(json.dumps(dict(d)))


def body_mismatch(record: Mapping[str, Any] | None, robot: Robot) -> str | None:
    """Why a result whose options record body `record` (`model_record`) may not drive `robot` (the device's robot
    file), or None. A PCC plan (or none recorded) always may. A rod plan's commanded cable lengths hold the rod
    where it was planned only under the mechanics it was planned with: the robot file must have
    ``[robot.mechanics]`` with every value the recorded one (the actuation mode and gravity included; the first
    that differs is named). (The robot's description is `crtraj.io.results.Result.check_robot`'s; with both the
    same, so is the rod surrogate the plan was made with.)"""
    if not isinstance(record, Mapping) or record.get("kind") != "rod":
        return None
    fix = "re-plan it with --model rod for this robot file"
    if robot.mechanics is None:
        return f"planned for the rod's body (--model rod) but robot {robot.name!r} has no [robot.mechanics]; {fix}"
    theirs = record.get("mechanics")
    if not isinstance(theirs, Mapping):
        return (
            f"planned for the rod's body (--model rod) but records no mechanics to check robot {robot.name!r} by; {fix}"
        )
    ours = _plain(Mechanics.from_robot(robot).to_dict())
    theirs = dict(theirs) | ({"actuation": record["actuation"]} if "actuation" in record else {})
    for key in sorted(set(ours) | set(theirs)):
        if ours.get(key) != theirs.get(key):
            return (
                f"robot.mechanics.{key}: the rod plan was made with {theirs.get(key)!r}, robot {robot.name!r} has "
                f"{ours.get(key)!r}; {fix}"
            )
    return None
