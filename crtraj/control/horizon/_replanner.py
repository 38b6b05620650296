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

The actuator limits (`crtraj.model.rate_limits.RateLimits`, J = d actuator value / d x) are linear
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

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from crtraj.control.horizon._backends import (
    SCREEN_SOLVES,
    CompiledBackend,
    HorizonCall,
    HorizonQuery,
    InterpretedBackend,
    ObstacleRows,
    PointScreen,
    RowCheck,
    ScreenedBackend,
    ScreenStart,
    replace,
)
from crtraj.control.horizon._broad import BroadPhase, Selection
from crtraj.control.horizon._buffers import ParameterBuffer
from crtraj.control.horizon._build import (
    CompiledParts,
    HorizonNLP,
    HorizonSpec,
    build_compiled,
    build_nlp,
    gauss_newton,
    nlp_solver,
)
from crtraj.control.horizon._obstacles import ObstacleTable, swept_states
from crtraj.control.horizon._options import (
    DIVERGED,
    HorizonResult,
    HorizonStatus,
    ReplanOptions,
    horizon_status,
)
from crtraj.control.horizon._rod_body import LinearCorrection, LinearisedBackend, reach_bound
from crtraj.control.horizon._rows import sagitta
from crtraj.control.horizon._shapes import HorizonShapes
from crtraj.control.horizon._stage import StageSolver
from crtraj.core.errors import InputError
from crtraj.core.fields import check_float
from crtraj.model.cosserat import RodModel
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits
from crtraj.world import margin, packing
from crtraj.world.geometry import MovingShape

__all__ = ["Replanner"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Warm:
    """The previous solution moved one step earlier (the next solve's start): x (N nx,), its multipliers (None
    after a rescue of a screened NLP) and what the screening knows of it."""

    x: np.ndarray
    lam_x: np.ndarray | None
    lam_g: np.ndarray | None
    start: ScreenStart


def _in_time(tried: list[HorizonCall], time_left: float | None) -> bool:
    """The solver calls so far (their wall, s) leave time before the deadline (always, without one)."""
    return time_left is None or sum(x.wall for x in tried) < time_left


class Replanner:
    """The horizon NLP for one robot and at most `max_obstacles` obstacles, built once.

    model: the robot's `Model`. options: `ReplanOptions`. safety_distance: D_sf (mm, the scene's). rate_limits:
    the actuators' speed and acceleration limits (`RateLimits`, full limits: the NLP uses ``options.limit_fraction``
    of them); None leaves only the mm/s rate limits. Use `obstacles_from_scene` / `obstacles_from_states` to make
    the obstacle parameter, then `solve`.
    solver_wrapper: called once with the interpreted solver of the QP's NLP (`solver`); what it returns (anything
    with ``call(args)`` and ``stats()``) is called instead, e.g. to inject a solver's failure (unused when the
    compiled C runs). rod_linear: a `RodModel`'s correction to first order about each call's start point
    (`crtraj.control.horizon._rod_body`); False: in full (interpreted only; the earlier path, for comparison).

    How a query is solved is chosen once here (`backend`): the interpreted solver or its compiled C, wrapped in
    the screening of `closest_points` when it applies; `rescue` is the IPOPT backend of the full NLP or None.
    """

    def __init__(
        self,
        model: Model,
        options: ReplanOptions | None = None,
        *,
        max_obstacles: int,
        safety_distance: float,
        rate_limits: RateLimits | None = None,
        solver_wrapper: Callable[[ca.Function], Any] | None = None,
        shapes: tuple[MovingShape, ...] = (),
        rod_linear: bool = True,
    ) -> None:
        self.model, self.robot = model, model.robot
        self.options = ReplanOptions() if options is None else options
        self.linear = LinearCorrection(model) if rod_linear and isinstance(model, RodModel) else None
        self._n_linear = 0 if self.linear is None else self.linear.n_params * self.options.horizon
        if isinstance(max_obstacles, bool) or not isinstance(max_obstacles, (int, np.integer)) or max_obstacles < 0:
            raise InputError(f"max_obstacles: must be an integer >= 0, got {max_obstacles!r}")
        self.max_obstacles = int(max_obstacles)
        self.safety_distance = check_float(safety_distance, "safety_distance", ge=0.0)
        o, r = self.options, self.robot
        self.nx, self.nq, self.N = r.nx, r.nq, o.horizon
        self.spacing = r.total_length / (o.points - 1)
        self.inflate = margin.inflation(self.safety_distance, r.body_radius, sagitta(r, self.spacing), o.margin)
        self.shapes = HorizonShapes(r, tuple(shapes), o.safety, self.safety_distance, o.points, o.margin)
        self._A, _ = r.cable_matrix()
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
        arcs = model.arc_positions(o.points)
        seg, frac = model.arc_segments(arcs)
        extra = [] if self.linear is None else [self.linear.correction.weights(arcs)]  # the rod's (`_slot_point`)
        self._slot_table = np.column_stack([np.eye(r.n_segments)[seg], frac, *extra])
        self._build(solver_wrapper)
        # with the fused call (issue 29) the parameters are written in place into one preallocated buffer
        self._buffer = (
            ParameterBuffer(model, self.N, self.max_obstacles, self.shapes.n_params, self._n_linear)
            if self.compiled and o.fused
            else None
        )
        # which obstacles of a larger scene enter the QP's slots (`obstacles_from_scene` with x0)
        self.broad = BroadPhase(model, o.points, self.step_limit, self.N)
        self.broad_overflows = 0  # steps on which more obstacles could matter than the QP has slots
        self._selection: Selection | None = None  # those, when they did (checked at the solution)
        # a known scene's spheres for the run's step times, tabulated before it (`ObstacleTable.tabulate`)
        self.obstacle_table = ObstacleTable(self.step_windows, self._rho, self.max_obstacles)
        self._warm: _Warm | None = None
        self._selected: np.ndarray | None = None  # the parameter `obstacles_from_scene` made with `_selection`
        self.solve_count = 0

    # ------------------------------------------------------------------ build
    def _build(self, solver_wrapper: Callable[[ca.Function], Any] | None) -> None:
        """The NLP (`build_nlp`), its solvers and the backends that solve it, chosen once."""
        o = self.options
        spec = HorizonSpec(
            model=self.model if self.linear is None else self.linear.pcc,
            options=o,
            max_obstacles=self.max_obstacles,
            cable_matrix=self._A,
            step_limit=self.step_limit,
            scale=self._scale,
            rate_limits=self.rate_limits,
            closest_points=self._K,
            shapes=self.shapes.terms,
            shape_keep=self.shapes.keep,
            shape_points=self.shapes.points,
            linear=self.linear,
        )
        nlp = self._nlp = build_nlp(spec)
        if o.solver == "sqp" and o.qpsol == "hpipm":
            # the stage form for HPIPM (`horizon_stage`), called like the dense solver
            self.solver = StageSolver(spec, nlp)
        else:
            self.solver = nlp_solver(o.solver, o, nlp.nlp, gauss_newton(o, nlp.r_vec, nlp.nlp, o.solver))
        self.compiled_message = ""
        parts: CompiledParts | None = None
        if o.compiled:
            stage = getattr(self.solver, "function", None)  # the stage form's dense-interface function
            self.compiled_message, parts = build_compiled(spec, nlp, self.solver if stage is None else stage)
            (log.debug if parts is not None else log.warning)("horizon: %s", self.compiled_message)
        self._rows = None
        if nlp.all_distance is not None:
            shape = (self.N, self.max_obstacles, o.points)
            self._rows = ObstacleRows(nlp.all_distance, None if parts is None else parts.distance, shape)
        self._screen = PointScreen(self._K, self._slot_table, nlp.n_lin + nlp.n_shape)
        self.compiled = parts is not None  # the generated C runs (else the interpreted solver)
        self.backend = self._backend(nlp, parts, solver_wrapper)
        self.rescue: InterpretedBackend | LinearisedBackend | None = None
        if o.solver == "sqp" and o.rescue:
            # the rescue: a failed sqpmethod solve is retried once with IPOPT (robust, slower) on the full NLP
            hess = gauss_newton(o, nlp.r_vec, nlp.nlp_full, "ipopt")
            full = RowCheck(
                self._box_lo, self._box_hi, nlp.lbg_full, nlp.ubg_full, nlp.n_lin, nlp.n_dist + nlp.n_shape > 0
            )
            self.rescue = InterpretedBackend("ipopt", nlp_solver("ipopt", o, nlp.nlp_full, hess), full)
        if self.linear is not None:  # each call linearises the rod's correction about its own start point
            self.backend = LinearisedBackend(self.backend, self.linear, self.N)
            if self.rescue is not None:
                self.rescue = LinearisedBackend(self.rescue, self.linear, self.N)

    def _backend(
        self, nlp: HorizonNLP, parts: CompiledParts | None, solver_wrapper: Callable[[ca.Function], Any] | None
    ) -> InterpretedBackend | CompiledBackend | ScreenedBackend:
        """The backend of the QP's NLP: the compiled C when it was built, else the interpreted solver; screened
        when `closest_points` keeps fewer than every point."""
        check = RowCheck(self._box_lo, self._box_hi, nlp.lbg, nlp.ubg, nlp.n_lin, nlp.n_dist + nlp.n_shape > 0)
        call: InterpretedBackend | CompiledBackend
        if parts is not None:
            call = CompiledBackend(parts, check, self.options.tol)
        else:
            solver = self.solver if solver_wrapper is None else solver_wrapper(self.solver)
            call = InterpretedBackend(self.options.solver, solver, check)
        if not self._K or self._rows is None:
            return call
        return ScreenedBackend(call, self._screen, self._rows, self.nearest_points, nlp.n_obstacle_p)

    # -------------------------------------------------------------- obstacles
    def _inflated(self, centers: np.ndarray, radii: np.ndarray) -> np.ndarray:
        """Obstacle parameter (N, packing.WIDTH * M) from sphere centres (N, m, 3) and radii (N, m) in mm.

        Each slot's radius is the inflated rho of the module docstring (the
        NLP compares point distances with it directly).
        """
        return packing.pack(centers, self._rho(radii), self.max_obstacles, "the replanner")

    def _rho(self, radii: np.ndarray) -> np.ndarray:
        """The inflated radii (mm) the NLP keeps its points outside of, from sphere radii (mm)."""
        return np.sqrt((np.maximum(radii, 0.0) + self.inflate) ** 2 + (self.spacing / 2.0) ** 2)

    def step_windows(self, t0: Any) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) windows (N,) s step k's configuration is kept clear over: [t_k-1, t_k+1]; t0 (T, 1): (T, N)."""
        k = np.arange(1, self.N + 1)
        dt = self.options.dt
        return t0 + (k - 1) * dt, t0 + (k + 1) * dt

    @property
    def obstacle_width(self) -> int:
        """Obstacle parameters per step: the sphere slots (packing.WIDTH each), then the shapes' (`ShapeTerms`)."""
        return packing.WIDTH * self.max_obstacles + self.shapes.n_params

    def obstacles_from_scene(self, scene: Any, t0: float, x0: np.ndarray | None = None) -> np.ndarray:
        """Obstacle parameter (N, `obstacle_width`) for the scene's known motion, horizon from t0 (s): per step the
        sphere slots, then the shapes' parameters over the step's window (`shape_parameters`).

        x0: the configuration (nx,) the horizon starts from. With it, a scene of more obstacles than the NLP's
        slots fills them with the obstacles the horizon's reachable body can come near (`BroadPhase`): the
        others cannot be active in any plan within reach. Without it such a scene is an `InputError`."""
        self._selection = self._selected = None
        if scene.n_obstacles == 0:
            out = self._inflated(np.zeros((self.N, 0, 3)), np.zeros((self.N, 0)))
        else:
            packed, centers, rho = self.obstacle_table.spheres(scene, float(t0))  # looked up if tabulated
            if x0 is not None and scene.n_obstacles > self.max_obstacles:
                out, self._selection = self.broad.pack(np.asarray(x0, float), centers, rho, self.max_obstacles)
                self.broad_overflows += self._selection is not None
            else:
                out = packed if packed is not None else packing.pack(centers, rho, self.max_obstacles, "the replanner")
        if self.shapes.n_params:  # each step's window of the shapes (`HorizonShapes.parameters`)
            shapes = self.shapes.parameters(scene, *self.step_windows(float(t0) + scene.time_origin))
            out = np.concatenate([out, shapes], axis=1)
        if self._selection is not None:
            self._selected = out  # `solve` checks the omitted obstacles when it is given this parameter
        return out

    def obstacles_from_states(
        self,
        centers: np.ndarray,
        radii: np.ndarray,
        velocities: np.ndarray | None = None,
        radius_rates: np.ndarray | None = None,
        age: float = 0.0,
    ) -> np.ndarray:
        """Obstacle parameter from a live state, extrapolated at constant velocity (`swept_states`), measured `age`
        s before the horizon starts. Not for a replanner with shapes (their motion is the scene's)."""
        if self.shapes.n_params:
            raise InputError(
                "obstacles: the replanner has shapes, whose motion is the scene's: use obstacles_from_scene"
            )
        return self._inflated(*swept_states(centers, radii, velocities, radius_rates, *self.step_windows(float(age))))

    def tabulate_obstacles(self, scene: Any, times: np.ndarray) -> None:
        """Tabulate a known scene's obstacle spheres for the run's step start times (s), before the run."""
        self.obstacle_table.tabulate(scene, times)

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
        x0 = np.asarray(x0, dtype=float).reshape(self.nx)
        if tip_reference is None and self.linear is not None:
            tip_reference = self.linear.tips(np.asarray(reference, dtype=float).reshape(self.N, self.nx))
        fill = self._parameters if self._buffer is None else self._buffer.fill
        p = fill(x0, reference, obstacles, x_prev, tip_reference)

        def cold() -> HorizonQuery:  # hold still: feasible (made only when it is tried)
            return HorizonQuery(p, np.tile(np.clip(x0, self._box[0], self._box[1]), self.N))

        used_warm = warm and self._warm is not None and self._warm_fits(x0)
        w = self._warm if used_warm else None
        query = cold() if w is None else HorizonQuery(p, w.x, w.lam_x, w.lam_g, w.start)
        tried: list[HorizonCall] = []
        r = self._attempt(query, tried, time_left)
        if used_warm and not r.ok and self._infeasible(r) and _in_time(tried, time_left):
            # a stale warm start can lead a solver astray: one cold retry before declaring failure (an iterate
            # the iteration cap stopped inside the constraints is a usable, if suboptimal, plan)
            r = self._attempt(cold(), tried, time_left)
        rescued = False
        # the rescue is for a failed solve: an iterate the cap stopped inside every constraint is a usable plan
        if not r.ok and self.rescue is not None and time_left is None and self._infeasible(r):
            rescued = True
            # IPOPT solves the full NLP: every point of every step against every obstacle
            rr = self.rescue.solve(cold())
            log.debug("horizon: rescue ipopt after %s: %s", tried[-1].status, rr.status)
            r = replace(rr, status=f"{tried[-1].status}; rescue ipopt: {rr.status}")
            tried.append(r)
        if self._selection is not None and obstacles is self._selected:
            r = self._omitted(r, p, tried, time_left)
        r = replace(r, wall=sum(x.wall for x in tried))
        return self._result(r, tried, rescued, used_warm)

    def _result(self, r: HorizonCall, tried: list[HorizonCall], rescued: bool, used_warm: bool) -> HorizonResult:
        """The result of a solve whose last call is r (of the calls `tried`); keeps its warm start."""
        self.solve_count += 1
        configs = r.x.reshape(self.N, self.nx)
        status = horizon_status(r.ok, configs, r.violation)
        # a feasible iterate (converged, or stopped by the iteration cap) is the next solve's warm start
        self._warm = self._shifted(r, reduced=not rescued) if status is not HorizonStatus.FAILED else None
        return HorizonResult(
            configs=configs,
            tips=self._tips(r, configs),
            status=status,
            solver_status=r.status,
            iterations=r.iterations,
            wall_time=r.wall,
            cost=r.cost,
            min_distance=r.min_distance,
            violation=r.violation,
            warm=used_warm,
            extra={"attempts": len(tried), "rescue": rescued, "screen_solves": sum(x.solves for x in tried)},
        )

    def _parameters(self, *args: Any) -> np.ndarray:
        """`_parameter_vector` of this replanner: `solve`'s inputs as the NLP's parameters."""
        return _parameter_vector(self, *args)

    def _warm_fits(self, x0: np.ndarray) -> bool:
        """The shifted previous solution starts within reach of x0 (else it belongs to another situation)."""
        first = self._warm.x[: self.nx] if self._warm is not None else None
        if first is None:
            return False
        return bool(np.all(np.abs(self._A @ (first - x0)) <= 2.0 * self.step_limit + 1e-9))

    def distances(self, xs: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """Obstacle rows of the full NLP (N, M, points), mm: distance of each backbone point of each step from
        the obstacle slot's centre minus its inflated radius, at configurations xs (N nx,); obstacles: the
        (N, packing.WIDTH * M) parameter. `InputError` when the NLP has no obstacle rows."""
        if self._rows is None:
            raise InputError("obstacles: this replanner has no obstacle rows (safety off or max_obstacles = 0)")
        xs, ob = np.asarray(xs, dtype=float), np.asarray(obstacles, dtype=float).ravel()
        if isinstance(self.backend, LinearisedBackend) and ob.size == self.N * self.obstacle_width:
            ob = self.backend.fill(np.append(ob, np.zeros(self._n_linear)), xs)  # about xs: the full body there
        return self._rows(xs, ob)

    def nearest_points(self, xs: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """Indices (N, M, K) of the K = `closest_points` backbone points closest to each obstacle slot at each
        step of configurations xs (N nx,), ascending (so the same set gives the same slots, and the warm start's
        multipliers stay with their points): the points the screened QP keeps as its rows (none when K = 0)."""
        return self._screen.nearest(self.distances(xs, obstacles))

    def _attempt(self, query: HorizonQuery, tried: list[HorizonCall], time_left: float | None) -> HorizonCall:
        """A solve from the query's start point (appended to `tried`): calls of max_iter iterations each, the
        next going on from the last one's iterate (with its multipliers and rows) while calls are left and it has
        not converged and has not diverged (`DIVERGED`). Under a deadline (time_left not None) only while time
        is left and only from an iterate that breaks a constraint: one inside every constraint is the plan (the
        deadline's time is the step's); without one, to convergence, so that the cap changes how the work is
        split, not what a solve returns."""
        r = self.backend.solve(query)
        tried.append(r)
        for _ in range(self.options.max_calls - 1):
            if r.ok or not r.finite or r.violation > DIVERGED or not _in_time(tried, time_left):
                break
            if time_left is not None and not self._infeasible(r):
                break
            lam_x, lam_g = np.asarray(r.sol["lam_x"]).ravel(), np.asarray(r.sol["lam_g"]).ravel()
            here = ScreenStart(r.distances, r.selection)  # the call's own iterate, not shifted
            r = self.backend.solve(replace(query, x0=r.x, lam_x0=lam_x, lam_g0=lam_g, start=here))
            tried.append(r)
        return r

    def _omitted(self, r: HorizonCall, p: np.ndarray, tried: list[HorizonCall], time_left: float | None) -> HorizonCall:
        """r checked against the obstacles the broad phase left out of a full QP (`BroadPhase.reselect`): solved
        again from its point with the ones it enters in the slots (at most `SCREEN_SOLVES` times, while time is
        left); if one is still entered, r with that violation (not a usable plan). A failed call is returned as is."""
        sel = self._selection
        for solves in range(SCREEN_SOLVES + 1):
            if sel is None or self._infeasible(r):
                return r  # a failed call is no plan either way
            P = self.model.points(r.x.reshape(self.N, self.nx), self.options.points)
            worst, sel = self.broad.reselect(sel, P, self.max_obstacles)
            if sel is None:
                return r
            if solves == SCREEN_SOLVES or not _in_time(tried, time_left):
                break
            p = p.copy()
            end = len(p) - self._n_linear  # the rod correction's parameters follow the obstacles
            Ob = p[end - self.N * self.obstacle_width : end].reshape(self.N, self.obstacle_width)
            Ob[:, : sel.packed.shape[1]] = sel.packed  # the sphere slots; the shapes' parameters stay
            r = self._attempt(HorizonQuery(p, r.x), tried, time_left)
        why = f"; an obstacle left out of the QP stays {-worst:.3g} mm inside its sphere"
        return replace(r, violation=max(r.violation, -worst), ok=False, status=r.status + why)

    def _infeasible(self, r: HorizonCall) -> bool:
        """`horizon_status`'s FAILED from `RowCheck.record`'s look (finite covers x; not finite: violation inf)."""
        return not (r.finite and r.violation <= 1e-6)

    def _shifted(self, r: HorizonCall, reduced: bool) -> _Warm:
        """Previous solution moved one step earlier, the last step repeated (the next solve's start), with its
        selection and obstacle rows (`ScreenedBackend`). Multipliers only from a solve of the QP's NLP
        (`reduced`; a rescue solved the full NLP, whose rows are others when `closest_points` screens)."""

        def steps(a: np.ndarray) -> np.ndarray:
            return np.concatenate([a[1:], a[-1:]])

        lam_x = lam_g = None
        if reduced or not self._K:
            lam_x = np.append(np.asarray(r.sol["lam_x"]).ravel(), 0.0)[self._nlp.shift_x]
            lam_g = np.append(np.asarray(r.sol["lam_g"]).ravel(), 0.0)[self._nlp.shift_g]
        sel = steps(r.selection) if r.selection is not None else None
        dist = steps(r.distances) if r.distances is not None else None
        return _Warm(np.append(r.x, 0.0)[self._nlp.shift_x], lam_x, lam_g, ScreenStart(dist, sel))

    def _tips(self, r: HorizonCall, configs: np.ndarray) -> np.ndarray:
        """Tip positions (N, 3) mm of a solve's configurations (NaN when they are not finite)."""
        if not r.finite:
            return np.full((self.N, 3), np.nan)
        if self.linear is not None:
            return self.linear.rows(configs)  # the full model's; kept for the next (shifted) start: `rows`
        if "tips" in r.sol:
            return r.sol["tips"].reshape(self.N, 3)  # computed by the compiled KKT check
        return self.model.tip_position(configs)

    def describe(self) -> dict[str, Any]:
        """Sizes of the NLP (for result files and benchmarks)."""
        return _sizes(self)


def _parameter_vector(
    rp: Replanner, x0: np.ndarray, reference: Any, obstacles: Any, x_prev: Any, tip_reference: Any
) -> np.ndarray:
    """The NLP's parameter vector from `solve`'s inputs; `InputError` for a wrong shape or NaN."""
    N, nx = rp.N, rp.nx
    Xr = np.asarray(reference, dtype=float).reshape(N, nx)
    xm1 = x0 if x_prev is None else np.asarray(x_prev, dtype=float).reshape(nx)
    Pr = rp.model.tip_position(Xr) if tip_reference is None else np.asarray(tip_reference, float).reshape(N, 3)
    Ob = np.asarray(obstacles, dtype=float)
    if Ob.size != N * rp.obstacle_width:
        raise InputError(
            f"obstacles: expected shape ({N}, {rp.obstacle_width}) from obstacles_from_scene "
            f"or obstacles_from_states, got {Ob.shape}"
        )
    Ob = Ob.reshape(N, rp.obstacle_width)
    p = np.concatenate([x0, xm1, Xr.ravel(), Pr.ravel(), Ob.ravel(), np.zeros(rp._n_linear)])
    if not np.isfinite(p).all():
        # one check of the whole vector; the slow search for the culprit only when there is one
        for name, arr in (("x0", x0), ("reference", Xr), ("x_prev", xm1), ("tip_reference", Pr), ("obstacles", Ob)):
            if not np.isfinite(arr).all():
                raise InputError(f"{name}: contains NaN or infinity")
    return p


def linearisation_bound(rp: Replanner) -> float | None:
    """The stated bound (mm) of the rod correction's first-order error over one step's reach of `rp`'s horizon
    (`crtraj.control.horizon._rod_body.reach_bound`, measured on first use); None without the linearisation."""
    if rp.linear is None:
        return None
    bound = getattr(rp, "_lin_bound", None)
    if bound is None:
        bound = rp._lin_bound = reach_bound(rp.linear, rp.step_limit)
    return bound


def _sizes(rp: Replanner) -> dict[str, Any]:
    """`Replanner.describe`: the sizes of its NLP."""
    o, nlp = rp.options, rp._nlp
    return {
        "solver": (o.solver if o.solver == "ipopt" else f"sqpmethod+{o.qpsol}")
        + (" (compiled C)" if rp.compiled else ""),
        "rescue": "ipopt" if rp.rescue is not None else None,
        "max_iter": o.max_iter,
        "max_calls": o.max_calls,
        "step_deadline_s": o.step_deadline,
        "variables": rp.nx * rp.N,
        "parameters": nlp.n_params,
        "constraints": len(nlp.lbg),
        "actuator_limits": None if rp.rate_limits is None else list(rp.rate_limits.names),
        "limit_fraction": o.limit_fraction,
        "obstacle_constraints": nlp.n_dist,
        "qp_obstacle_rows": (rp._K or o.points) * rp.max_obstacles * rp.N if nlp.n_dist else 0,
        "max_obstacles": rp.max_obstacles,
        "shapes": len(rp.shapes.terms.shapes),
        "shape_constraints": nlp.n_shape,
        "shape_keep_mm": rp.shapes.keep if nlp.n_shape else None,
        "inflate_mm": rp.inflate,
        "point_spacing_mm": rp.spacing,
        "rod_body": None if rp.linear is None else "first order about each call's start point",
        "linearisation_bound_mm": linearisation_bound(rp),
    }
