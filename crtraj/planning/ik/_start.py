"""The start configuration of a planning query: the given one, checked, or safe IK for a start tip. Units mm, rad."""

from __future__ import annotations

from typing import Any

import numpy as np

from crtraj.core.fields import check_array
from crtraj.planning.ik._run import format_statuses
from crtraj.planning.ik._safe_ik import SafeIK
from crtraj.planning.validity import MotionValidator


def resolve_start(
    ik: SafeIK,
    validator: MotionValidator,
    *,
    start_config: Any,
    start_tip: Any,
    t0: float,
    rng: np.random.Generator,
    seeds: int,
    iterations: int,
    deadline: float | None,
    tip_tolerance: float,
    max_nlp: int | None = None,
) -> tuple[np.ndarray | None, str, int]:
    """The start configuration of a query: checked when given, else safe IK for the start tip.

    Returns (x or None, why it is invalid, IK solves). Among several safe IK
    solutions the least bent one is taken (smallest bending body motion).
    Bad input (shape, NaN) raises `InputError`.
    """
    robot = ik.robot
    if start_config is not None:
        xs = check_array(start_config, "start_config", (robot.nx,))
        # the validator's limit test is Robot.limit_violation's arithmetic on kept matrices (the same verdict,
        # a fraction of its cost); the violation itself is computed only for the message
        if not validator.within_limits(xs[None])[0]:
            viol = float(robot.limit_violation(xs)[0])
            return None, f"start configuration violates the robot limits by {viol:.3g}", 0
        c = float(validator.clearance(xs[None], t0)[0])
        if c < 0:
            return None, f"start configuration is in collision: body clearance {c:.2f} mm (below D_sf + margins)", 0
        return xs, "", 0
    st = check_array(start_tip, "start_tip", (3,))
    batch = ik.solve(
        st,
        lambda: validator.scene.pack(t0, ik.max_obstacles),
        validator.sample(rng, seeds),
        t_check=(t0, t0),
        want=1,
        newton_iterations=iterations,
        deadline=deadline,
        validator=validator,
        tip_tolerance=tip_tolerance,
        max_nlp=max_nlp,
    )
    if not len(batch.safe):
        return (
            None,
            f"no safe configuration puts the tip on the start {st.tolist()} mm "
            f"({seeds} IK starts: {format_statuses(batch.statuses)})",
            len(batch.solutions),
        )
    bend = batch.safe.copy()
    bend[:, -1] = 0.0
    return batch.safe[int(np.argmin(validator.motion_bound(bend)))], "", len(batch.solutions)
