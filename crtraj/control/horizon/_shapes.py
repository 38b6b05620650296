"""The scene's obstacles of other shapes in the horizon NLP (issue 39): how many points keep how far from them,
and their parameters over a horizon's step windows. Units: mm, s.

Each of `points` backbone points (the NLP's `points` and the midpoints between them) of every step keeps
``D_sf + body + sagitta + margin + h / 2`` mm (h their spacing) from each shape's lower bound over the step's
window (`crtraj.world.geometry.ShapeTerms`): a point of the chord to a neighbour is within h / 2 of one of its
ends, a distance is 1-Lipschitz, and the arc stays within the sagitta of its chord.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.control.horizon._rows import sagitta
from crtraj.core.errors import InputError
from crtraj.world import margin
from crtraj.world.geometry import MovingShape, ShapeTerms, shape_to_dict


class HorizonShapes:
    """The shapes of one horizon NLP (module docstring).

    robot: the robot (its length, body radius, curvature). shapes: the scene's `MovingShape`s (none when
    `safety` is off). safety_distance: D_sf (mm). points: the NLP's backbone points. extra: the margin (mm).
    """

    def __init__(
        self,
        robot: Any,
        shapes: tuple[MovingShape, ...],
        safety: bool,
        safety_distance: float,
        points: int,
        extra: float,
    ) -> None:
        self.terms = ShapeTerms(tuple(shapes) if safety else ())
        self.points = 2 * points - 1
        h = robot.total_length / (self.points - 1)
        self.keep = margin.inflation(safety_distance, robot.body_radius, sagitta(robot, h), extra) + 0.5 * h
        self._static: np.ndarray | None = None

    @property
    def n_params(self) -> int:
        """Parameters per step (`ShapeTerms.n_params`)."""
        return self.terms.n_params

    def parameters(self, scene: Any, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The parameters (N, n_params) of the step windows [lo_k, hi_k] (absolute s). The scene's shapes must be
        the ones the NLP was built with (else `InputError`)."""
        mine, theirs = self.terms.shapes, tuple(getattr(scene, "shapes", ()))
        if len(mine) != len(theirs) or any(
            a is not b and shape_to_dict(a) != shape_to_dict(b) for a, b in zip(mine, theirs, strict=True)
        ):
            raise InputError(
                f"scene.shape: the replanner was built for {len(mine)} shape(s), the scene has {len(theirs)} "
                "other ones; build the replanner with the scene's shapes"
            )
        if self._static is not None:
            return self._static
        out = np.stack([self.terms.values(float(a), float(b)) for a, b in zip(lo, hi, strict=True)])
        if all(ms.static for ms in mine):  # the same numbers at every time: kept
            out.setflags(write=False)
            self._static = out
        return out
