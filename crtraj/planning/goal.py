"""A goal for the tip: a position (mm) and, optionally, a direction its tangent must keep within a cone.

``[task] goal_direction = [x, y, z]`` with ``goal_cone`` (degrees, in (0, 180]) asks the tip tangent at the
goal (the third column of the tip frame's rotation, `Model.frame`) to lie within ``goal_cone`` of the
direction. A planner that takes a `TipGoal` instead of a plain (3,) goal honours the cone in its goal
IK (`crtraj.planning.ik.SafeIK.solve`, ``direction=``); a goal without a direction is the plain goal.
Units: mm; the cone is held in radians (the file's degrees are converted once, here).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, check_array, check_float

__all__ = ["TipGoal", "tip_tangents"]


@dataclass(frozen=True)
class TipGoal:
    """position (3,) mm; direction (3,) unit vector or None; cone: half-angle (rad) in (0, pi], or None.

    Build with `TipGoal.of` (checks the input; `direction` is normalised there).
    """

    position: np.ndarray
    direction: np.ndarray | None = None
    cone: float | None = None

    @classmethod
    def of(cls, goal: Any, direction: Any = None, cone_deg: Any = None, *, prefix: str = "") -> TipGoal:
        """A checked goal: `goal` a (3,) position (mm) or a `TipGoal` (returned as it is); `direction` any
        non-zero (3,) vector and `cone_deg` (degrees, in (0, 180]) given together or not at all. Bad input is
        one `InputError` naming the key (``goal_direction``, ``goal_cone``, after `prefix`, e.g. "task.")."""
        if isinstance(goal, TipGoal):
            return goal
        p = check_array(goal, f"{prefix}goal", (3,), limit=MAX_LENGTH)
        if direction is None and cone_deg is None:
            return cls(p)
        kd, kc = f"{prefix}goal_direction", f"{prefix}goal_cone"
        if direction is None:
            raise InputError(f"{kc}: given without goal_direction; add goal_direction = [x, y, z] or drop it")
        if cone_deg is None:
            raise InputError(f"{kd}: needs goal_cone (degrees in (0, 180]), the angle the tip may keep from it")
        d = check_array(direction, kd, (3,), limit=MAX_LENGTH)
        n = float(np.linalg.norm(d))
        if not n > 1e-9:
            raise InputError(f"{kd}: must be a non-zero vector, got {d.tolist()}")
        c = check_float(cone_deg, kc, gt=0.0, le=180.0)
        return cls(p, d / n, math.radians(c))

    @property
    def has_direction(self) -> bool:
        return self.direction is not None

    @property
    def cone_deg(self) -> float:
        """The cone's half-angle in degrees (NaN without a direction)."""
        return float("nan") if self.cone is None else math.degrees(self.cone)

    def angles(self, tangents: np.ndarray) -> np.ndarray:
        """Angles (rad) between tip tangents (..., 3) and the direction (zeros without a direction)."""
        t = np.asarray(tangents, dtype=float)
        if self.direction is None:
            return np.zeros(t.shape[:-1])
        c = (t @ self.direction) / np.maximum(np.linalg.norm(t, axis=-1), 1e-300)
        return np.arccos(np.clip(c, -1.0, 1.0))

    def within(self, tangents: np.ndarray, slack: float = 0.0) -> np.ndarray:
        """Which tip tangents (..., 3) lie within the cone, less `slack` rad (all, without a direction)."""
        if self.cone is None:
            return np.ones(np.asarray(tangents).shape[:-1], dtype=bool)
        return self.angles(tangents) <= self.cone - slack

    def describe(self) -> str:
        """'[x, y, z] mm' or '[x, y, z] mm with the tip within 10 deg of [dx, dy, dz]' (for messages)."""
        text = f"{np.round(self.position, 3).tolist()} mm"
        if self.direction is None:
            return text
        return f"{text} with the tip tangent within {self.cone_deg:g} deg of {np.round(self.direction, 4).tolist()}"


def tip_tangents(model: Any, X: np.ndarray) -> np.ndarray:
    """Unit tip tangents (N, 3) of configurations X (N, nx): the z column of each tip frame's rotation."""
    return np.asarray(model.frame(np.atleast_2d(X)))[:, :3, 2]
