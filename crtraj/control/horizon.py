"""Receding-horizon (MPC) replanner: one CasADi NLP over N future configurations, built once.

At every control step the robot is at x_0 (measured). The NLP chooses the next
N configurations x_1..x_N, one per step of length dt (s):

    minimise   sum_k  w_tip |tip(x_k) - p_ref,k|^2                     (follow the reference path, mm^2)
                    + w_cfg |S (x_k - x_ref,k)|^2                       (stay near the reference body shape)
                    + w_vel |S (x_k - x_k-1)|^2                          (effort)
                    + w_acc |S (x_k - 2 x_k-1 + x_k-2)|^2                (smoothness)
               + w_term |tip(x_N) - p_ref,N|^2
    subject to |p_j(x_k) - c_i,k| >= rho_i,k      every backbone point j, obstacle i, step k
               limits(x_k) within the robot's bounds, x_k in robot.config_box()
               |A_q (x_k - x_k-1)| <= v_max dt                          (per-actuator rate limits)
               |J (x_k - x_k-1)| <= f vmax dt                            (actuator speed limits)
               |J (x_k - 2 x_k-1 + x_k-2)| <= f amax dt^2                (actuator acceleration limits)

The actuator limits (`crtraj.planning.rate_limits.RateLimits`, J = d actuator value / d x) are linear
in x, so they cost one sparse row each; x_-1 (the configuration one step before the measured x_0) is a
parameter, so the first step's acceleration is measured against the previous applied step's velocity
and nothing is rebuilt per step. f is ``limit_fraction`` (a reserve for the tracking and the
interpolation of the executed motion).

S scales bending (rad) by the segment length so every term is in mm. Obstacle
slot (c_i,k, rho_i,k) is one sphere that encloses everything obstacle i
sweeps during [t_k-1, t_k+1] (`Scene.swept`, or a constant-velocity
extrapolation of a live state), so both ends of each step's motion are kept
clear of the obstacle over that whole step. The radius is inflated so that
the continuous body, not only the n sampled points, keeps the safety
distance D_sf (the `validity.MotionValidator` bounds):

    rho = sqrt((R + D_sf + body_radius + sagitta(h) + margin)^2 + (h/2)^2)

with h the arc spacing of the NLP's points: a point outside rho keeps every
chord to its neighbour outside R + D_sf + body + sagitta + margin, and the
arc stays within the sagitta of its chord. `margin` (mm) absorbs the servo
lag of the real robot. With ``safety = false`` the obstacle constraints are
left out (the paper's simulation 2, Fig. 4(b)).

Each QP keeps only the `closest_points` (K) backbone points per obstacle and step that are nearest to
it at the point the solve starts from (the shifted previous solution): parameters pick them (per
slot, the point's segment, one-hot, and the fraction of that segment's arc, so the NLP computes one
point per segment and slot), the NLP is still built once, and the QP has K M N obstacle rows instead of
n M N (the QP solver's work grows with its rows). Every point of every step is checked at the
solution; if an omitted one is inside its sphere, the solve is repeated from there with the points
nearest there (`SCREEN_SOLVES`). A solution whose omitted rows all hold is a KKT point of the full
NLP as well (zero multipliers on those rows), so a SOLVED status means the same with or without
screening. The rescue (IPOPT) solves the full NLP. The speed rows of the actuator limits that are
parallel to the rate rows are merged into them, and the acceleration rows that the speed rows imply
(from step 2 on) are left out (`merge_parallel_rows`, `implied_rows`).

Obstacles, current state and reference are parameters of one `casadi.nlpsol`
built at construction (the "compile once, call repeatedly" pattern of
rockit's repeated_solve example); each solve is warm-started from the
previous solution shifted by one step. Units: mm, rad, s.
"""

from __future__ import annotations

import enum
import math
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import Table, check_float
from crtraj.core.options import Options, option
from crtraj.model.kinematics import Model
from crtraj.planning.compiled_nlp import CODEGEN_QP, CompiledFunction, compiled_library
from crtraj.planning.rate_limits import RateLimits
from crtraj.world import margin, packing

SOLVERS = ("ipopt", "sqp")
QP_SOLVERS = ("daqp", "qrqp", "osqp", "qpoases")
HESSIANS = ("gauss-newton", "exact")

# Keys of the closed loop's own options, once read from [replan]: now the [loop] section
# (`crtraj.control.loop_options.LoopOptions`). An old file that still has one gets a one-line error.
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

# With `closest_points`, at most this many solves of the QP's NLP per call of the solver: a solution that
# leaves an omitted point inside its sphere is solved again with the closest points there.
SCREEN_SOLVES = 3
# An iterate further than this outside a constraint (mm, mm per step, rad: 1000 of any of the NLP's units) has
# diverged: going on from it (`max_calls`) only spends the step (seen live under load: 20 calls up to 1e16).
DIVERGED = 1e3


@dataclass(frozen=True)
class ReplanOptions(Options):
    """The ``[replan]`` problem section (units mm, rad, s).

    Horizon NLP: horizon N (steps), dt (s per step), points (backbone points
    constrained per configuration), closest_points (0 = all: how many of
    those points per obstacle and step the QP keeps, see `Replanner`),
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
    compiled (with solver "sqp" and qpsol daqp or qrqp): generate C for the
    whole sqpmethod solver, compile it once (cached) and call it through
    ctypes; convergence is sqpmethod's own KKT test on the returned point
    (the generated code reports no iteration count: -1). Without a C
    compiler the interpreted solver runs (`Replanner.compiled_message`).
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
    (`crtraj.control.loop_options.LoopOptions`).
    """

    SECTION: ClassVar[str] = "replan"

    horizon: int = option(10, ge=1, le=200)
    dt: float = option(0.1, ge=1e-3, le=10.0)
    points: int = option(16, ge=2, le=200)
    closest_points: int = option(3, ge=0, le=200)
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


def _in_time(tried: list[dict[str, Any]], time_left: float | None) -> bool:
    """The solver calls so far (their "wall", s) leave time before the deadline (always, without one)."""
    return time_left is None or sum(x["wall"] for x in tried) < time_left


def horizon_status(converged: bool, configs: np.ndarray, violation: float) -> HorizonStatus:
    """The status of a solve: converged (and within the constraints), else feasible or failed."""
    if not (bool(np.all(np.isfinite(configs))) and violation <= 1e-6):
        return HorizonStatus.FAILED
    return HorizonStatus.SOLVED if converged else HorizonStatus.FEASIBLE


def sagitta(robot: Any, spacing: float) -> float:
    """Largest distance (mm) of a backbone arc of length `spacing` (mm) from its chord."""
    kappa = max(s.theta_max / s.length for s in robot.segments)
    half = min(kappa * spacing / 2.0, math.pi / 2.0)
    return float((1.0 - math.cos(half)) / kappa)


def _multiple(row: np.ndarray, base: np.ndarray) -> float:
    """s with row = s base (to 1e-12 relative), else 0."""
    s = float(row @ base) / float(base @ base) if base.any() else 0.0
    return s if s != 0.0 and np.max(np.abs(row - s * base)) <= 1e-12 * np.max(np.abs(row)) else 0.0


def merge_parallel_rows(rows: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Constraints |rows @ v| <= bound (rows (m, n), bound (m,)) without repeats.

    A row that is a nonzero multiple s of an earlier kept row states the same constraint as
    |earlier @ v| <= bound_i / |s|: it is dropped and the earlier row keeps the tighter bound.
    Returns (rows (k, n), bounds (k,)) in first-seen order.
    """
    R = np.asarray(rows, dtype=float)
    b = np.array(bound, dtype=float).reshape(len(R))
    keep: list[int] = []
    for i, r in enumerate(R):
        for j in keep:
            s = _multiple(r, R[j])
            if s:
                b[j] = min(b[j], b[i] / abs(s))
                break
        else:
            keep.append(i)
    return R[keep].copy(), b[keep]


def implied_rows(speed: np.ndarray, speed_bound: np.ndarray, acc: np.ndarray, acc_bound: np.ndarray) -> np.ndarray:
    """Which acceleration rows (|acc @ (dx_k - dx_k-1)| <= acc_bound) the speed rows (|speed @ dx| <=
    speed_bound, at both steps) imply: a multiple s of a speed row with |s| 2 speed_bound <= acc_bound.
    Boolean (len(acc),)."""
    out = np.zeros(len(acc), dtype=bool)
    for i, r in enumerate(acc):
        scales = [abs(_multiple(r, base)) for base in speed]
        out[i] = any(s > 0.0 and s * 2.0 * b <= acc_bound[i] for s, b in zip(scales, speed_bound, strict=True))
    return out


def shift_index(blocks: tuple[tuple[int, int], ...]) -> np.ndarray:
    """Indices that move a vector of step-by-step blocks ((rows per step, steps) each) one step earlier, the
    last step repeated: ``np.append(v, 0.0)[index]``. A block of one step (rows of step 1 only) takes the
    zero appended past the end (step 2 had no such rows)."""
    total = sum(w * steps for w, steps in blocks)
    idx, start = [], 0
    for w, steps in blocks:
        if steps == 1:
            idx.append(np.full(w, total))
        else:
            k = np.minimum(np.arange(steps) + 1, steps - 1)
            idx.append((start + k[:, None] * w + np.arange(w)).ravel())
        start += w * steps
    return np.concatenate(idx).astype(np.intp)


class Replanner:
    """The horizon NLP for one robot and at most `max_obstacles` obstacles, built once.

    model: the robot's `Model`. options: `ReplanOptions`. safety_distance:
    D_sf (mm, the scene's). rate_limits: the actuators' speed and acceleration
    limits (`RateLimits`, full limits: the NLP uses ``options.limit_fraction`` of
    them); None leaves only the mm/s rate limits. Use `obstacles_from_scene` /
    `obstacles_from_states` to make the obstacle parameter, then `solve`.
    """

    def __init__(
        self,
        model: Model,
        options: ReplanOptions | None = None,
        *,
        max_obstacles: int,
        safety_distance: float,
        rate_limits: RateLimits | None = None,
    ) -> None:
        self.model = model
        self.robot = model.robot
        self.options = ReplanOptions() if options is None else options
        if isinstance(max_obstacles, bool) or not isinstance(max_obstacles, (int, np.integer)) or max_obstacles < 0:
            raise InputError(f"max_obstacles: must be an integer >= 0, got {max_obstacles!r}")
        self.max_obstacles = int(max_obstacles)
        self.safety_distance = check_float(safety_distance, "safety_distance", ge=0.0)
        o, r = self.options, self.robot
        self.nx, self.nq, self.N = r.nx, r.nq, o.horizon
        self.spacing = r.total_length / (o.points - 1)
        self.inflate = margin.inflation(self.safety_distance, r.body_radius, sagitta(r, self.spacing), o.margin)
        A, _ = r.cable_matrix()
        self._A = A
        self.step_limit = np.append(np.full(3 * r.n_segments, o.max_cable_speed), o.max_z_speed) * o.dt  # mm
        self._box = r.config_box()
        self._box_lo, self._box_hi = np.tile(self._box[0], self.N), np.tile(self._box[1], self.N)
        self._scale = np.append(np.repeat([s.length for s in r.segments], 2), 1.0)
        self.rate_limits = None if rate_limits is None else rate_limits.scaled(o.limit_fraction)
        if self.rate_limits is not None and self.rate_limits.jacobian.shape[1] != self.nx:
            raise InputError(
                f"rate_limits: written for {self.rate_limits.jacobian.shape[1]} configuration coordinates, "
                f"robot {r.name!r} has {self.nx}"
            )
        # points per obstacle and step in the QP (0: all of them)
        screens = o.safety and self.max_obstacles > 0 and 0 < o.closest_points < o.points
        self._K = o.closest_points if screens else 0
        # per backbone point of the NLP, its slot parameters: one-hot over the segments, then the fraction
        # of that segment's arc (the QP's slots select their points by them)
        seg, frac = model.arc_segments(model.arc_positions(o.points))
        self._slot_table = np.column_stack([np.eye(r.n_segments)[seg], frac])
        self._build()
        self._warm: dict[str, np.ndarray] | None = None
        self.solve_count = 0

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        o, model = self.options, self.model
        nx, N, M = self.nx, self.N, self.max_obstacles
        X = ca.SX.sym("X", nx, N)
        x0 = ca.SX.sym("x0", nx)
        xm1 = ca.SX.sym("x_prev", nx)
        Xr = ca.SX.sym("x_ref", nx, N)
        Pr = ca.SX.sym("tip_ref", 3, N)
        O = ca.SX.sym("obstacles", packing.WIDTH * M, N)
        S = ca.DM(self._scale)
        Xall = ca.horzcat(xm1, x0, X)  # columns k = -1, 0, 1..N
        tips = model.tip.map(N)(X)  # 3 x N
        res = []
        res.append(math.sqrt(o.tip_weight) * ca.vec(tips - Pr))
        res.append(math.sqrt(o.config_weight) * ca.vec((X - Xr) * ca.repmat(S, 1, N)))
        dX = Xall[:, 2:] - Xall[:, 1:-1]
        res.append(math.sqrt(o.velocity_weight) * ca.vec(dX * ca.repmat(S, 1, N)))
        ddX = Xall[:, 2:] - 2 * Xall[:, 1:-1] + Xall[:, :-2]
        res.append(math.sqrt(o.smooth_weight) * ca.vec(ddX * ca.repmat(S, 1, N)))
        res.append(math.sqrt(o.terminal_weight) * (tips[:, -1] - Pr[:, -1]))
        r_vec = ca.vertcat(*res)
        f = ca.sumsqr(r_vec)
        g, lbg, ubg = [], [], []
        # per-step limits on each actuator's change (linear in x): the mm/s rate limits and, with actuator
        # limits, their speed limits, one row per direction (`merge_parallel_rows`: a speed row parallel to
        # a rate row would be the same constraint twice, and every QP row costs the QP solver time)
        rl = self.rate_limits
        speed_rows = [self._A] if rl is None else [self._A, rl.jacobian]
        speed_bounds = [self.step_limit] if rl is None else [self.step_limit, rl.vmax * o.dt]
        Rv, bv = merge_parallel_rows(np.vstack(speed_rows), np.concatenate(speed_bounds))
        blocks = [(Rv, bv, dX)]
        if rl is not None:
            # actuator acceleration (k = 1 uses x_-1, the previous applied step). From step 2 on, a row
            # parallel to a speed row whose two steps cannot differ by more than the acceleration bound
            # (|s| 2 b_speed <= b_acc) is implied by the speed rows of steps k and k-1, and left out; step 1's
            # is kept, since the measured step before it is not bounded by this NLP.
            Ra, ba = merge_parallel_rows(rl.jacobian, rl.amax * o.dt**2)
            implied = implied_rows(Rv, bv, Ra, ba)
            blocks.append((Ra[~implied], ba[~implied], ddX))
            if implied.any():
                blocks.append((Ra[implied], ba[implied], ddX[:, :1]))
        widths = []
        for R, bound, expr in blocks:
            if not len(bound):
                continue
            steps = expr.size2()
            g.append(ca.vec(ca.DM(R) @ expr))
            lbg.append(np.tile(-bound, steps))
            ubg.append(np.tile(bound, steps))
            widths.append((len(bound), steps))
        # actuation limits
        lim = model.limits.map(N)(X)
        lo, hi = model.limit_bounds()
        g.append(ca.vec(lim))
        lbg.append(np.tile(lo, N))
        ubg.append(np.tile(hi, N))
        widths.append((len(lo), N))
        self._n_lin = int(sum(len(b) for b in lbg))
        p = ca.vertcat(x0, xm1, ca.vec(Xr), ca.vec(Pr), ca.vec(O))
        self._np = int(p.numel())
        self._n_obstacle_p = int(O.numel())  # the obstacle slots are the parameter vector's last entries
        xv = ca.vec(X)
        n, K = o.points, self._K
        self._all_distance: ca.Function | None = None
        # what the compiled KKT check returns besides the residual: every obstacle row and the tips
        self._checked: tuple[ca.SX, ca.SX] = (ca.SX(0, 1), ca.vec(tips))
        # the full NLP (every point of every step against every obstacle) and the QP's NLP, which keeps
        # only the K closest points per obstacle and step (`closest_points`; the same NLP when K = 0)
        g_full, g_red, p_red = list(g), list(g), p
        lb_full, lb_red = list(lbg), list(lbg)
        if o.safety and M > 0:
            x = ca.SX.sym("x", nx)
            ob = ca.SX.sym("ob", packing.WIDTH * M)
            S_ = self.robot.n_segments
            # per slot: one-hot weights over the segments, then the fraction of that segment's arc
            sel = ca.SX.sym("sel", S_ + 1, max(K, 1) * M)
            pts = model.backbone_function(n)(x)  # 3 x n
            seg_points = model.segment_point_function()
            d, ds = [], []
            for i in range(M):
                # the slot's radius is the inflated rho (`_inflated`); padding has rho = 0 at 1e6 mm
                c, rho, _ = packing.slot(ob, i)
                diff = pts - ca.repmat(c, 1, n)
                d.append(ca.sqrt(ca.sum1(diff * diff) + 1e-9).T - rho)
                if K:
                    # slot (i, j) is one backbone point, chosen by parameters: its segment (one-hot) and
                    # the fraction of that segment's arc (one point per segment is computed, not all n)
                    cols = [seg_points(x, sel[S_, i * K + j]) @ sel[:S_, i * K + j] for j in range(K)]
                    diff = ca.horzcat(*cols) - ca.repmat(c, 1, K)
                    ds.append(ca.sqrt(ca.sum1(diff * diff) + 1e-9).T - rho)
            dist = ca.Function("horizon_distance", [x, ob], [ca.vertcat(*d)], {"cse": True})
            D = dist.map(N)(X, O)  # (n M) x N
            g_full.append(ca.vec(D))
            self._checked = (ca.vec(D), ca.vec(tips))
            lb_full.append(np.zeros(n * M * N))
            tag = f"{self.robot.n_segments}s_{M}o_{N}n"
            self._all_distance = ca.Function(f"horizon_all_distance_{tag}", [xv, ca.vec(O)], [D], {"cse": True})
            if K:
                slots = ca.Function("horizon_slot_distance", [x, ob, ca.vec(sel)], [ca.vertcat(*ds)], {"cse": True})
                Sel = ca.SX.sym("selection", (S_ + 1) * K * M, N)
                g_red.append(ca.vec(slots.map(N)(X, O, Sel)))
                lb_red.append(np.zeros(K * M * N))
                p_red = ca.vertcat(p, ca.vec(Sel))
            else:
                g_red, lb_red = g_full, lb_full
        self._n_dist = int(n * M * N) if (o.safety and M > 0) else 0
        if self._n_dist:
            widths.append(((K or n) * M, N))
        # (rows per step, steps) of each constraint block of the QP's NLP, laid out step by step
        self._widths = tuple(widths)
        self._shift_x, self._shift_g = shift_index(((nx, N),)), shift_index(self._widths)
        self._lbg_full = np.concatenate(lb_full)
        self._ubg_full = np.concatenate([*ubg, np.full(len(self._lbg_full) - self._n_lin, np.inf)])
        self._lbg = np.concatenate(lb_red)
        self._ubg = np.concatenate([*ubg, np.full(len(self._lbg) - self._n_lin, np.inf)])
        nlp_full = {"x": xv, "p": p, "f": f, "g": ca.vertcat(*g_full)}
        nlp = {"x": xv, "p": p_red, "f": f, "g": ca.vertcat(*g_red)}
        self.solver = self._solver(o.solver, nlp, self._gauss_newton(r_vec, xv, p_red, len(self._lbg), o.solver))
        self.compiled_message = ""
        self._compiled: tuple[CompiledFunction, CompiledFunction] | None = None
        self._compiled_distance: CompiledFunction | None = None
        if o.compiled:
            self._build_compiled(nlp)
        # the rescue: a failed sqpmethod solve is retried once with IPOPT (robust, slower) on the full NLP
        self.rescue = (
            self._solver("ipopt", nlp_full, self._gauss_newton(r_vec, xv, p, len(self._lbg_full), "ipopt"))
            if o.solver == "sqp" and o.rescue
            else None
        )

    def _gauss_newton(self, r_vec: ca.SX, xv: ca.SX, p: ca.SX, ng: int, kind: str) -> ca.Function | None:
        """The Gauss-Newton Hessian of the least-squares cost for solver `kind` of an NLP with parameters
        p and ng constraints (None: the exact Hessian)."""
        if self.options.hessian != "gauss-newton":
            return None
        # positive semidefinite, so every QP of the SQP path is convex (daqp and qrqp need that), and much
        # cheaper to evaluate than the exact Hessian of hundreds of distance constraints
        lam_f = ca.SX.sym("lam_f")
        lam_g = ca.SX.sym("lam_g", ng)
        Jr = ca.jacobian(r_vec, xv)
        H = 2 * lam_f * (Jr.T @ Jr) + 1e-9 * ca.SX.eye(xv.numel())
        # ipopt wants the upper triangle, sqpmethod the full symmetric matrix
        out = ca.triu(H) if kind == "ipopt" else H
        return ca.Function("nlp_hess_l", [xv, p, lam_f, lam_g], [out], {"cse": True})

    def _build_compiled(self, nlp: dict[str, Any]) -> None:
        """The sqpmethod solver and its KKT residual as generated C, loaded through ctypes (option `compiled`)."""
        o = self.options
        if o.solver != "sqp" or o.qpsol not in CODEGEN_QP:
            self.compiled_message = (
                f"compiled: needs solver 'sqp' with qpsol {' or '.join(CODEGEN_QP)} "
                f"(got {o.solver}/{o.qpsol}): interpreted solver"
            )
            return
        xv, p = nlp["x"], nlp["p"]
        lam_g = ca.SX.sym("lam_g", nlp["g"].numel())
        lam_x = ca.SX.sym("lam_x", xv.numel())
        # the Lagrangian's gradient by one reverse sweep (never the whole constraint Jacobian)
        grad = ca.gradient(nlp["f"] + ca.dot(lam_g, nlp["g"]), xv) + lam_x
        tag = f"{self.robot.n_segments}s_{self.max_obstacles}o_{self.N}n"
        # one call after the solve: the dual residual, every obstacle row of the full NLP and the tips
        outs = [ca.norm_inf(grad), *self._checked]
        kkt = ca.Function(f"horizon_kkt_{tag}", [xv, p, lam_g, lam_x], outs, {"cse": True})
        solver = self.solver
        extra = [] if self._all_distance is None else [self._all_distance]
        try:
            lib, how = compiled_library(f"horizon_{tag}", [solver, kkt, *extra], o.qpsol)
        except (RuntimeError, OSError) as exc:
            self.compiled_message = f"compiled: build failed ({str(exc).strip().splitlines()[-1]}): interpreted solver"
            return
        self.compiled_message = f"compiled: {how}"
        if lib is not None:
            self._compiled = (CompiledFunction(lib, solver.name()), CompiledFunction(lib, kkt.name()))
            if extra:
                self._compiled_distance = CompiledFunction(lib, extra[0].name())

    def _solver(self, kind: str, nlp: dict[str, Any], hess: ca.Function | None) -> ca.Function:
        o = self.options
        # calc_lam_p off: the parametric sensitivities are never used, and computing them is a full
        # gradient over every parameter after each solve
        common: dict[str, Any] = {
            "print_time": False,
            "error_on_fail": False,
            "record_time": True,
            "calc_lam_p": False,
        }
        if hess is not None:
            common["hess_lag"] = hess
        if kind == "ipopt":
            opts = {
                **common,
                "ipopt.print_level": 0,
                "ipopt.sb": "yes",
                "ipopt.max_iter": o.max_iter * o.max_calls,
                "ipopt.tol": o.tol,
                "ipopt.constr_viol_tol": 1e-7,
                "ipopt.acceptable_tol": 1e-4,
                "ipopt.acceptable_constr_viol_tol": 1e-7,
                "ipopt.max_wall_time": o.max_solve_time,
                "ipopt.mu_strategy": "adaptive",
                "ipopt.warm_start_init_point": "yes",
                "ipopt.warm_start_bound_push": 1e-6,
                "ipopt.warm_start_mult_bound_push": 1e-6,
                "ipopt.mu_init": 1e-3,
            }
            return ca.nlpsol("replan_ipopt", "ipopt", nlp, opts)
        qp_opts: dict[str, Any] = {"error_on_fail": False}
        if o.qpsol == "qrqp":
            qp_opts["print_iter"] = False
            qp_opts["print_header"] = False
            # qrqp's default of 1000 active-set iterations can stall one step for seconds
            qp_opts["max_iter"] = 200
        if o.qpsol == "osqp":
            qp_opts["osqp"] = {"verbose": False}
        if o.qpsol == "qpoases":
            qp_opts["printLevel"] = "none"
        opts = {
            **common,
            "qpsol": o.qpsol,
            "qpsol_options": qp_opts,
            "max_iter": o.max_iter,
            "tol_pr": 1e-7,
            "tol_du": o.tol,
            "print_header": False,
            "print_iteration": False,
            "print_status": False,
            "min_step_size": 1e-12,
        }
        if o.hessian == "exact":
            opts["convexify_strategy"] = "regularize"
        return ca.nlpsol("replan_sqp", "sqpmethod", nlp, opts)

    # -------------------------------------------------------------- obstacles
    def _inflated(self, centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """Obstacle parameter (N, packing.WIDTH * M) from sphere centres (N, m, 3) and radii (N, m) in mm.

        Each slot's radius is the inflated rho of the module docstring (the
        NLP compares point distances with it directly).
        """
        rho = np.sqrt((np.maximum(radii, 0.0) + self.inflate) ** 2 + (self.spacing / 2.0) ** 2)
        return packing.pack(centers, rho, self.max_obstacles, "the replanner")

    def step_windows(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) time windows (N,) s that step k's configuration is kept clear over: [t_k-1, t_k+1]."""
        k = np.arange(1, self.N + 1)
        dt = self.options.dt
        return t0 + (k - 1) * dt, t0 + (k + 1) * dt

    def obstacles_from_scene(self, scene: Any, t0: float) -> np.ndarray:
        """Obstacle parameter (N, packing.WIDTH * max_obstacles) for the scene's known motion, horizon from t0 (s)."""
        lo, hi = self.step_windows(float(t0))
        if scene.n_obstacles == 0:
            return self._inflated(np.zeros((self.N, 0, 3)), np.zeros((self.N, 0)))
        centers, radii = scene.swept_spheres(lo, hi)  # (N, M, 3), (N, M)
        return self._inflated(centers, radii)

    def obstacles_from_states(
        self,
        centers: np.ndarray,
        radii: np.ndarray,
        velocities: np.ndarray | None = None,
        radius_rates: np.ndarray | None = None,
        age: float = 0.0,
    ) -> np.ndarray:
        """Obstacle parameter from a live state, extrapolated at constant velocity.

        centers (m, 3) mm, radii (m,) mm, velocities (m, 3) mm/s, radius_rates
        (m,) mm/s, all measured `age` seconds before the horizon starts.
        """
        c = np.asarray(centers, dtype=float).reshape(-1, 3)
        m = len(c)
        r = np.asarray(radii, dtype=float).reshape(m)
        v = np.zeros((m, 3)) if velocities is None else np.asarray(velocities, dtype=float).reshape(m, 3)
        rd = np.zeros(m) if radius_rates is None else np.asarray(radius_rates, dtype=float).reshape(m)
        lo, hi = self.step_windows(float(age))
        ca_ = c[None] + lo[:, None, None] * v[None]
        cb_ = c[None] + hi[:, None, None] * v[None]
        rmax = np.maximum(r[None] + lo[:, None] * rd[None], r[None] + hi[:, None] * rd[None])
        return self._inflated(0.5 * (ca_ + cb_), rmax + 0.5 * np.linalg.norm(cb_ - ca_, axis=-1))

    # ------------------------------------------------------------------ solve
    def reset(self) -> None:
        """Forget the warm start (the next solve starts from the reference)."""
        self._warm = None

    def solve(
        self,
        x0: np.ndarray,
        reference: np.ndarray,
        obstacles: np.ndarray,
        *,
        x_prev: np.ndarray | None = None,
        tip_reference: np.ndarray | None = None,
        warm: bool = True,
        time_left: float | None = None,
    ) -> HorizonResult:
        """Plan x_1..x_N from the current configuration x0 (nx).

        reference: (N, nx) reference configurations for steps 1..N.
        obstacles: (N, packing.WIDTH * max_obstacles) from `obstacles_from_scene` /
        `obstacles_from_states`. x_prev: configuration one step before x0
        (smoothness, and the history of the first step's actuator acceleration
        limit; default x0, i.e. at rest). tip_reference: (N, 3) mm (default: tips of
        the reference). warm: start from the previous solution shifted by one
        step (when there is one). time_left: s left of the step's deadline when the
        solve began (None: no deadline): a failed try is followed by the cold retry
        only while time is left, and never by the rescue (an IPOPT solve takes tens
        of ms): a result after the deadline is not used. A try stopped by the
        iteration cap goes on from its iterate (`_attempt`); one that stops at a
        feasible iterate is not rescued (it is a usable plan) and warm-starts the
        next solve.
        """
        N, nx = self.N, self.nx
        x0 = np.asarray(x0, dtype=float).reshape(nx)
        p = self._parameters(x0, reference, obstacles, x_prev, tip_reference)
        lbx, ubx = self._box_lo, self._box_hi
        args: dict[str, Any] = {"p": p, "lbx": lbx, "ubx": ubx, "lbg": self._lbg, "ubg": self._ubg}
        cold = np.tile(np.clip(x0, self._box[0], self._box[1]), N)  # hold still: rate- and limit-feasible
        used_warm = warm and self._warm is not None and self._warm_fits(x0)
        w = self._warm if used_warm else None
        if w is not None:
            args["x0"] = w["x"]
            if w["lam_g"] is not None:
                args.update(lam_x0=w["lam_x"], lam_g0=w["lam_g"])
        else:
            args["x0"] = cold
        tried: list[dict[str, Any]] = []
        r = self._attempt(args, w, tried, time_left)
        if used_warm and not r["ok"] and self._infeasible(r) and _in_time(tried, time_left):
            # a stale warm start can lead a solver astray: one cold retry before declaring failure (an iterate
            # the iteration cap stopped inside the constraints is a usable, if suboptimal, plan)
            args = {k: v for k, v in args.items() if k not in ("lam_x0", "lam_g0")}
            args["x0"] = cold
            r = self._attempt(args, None, tried, time_left)
        rescued = False
        # the rescue is for a failed solve: an iterate the cap stopped inside every constraint is a usable plan
        if not r["ok"] and self.rescue is not None and time_left is None and self._infeasible(r):
            rescued = True
            # IPOPT solves the full NLP: every point of every step against every obstacle
            args = {"p": p, "lbx": lbx, "ubx": ubx, "lbg": self._lbg_full, "ubg": self._ubg_full, "x0": cold}
            r = self._call(self.rescue, args)
            r["status"] = f"{tried[-1]['status']}; rescue ipopt: {r['status']}"
            tried.append(r)
        r["wall"] = sum(x["wall"] for x in tried)
        self.solve_count += 1
        configs = r["x"].reshape(N, nx)
        status = horizon_status(r["ok"], configs, r["violation"])
        # a feasible iterate (converged, or stopped by the iteration cap) is the next solve's warm start
        self._warm = self._shifted(r, reduced=not rescued) if status is not HorizonStatus.FAILED else None
        return HorizonResult(
            configs=configs,
            tips=self._tips(r, configs),
            status=status,
            solver_status=r["status"],
            iterations=r["iterations"],
            wall_time=r["wall"],
            cost=r["cost"],
            min_distance=r["min_distance"],
            violation=r["violation"],
            warm=used_warm,
            extra={"attempts": len(tried), "rescue": rescued, "screen_solves": sum(x["solves"] for x in tried)},
        )

    def _parameters(
        self, x0: np.ndarray, reference: Any, obstacles: Any, x_prev: Any, tip_reference: Any
    ) -> np.ndarray:
        """The NLP's parameter vector from `solve`'s inputs; `InputError` for a wrong shape or NaN."""
        N, nx = self.N, self.nx
        Xr = np.asarray(reference, dtype=float).reshape(N, nx)
        xm1 = x0 if x_prev is None else np.asarray(x_prev, dtype=float).reshape(nx)
        Pr = self.model.tip_position(Xr) if tip_reference is None else np.asarray(tip_reference, float).reshape(N, 3)
        Ob = np.asarray(obstacles, dtype=float)
        if Ob.size != N * packing.WIDTH * self.max_obstacles:
            raise InputError(
                f"obstacles: expected shape ({N}, {packing.WIDTH * self.max_obstacles}) from obstacles_from_scene "
                f"or obstacles_from_states, got {Ob.shape}"
            )
        Ob = Ob.reshape(N, packing.WIDTH * self.max_obstacles)
        p = np.concatenate([x0, xm1, Xr.ravel(), Pr.ravel(), Ob.ravel()])
        if not np.isfinite(p).all():
            # one check of the whole vector; the slow search for the culprit only when there is one
            for name, arr in (("x0", x0), ("reference", Xr), ("x_prev", xm1), ("tip_reference", Pr), ("obstacles", Ob)):
                if not np.isfinite(arr).all():
                    raise InputError(f"{name}: contains NaN or infinity")
        return p

    def _warm_fits(self, x0: np.ndarray) -> bool:
        """The shifted previous solution starts within reach of x0 (else it belongs to another situation)."""
        first = self._warm["x"][: self.nx] if self._warm is not None else None
        if first is None:
            return False
        return bool(np.all(np.abs(self._A @ (first - x0)) <= 2.0 * self.step_limit + 1e-9))

    def _call(self, solver: ca.Function, args: dict[str, Any]) -> dict[str, Any]:
        """One solver call and an independent look at what it returned."""
        t_start = time.perf_counter()
        if solver is self.solver and self._compiled is not None:
            sol, st = self._call_compiled(args)
        else:
            sol = solver.call(args)
            st = solver.stats()
        wall = time.perf_counter() - t_start
        xs = np.asarray(sol["x"]).ravel()
        gs = np.asarray(sol["g"]).ravel()
        finite = bool(np.isfinite(xs).all() and np.isfinite(gs).all())
        if not finite:
            viol = math.inf
        elif "violation" in st:
            viol = st["violation"]  # the compiled call's own check, of the same point and rows
        else:
            viol = self._violation(xs, gs, args["lbg"], args["ubg"])
        return {
            "sol": sol,
            "x": xs,
            "wall": wall,
            "finite": finite,
            "violation": viol,
            "status": str(st.get("return_status", "unknown")),
            "ok": bool(st.get("success", False)) and finite and viol <= 1e-6,
            "iterations": int(st.get("iter_count", -1)),
            "cost": float(sol["f"]) if finite else math.inf,
            # the smallest obstacle row (of the full NLP; `_call_screened` checks every point after a QP NLP)
            "min_distance": float(np.min(gs[self._n_lin :])) if (self._n_dist and finite) else math.inf,
            "solves": 1,
        }

    def _call_compiled(self, args: dict[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """One call of the compiled solver: its outputs and the stats sqpmethod would give (success by its
        own test: primal violation < 1e-7 and dual residual < tol, recomputed at the returned point)."""
        step, kkt = self._compiled  # type: ignore[misc]
        names = ("x0", "p", "lbx", "ubx", "lbg", "ubg", "lam_x0", "lam_g0")
        out = step(*[args.get(n) for n in names])
        sol = dict(zip(("x", "f", "g", "lam_x", "lam_g", "lam_p"), (a.copy() for a in out), strict=True))
        sol["f"] = float(sol["f"][0])
        du_, distances, tips = kkt(sol["x"], args["p"], sol["lam_g"], sol["lam_x"])
        du = float(du_[0])
        sol["distances"], sol["tips"] = distances.copy(), tips.copy()
        pr = self._violation(sol["x"], sol["g"], args["lbg"], args["ubg"])
        ok = bool(np.isfinite(du) and np.isfinite(pr)) and pr < 1e-7 and du < self.options.tol
        status = "Solve_Succeeded" if ok else f"Not_Converged (compiled sqpmethod: primal {pr:.2g}, dual {du:.2g})"
        return sol, {"success": ok, "return_status": status, "iter_count": -1, "violation": pr}

    def _violation(self, xs: np.ndarray, gs: np.ndarray, lbg: np.ndarray, ubg: np.ndarray) -> float:
        """Largest violation of the box and of the rows lbg <= g <= ubg (mixed units; 0 when all hold)."""
        return max(
            float(np.max(lbg - gs, initial=0.0)),
            float(np.max(gs - ubg, initial=0.0)),
            float(np.max(self._box_lo - xs, initial=0.0)),
            float(np.max(xs - self._box_hi, initial=0.0)),
        )

    def _call_screened(self, args: dict[str, Any], warm: dict[str, Any] | None) -> dict[str, Any]:
        """One solve of the QP's NLP (`_call`); with `closest_points`, the K closest backbone points per
        obstacle and step at the start point are its obstacle rows, and every point is checked at the
        solution. A solution that leaves an omitted point inside its sphere is solved again, from there, with
        the closest points there (at most `SCREEN_SOLVES` solves); if one still does, the result is not ok.
        A solution whose omitted points all hold is a KKT point of the full NLP too (their multipliers are
        zero), so "ok" means what it means without screening. warm: the shifted previous solve (`_shifted`)
        the start point is, or None: its selection (that its multipliers belong to) and its obstacle rows
        shifted (the same windows one step later: the first selection needs no evaluation of its own)."""
        if not self._K:
            return self._call(self.solver, args)
        t_start = time.perf_counter()
        args = dict(args)
        p, O = args["p"], args["p"][self._np - self._n_obstacle_p :]
        known = warm is not None and warm["dist"] is not None
        sel = self._nearest(warm["dist"]) if known else self._closest(args["x0"], O)  # type: ignore[index]
        if "lam_g0" in args and warm is not None and warm["sel"] is not None:
            args["lam_g0"] = self._keep_multipliers(args["lam_g0"], warm["sel"], sel)
        solves = 0
        while True:
            args["p"] = np.concatenate([p, self._selection(sel)])
            r = self._call(self.solver, args)
            solves += 1
            if not r["finite"]:
                break
            D = r["sol"]["distances"] if "distances" in r["sol"] else self._distances(r["x"], O)
            r["distances"] = D.reshape(self.N, self.max_obstacles, self.options.points)
            dmin = float(np.min(D))
            r["min_distance"] = dmin
            r["violation"] = max(r["violation"], -dmin)
            r["ok"] = r["ok"] and r["violation"] <= 1e-6
            if dmin >= -1e-6 or solves >= SCREEN_SOLVES:
                if dmin < -1e-6:
                    r["status"] += f"; an omitted point stays {-dmin:.3g} mm inside its sphere"
                break
            # an omitted point entered its sphere: again, with the closest points of this solution
            new = self._closest(r["x"], O)
            lam_g = self._keep_multipliers(np.asarray(r["sol"]["lam_g"]).ravel(), sel, new)
            args.update(x0=r["x"], lam_x0=np.asarray(r["sol"]["lam_x"]).ravel(), lam_g0=lam_g)
            sel = new
        r["selection"], r["solves"] = sel, solves
        r["wall"] = time.perf_counter() - t_start
        return r

    def _tips(self, r: dict[str, Any], configs: np.ndarray) -> np.ndarray:
        """Tip positions (N, 3) mm of a solve's configurations (NaN when they are not finite)."""
        if not r["finite"]:
            return np.full((self.N, 3), np.nan)
        if "tips" in r["sol"]:
            return r["sol"]["tips"].reshape(self.N, 3)  # computed by the compiled KKT check
        return self.model.tip_position(configs)

    def _distances(self, xs: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """Obstacle rows of the full NLP (N, M, points), mm: distance of each backbone point of each step
        from the obstacle slot's centre minus its inflated radius, at configurations xs (N nx,)."""
        if self._compiled_distance is not None:
            d = self._compiled_distance(xs, obstacles)[0]
        else:
            d = np.asarray(self._all_distance(xs, obstacles)).ravel(order="F")  # type: ignore[misc]
        return d.reshape(self.N, self.max_obstacles, self.options.points)

    def _closest(self, xs: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """Indices (N, M, K) of the K backbone points closest to each obstacle slot at each step, ascending
        (so the same set gives the same slots, and the warm start's multipliers stay with their points)."""
        return self._nearest(self._distances(np.asarray(xs, dtype=float), obstacles))

    def _nearest(self, d: np.ndarray) -> np.ndarray:
        """`_closest` from the obstacle rows d (N, M, points)."""
        return np.sort(np.argsort(d, axis=-1, kind="stable")[..., : self._K], axis=-1)

    def _selection(self, selection: np.ndarray) -> np.ndarray:
        """The selection parameter of the QP's NLP: per slot, a one-hot column over the segments and the
        fraction of that segment's arc where the selected backbone point lies."""
        return self._slot_table[selection].ravel()

    def _keep_multipliers(self, lam_g: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """lam_g with the multipliers of the obstacle slots whose point changed set to zero."""
        lam = np.array(lam_g, dtype=float)
        lam[self._n_lin :].reshape(old.shape)[old != new] = 0.0
        return lam

    def _attempt(
        self, args: dict[str, Any], start: dict[str, Any] | None, tried: list[dict[str, Any]], time_left: float | None
    ) -> dict[str, Any]:
        """A solve from args' start point (appended to `tried`): calls of max_iter iterations each, the next going
        on from the last one's iterate (with its multipliers and rows) while calls are left and it has not
        converged and has not diverged (`DIVERGED`). Under a deadline (time_left not None) only while time is left
        and only from an iterate that breaks a constraint: one inside every constraint is the plan (the deadline's
        time is the step's); without one, to convergence, so that the cap changes how the work is split, not what
        a solve returns."""
        r = self._call_screened(args, start)
        tried.append(r)
        for _ in range(self.options.max_calls - 1):
            if r["ok"] or not r["finite"] or r["violation"] > DIVERGED or not _in_time(tried, time_left):
                break
            if time_left is not None and not self._infeasible(r):
                break
            sol = r["sol"]
            lam = {"lam_x0": np.asarray(sol["lam_x"]).ravel(), "lam_g0": np.asarray(sol["lam_g"]).ravel()}
            r = self._call_screened({**args, "x0": r["x"], **lam}, self._here(r))
            tried.append(r)
        return r

    def _infeasible(self, r: dict[str, Any]) -> bool:
        """A solver call's iterate breaks a constraint (or is not finite): not a usable plan."""
        return horizon_status(False, r["x"].reshape(self.N, self.nx), r["violation"]) is HorizonStatus.FAILED

    def _here(self, r: dict[str, Any]) -> dict[str, Any]:
        """A solve's own iterate as the start of the next call (`_call_screened`'s warm argument, not shifted)."""
        return {"dist": r.get("distances"), "sel": r.get("selection")}

    def _shifted(self, r: dict[str, Any], reduced: bool) -> dict[str, Any]:
        """Previous solution moved one step earlier, the last step repeated (the next solve's start), with
        its selection and obstacle rows (`_call_screened`). Multipliers only from a solve of the QP's NLP
        (`reduced`; a rescue solved the full NLP, whose rows are others when `closest_points` screens)."""

        def steps(a: np.ndarray) -> np.ndarray:
            return np.concatenate([a[1:], a[-1:]])

        out: dict[str, Any] = {"x": np.append(r["x"], 0.0)[self._shift_x], "lam_x": None, "lam_g": None}
        if reduced or not self._K:
            out["lam_x"] = np.append(np.asarray(r["sol"]["lam_x"]).ravel(), 0.0)[self._shift_x]
            out["lam_g"] = np.append(np.asarray(r["sol"]["lam_g"]).ravel(), 0.0)[self._shift_g]
        out["sel"] = steps(r["selection"]) if "selection" in r else None
        out["dist"] = steps(r["distances"]) if "distances" in r else None
        return out

    def describe(self) -> dict[str, Any]:
        """Sizes of the NLP (for result files and benchmarks)."""
        return {
            "solver": (self.options.solver if self.options.solver == "ipopt" else f"sqpmethod+{self.options.qpsol}")
            + (" (compiled C)" if self._compiled is not None else ""),
            "rescue": "ipopt" if self.rescue is not None else None,
            "max_iter": self.options.max_iter,
            "max_calls": self.options.max_calls,
            "step_deadline_s": self.options.step_deadline,
            "variables": self.nx * self.N,
            "parameters": self._np,
            "constraints": len(self._lbg),
            "actuator_limits": None if self.rate_limits is None else list(self.rate_limits.names),
            "limit_fraction": self.options.limit_fraction,
            "obstacle_constraints": self._n_dist,
            "qp_obstacle_rows": (self._K or self.options.points) * self.max_obstacles * self.N if self._n_dist else 0,
            "max_obstacles": self.max_obstacles,
            "inflate_mm": self.inflate,
            "point_spacing_mm": self.spacing,
        }
