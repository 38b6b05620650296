"""The horizon replanner's options, its result and its status (units mm, rad, s).

`ReplanOptions` is the ``[replan]`` problem section; `HorizonResult` is one solve of the horizon NLP
(`crtraj.control.horizon.Replanner`) and `HorizonStatus` its one-word outcome.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, ClassVar

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.options import Options, option

SOLVERS = ("ipopt", "sqp")
QP_SOLVERS = ("daqp", "qrqp", "osqp", "qpoases", "hpipm")
HESSIANS = ("gauss-newton", "exact")

# Keys of the closed loop's own options, once read from [replan]: now the [loop] section
# (`crtraj.control.loop.LoopOptions`). An old file that still has one gets a one-line error.
MOVED_TO_LOOP = (
    "duration",
    "replan_period",
    "planner_time",
    "stall_time",
    "reference_speed",
    "max_body_speed",
    "check_resolution",
    "check_points",
    "settle_time",
)

# The closed loop keeps its samples' acceleration (NLP steps, tracking set-points, hence the servos'
# motion at every control period) within the actuator limit divided by this gain. `crtraj stream` sends
# a recorded run as the B-spline of its executed actuation (`crtraj.control.executed`), whose
# acceleration never exceeds the samples' own, so a replayed run keeps half the limit (0.47 of it on
# paper_dynamic). The gain dates from the PCHIP interpolation it replaced (which amplified up to ~4x at
# reversals); it stays at 2 because lowering it changes every run's timing and the margins of the live
# stream's follower (`crtraj.hardware.link`).
INTERPOLATION_GAIN = 2.0

# An iterate further than this outside a constraint (mm, mm per step, rad: 1000 of any of the NLP's units) has
# diverged: going on from it (`max_calls`) only spends the step (seen live under load: 20 calls up to 1e16).
DIVERGED = 1e3


@dataclass(frozen=True)
class ReplanOptions(Options):
    """The ``[replan]`` problem section (units mm, rad, s).

    Horizon NLP: horizon N (steps), dt (s per step), points (backbone points
    constrained per configuration), closest_points (0 = all: how many of
    those points per obstacle and step the QP keeps, see `Replanner`),
    qp_obstacles (0 = all: in a scene of more obstacles than this, the
    QP is built for this many, and a broad phase picks, each step, the
    obstacles the horizon's reachable body can come near, the nearest
    first, `crtraj.control.horizon._broad`; a solution is checked against
    every obstacle and solved again with one it enters; every move is still
    verified against all; 3 since issue 29: 8 slots made a 31-obstacle
    step 3x the 1-obstacle one, 3 slots 1.9x),
    margin (mm of clearance kept on top of
    D_sf + body radius + sampling bounds, for servo lag), weights
    (tip_weight, config_weight, velocity_weight, smooth_weight,
    terminal_weight; see the module docstring), max_cable_speed and
    max_z_speed (mm/s, the per-step rate limits), solver ("ipopt" or "sqp"
    = CasADi sqpmethod with a QP solver `qpsol`), hessian ("gauss-newton"
    of the least-squares cost, or "exact"), max_iter, tol, max_solve_time
    (s, IPOPT's wall-time cap of one solve; sqpmethod is capped by
    max_iter), rescue (with solver "sqp": retry a failed solve once with
    IPOPT, built alongside), safety (false drops the obstacle constraints),
    limit_fraction (share (0, 1] of each actuator's speed and acceleration limit the
    NLP and the tracking may use, when the robot's actuator limits are given).
    qpsol "hpipm" (issue 29): the same NLP in stage form, state (x_k, x_k-1)
    and input x_k+1, for HPIPM's Riccati interior point
    (`crtraj.control.horizon._stage`); same rows, answers and success test.
    compiled (with solver "sqp" and qpsol daqp, qrqp or hpipm): generate C for the
    whole sqpmethod solver, compile it once (cached) and call it through
    ctypes; convergence is sqpmethod's own KKT test on the returned point
    (the generated code reports no iteration count: -1). Without a C
    compiler the interpreted solver runs (`Replanner.compiled_message`).
    fused (with compiled): the solver, its KKT check and the check of the
    box and rows are one generated C function called once per solver call on
    preallocated buffers (issue 29); false: the solver and the KKT check are
    two calls and the rows are checked in numpy (the previous path).
    step_deadline (s, 0 = none): wall-time deadline of one replanning
    iteration; a solve that finishes after it is not used (the loop falls
    back to the last verified plan, shifted, or a verified hold) and is
    counted as a deadline miss. max_iter is the fixed iteration cap of one
    solver call; max_calls (sqpmethod): calls per solve, each next one going on
    from the iterate the cap stopped. Without step_deadline, calls go on to
    convergence. With it, only while time is left and only from an iterate
    outside a constraint: one the cap stopped inside every constraint is a
    usable plan (status FEASIBLE), applied as a suboptimal move once verified.
    The IPOPT rescue may take max_iter x max_calls iterations.

    The closed loop's options are the ``[loop]`` section
    (`crtraj.control.loop.LoopOptions`).
    """

    SECTION: ClassVar[str] = "replan"

    horizon: int = option(10, ge=1, le=200)
    dt: float = option(0.1, ge=1e-3, le=10.0)
    points: int = option(16, ge=2, le=200)
    closest_points: int = option(3, ge=0, le=200)
    qp_obstacles: int = option(3, ge=0, le=10_000)
    margin: float = option(1.5, ge=0.0)
    tip_weight: float = option(1.0, ge=0.0)
    config_weight: float = option(0.01, ge=0.0)
    velocity_weight: float = option(0.02, ge=0.0)
    smooth_weight: float = option(0.2, ge=0.0)
    terminal_weight: float = option(10.0, ge=0.0)
    max_cable_speed: float = option(8.0, gt=0.0)
    max_z_speed: float = option(40.0, gt=0.0)
    solver: str = option("ipopt", choices=SOLVERS)
    qpsol: str = option("daqp", choices=QP_SOLVERS)
    hessian: str = option("gauss-newton", choices=HESSIANS)
    max_iter: int = option(60, ge=1, le=100_000)
    max_calls: int = option(1, ge=1, le=1000)
    tol: float = option(1e-4, gt=0.0, le=1.0)
    max_solve_time: float = option(0.5, gt=0.0, le=3600.0)
    limit_fraction: float = option(0.9, gt=0.0, le=1.0)
    rescue: bool = option(True)
    safety: bool = option(True)
    compiled: bool = option(False)
    fused: bool = option(True)
    step_deadline: float = option(0.0, ge=0.0, le=3600.0)

    def _check(self) -> None:
        # a QP solver may be a plugin missing from this CasADi build: refuse it before building the NLP
        if self.solver == "sqp" and not ca.has_conic(self.qpsol):
            raise InputError(f"replan.qpsol: QP solver {self.qpsol!r} is not available in this CasADi build")

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        # no read=False fields; an old file that still has a closed-loop key gets a pointer to [loop]
        # (checked here, before Table.finish would call it an unknown key)
        for name in MOVED_TO_LOOP:
            if t.has(name):
                raise InputError(f"replan.{name}: moved to the [loop] section; write it under [loop]")
        return {}


class HorizonStatus(str, enum.Enum):
    """Outcome of one horizon NLP solve."""

    SOLVED = "solved"  # the solver converged AND its point satisfies every constraint (within 1e-6)
    FEASIBLE = "feasible"  # not converged (iteration/time limit), but the last iterate satisfies every constraint
    FAILED = "failed"  # no usable point: constraints violated, or NaN/inf
    SKIPPED = "skipped"  # not solved at all (e.g. no trustworthy obstacle state); solver_status says why

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class HorizonResult:
    """One solve of the horizon NLP.

    configs: (N, nx) planned configurations x_1..x_N (the solver's last
    iterate even on failure). tips: (N, 3) mm. status: `HorizonStatus`
    (`is_success()`: SOLVED). solver_status: the solver's own status text.
    iterations, wall_time (s). min_distance: smallest value of the obstacle
    constraints (mm; >= 0 means every sampled point is outside its inflated
    sphere; inf without obstacles). violation: largest constraint violation
    (mixed units).
    """

    configs: np.ndarray
    tips: np.ndarray
    status: HorizonStatus
    solver_status: str
    iterations: int
    wall_time: float
    cost: float
    min_distance: float
    violation: float
    warm: bool = False
    extra: dict[str, Any] = field(default_factory=dict)

    def is_success(self) -> bool:
        """The solver converged to a point that satisfies every constraint."""
        return self.status is HorizonStatus.SOLVED

    @property
    def feasible(self) -> bool:
        """The returned configurations satisfy every constraint (within 1e-6), converged or not: a move
        the loop may use (SOLVED or FEASIBLE)."""
        return self.status in (HorizonStatus.SOLVED, HorizonStatus.FEASIBLE)


def horizon_status(converged: bool, configs: np.ndarray, violation: float) -> HorizonStatus:
    """The status of a solve: converged (and within the constraints), else feasible or failed."""
    if not (bool(np.all(np.isfinite(configs))) and violation <= 1e-6):
        return HorizonStatus.FAILED
    return HorizonStatus.SOLVED if converged else HorizonStatus.FEASIBLE
