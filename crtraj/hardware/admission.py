"""Admission: what may be sent to a device. Refusals made before anything moves, for every caller
(the CLI, the use cases in `crtraj.app`, a Python user), each a one-line `InputError`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import read_json
from crtraj.world.scene import Scene


def check_replay_time_scale(result: dict[str, Any] | str | Path, time_scale: float) -> None:
    """Refuse to slow down a run among moving or breathing obstacles: its slowed timing was never checked.

    result: a result document (or its file) whose "scene" describes the obstacles. time_scale: the
    replay's slow-down factor (1 = as planned).
    """
    if time_scale == 1.0:
        return
    data = result if isinstance(result, dict) else read_json(result)
    scene = Scene.from_table(Table(data.get("scene", {}), "scene"))
    if any(ob.amplitude != 0.0 or ob.to is not None for ob in scene.obstacles):
        raise InputError(
            f"--time-scale: {time_scale:g} refused: the run's obstacles move or change size, and a slowed replay "
            "was never checked against them (plan again with lower speed limits instead)"
        )


def check_stream_safety(safety: bool) -> None:
    """Refuse to drive a device with a run that has no collision-free terms."""
    if not safety:
        raise InputError(
            "--stream: refused with --no-safety (a run without the collision-free terms never drives a device)"
        )
