"""Safety-constrained inverse kinematics from many seeded starts.

Finds configurations x whose tip is exactly on a target point and whose
whole body keeps the safety distance from every obstacle, in three stages:

1. Batch projection: every seed configuration takes damped-Newton steps onto
   tip(x) = target at once (one CasADi call per step for all seeds), each
   step the smallest body motion that removes the tip error, then back into
   the bending discs and z stroke. Projections that the validator finds
   safe are kept directly. This is where most goal configurations come from,
   in a few milliseconds.
2. Push-out: projections on the target that come too close to an obstacle
   move, all at once, along the tip constraint's null space up the gradient
   of their body clearance (finite differences of the batched clearance;
   each step asks for the missing clearance plus `PUSH_EXTRA` mm by the
   linear model, at most `PUSH_STEP` mm of body motion), then back onto the
   target by a few Newton steps. Most goal and start configurations the
   projection misses come from here, in 2-5 ms instead of IPOPT's 5-30 ms.
3. The safety-constrained NLP, solved with IPOPT from the remaining
   projections while fewer than the wanted number of safe configurations
   exist:

    minimise    |M (x - x_ref)|^2 / 1e4              (closest to the projection, body-motion units)
    subject to  tip(x) = target                        (3 equalities, mm)
                limits(x) within bounds                (bending discs, cable strokes, z stroke)
                tangent(x) . d >= cos(cone)            (a tip direction goal; inert without one)
                |p_i(x) - c_j|^2 >= (R_j + inflate)^2 + (h/2)^2   for every check point i, obstacle j

   The last line makes every *chord* between neighbouring check points (arc
   spacing h) clear R_j + inflate, which is what `MotionValidator` verifies,
   so the NLP's solutions pass the planner's checks (they are re-verified
   anyway). Obstacles, target and reference are parameters: the NLP is
   built once per (model, max obstacles), on first use, and re-solved.
   A scene's other shapes add ``d_k(p_i(x)) >= inflate`` per check point with d_k the shape's NLP distance
   (`crtraj.world.geometry.ShapeTerms`: a lower bound; their poses are parameters, the NLP is rebuilt only
   for another set of shapes).

A tip direction goal (`crtraj.planning.goal.TipGoal` with a direction, ``solve(direction=)``) replaces stage
1's projection by one onto the position and the cone together (`crtraj.planning.ik._direction`), and every
stage keeps only configurations whose tip tangent lies within the cone.

Seeds pull toward their own random configurations, so the kept solutions
spread over the robot's redundancy (3 tip equalities leave a 2-D family of
goal configurations for the 5-DOF robot).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.interrupt import check as check_interrupt
from crtraj.model.kinematics import Model
from crtraj.planning.goal import TipGoal
from crtraj.planning.ik._direction import DirectionProjection
from crtraj.planning.ik._rescue import IKRescue
from crtraj.planning.ik._run import IKRun
from crtraj.planning.ik._tips import TipJacobians
from crtraj.planning.validity import MotionValidator, ProjectionLimits, ProjectionSteps
from crtraj.world import packing
from crtraj.world.geometry import ShapeTerms

PUSH_EXTRA = 2.0  # mm of clearance a push-out step asks for beyond the required one (overshoot, so few steps)
PUSH_STEP = 40.0  # mm: largest body motion of one push-out step (the linear model's trust region)
PUSH_FD = 1e-3  # mm of body motion per finite-difference step of the clearance gradient
PUSH_NEWTON = 4  # Newton steps back onto the target after each push-out step
DIRECTION_ITERATIONS = 15  # Newton steps a direction goal's projection takes beyond the position's


def build_nlp(
    model: Model, validator: MotionValidator, M: int, terms: ShapeTerms, max_iter: int
) -> tuple[ca.Function, np.ndarray, np.ndarray]:
    """The safe IK's IPOPT NLP (module docstring, stage 3) for M sphere slots and the shapes of `terms`, with
    its constraint bounds (lbg, ubg)."""
    n = validator.check_points
    x = ca.SX.sym("x", model.robot.nx)
    goal = ca.SX.sym("goal", 3)
    obs = ca.SX.sym("obstacles", packing.WIDTH * M)
    xref = ca.SX.sym("x_ref", model.robot.nx)
    inflate = ca.SX.sym("inflate")
    Mm = ca.DM(validator.metric_matrix / 100.0)
    f = ca.sumsqr(Mm @ (x - xref))
    g = [model.tip(x) - goal, model.limits(x)]
    lbg = [np.zeros(3), model.limit_bounds()[0]]
    ubg = [np.zeros(3), model.limit_bounds()[1]]
    pts = model.backbone_function(n)(x)  # 3 x n
    if M:
        h = model.robot.total_length / (n - 1)
        cl = []
        for j in range(M):
            c, radius, act = packing.slot(obs, j)
            r = radius + inflate
            d2 = ca.sum1((pts - ca.repmat(c, 1, n)) ** 2)
            # padding slots have active = 0: the row is 0 >= 0 and inert
            cl.append((act * ((d2 - (h / 2.0) ** 2) / (r * r) - 1.0)).T)
        g.append(ca.vertcat(*cl))
        lbg.append(np.zeros(n * M))
        ubg.append(np.full(n * M, np.inf))
    shapes = terms.symbols()
    if terms.shapes:  # each check point keeps inflate from each shape (its lower bound over the window)
        rows = terms.distances(pts, shapes)
        g.append(ca.vertcat(*[(row - inflate).T for row in rows]))
        lbg.append(np.zeros(n * len(rows)))
        ubg.append(np.full(n * len(rows), np.inf))
    # a tip direction goal: tangent . direction >= cos(cone); inert (1 >= 0) for direction 0 and cos -1
    direction, cos_cone = ca.SX.sym("direction", 3), ca.SX.sym("cos_cone")
    g.append(ca.dot(model.tip_frame(x)[:3, 2], direction) - cos_cone)
    lbg.append(np.zeros(1))
    ubg.append(np.full(1, np.inf))
    params = ca.vertcat(goal, obs, xref, inflate, shapes, direction, cos_cone)
    nlp = {"x": x, "p": params, "f": f, "g": ca.vertcat(*g)}
    opts = {
        "ipopt.print_level": 0,
        "print_time": False,
        "ipopt.sb": "yes",
        "ipopt.max_iter": max_iter,
        "ipopt.tol": 1e-8,
        "ipopt.constr_viol_tol": 1e-7,
        "error_on_fail": False,
    }
    return ca.nlpsol("safe_ik", "ipopt", nlp, opts), np.concatenate(lbg), np.concatenate(ubg)


@dataclass(frozen=True)
class IKSolution:
    """Outcome of one start: configuration, IPOPT status and independent checks.

    `is_success()`: converged with the tip on the target, within limits and
    clear of the obstacles (`safe`).
    """

    x: np.ndarray
    solver_status: str  # IPOPT's return status
    converged: bool  # IPOPT converged and the tip is within tolerance
    tip_error: float  # mm
    clearance: float  # conservative body clearance (mm, minus D_sf) by MotionValidator
    within_limits: bool
    wall_time: float  # s

    @property
    def safe(self) -> bool:
        return self.converged and self.within_limits and self.clearance >= 0.0

    def is_success(self) -> bool:
        return self.safe


@dataclass(frozen=True)
class IKBatch:
    """All starts of one query and the safe, distinct solutions among them."""

    solutions: tuple[IKSolution, ...]
    safe: np.ndarray  # (G, nx) safe distinct configurations
    wall_time: float
    statuses: dict[str, int] = field(default_factory=dict)


class SafeIK:
    """Multi-start safe IK on one IPOPT NLP with obstacles as parameters.

    model: the robot model. validator: supplies the check points, the metric,
    the scene's safety distance and the final verification. max_obstacles: obstacle slots in the NLP
    (a scene may use fewer). margin: extra clearance (mm) the NLP keeps on top
    of the validator's, so solutions survive the validator's edge margins.
    push_rounds: rounds of the push-out stage (`push_out`; 0 skips it). rescue_starts: batched starts
    around a projection before the NLP is solved from it (`crtraj.planning.ik._rescue`; 0: none).
    compiled: run the projection's Newton loop in the validator's compiled kernel when it has one (each
    configuration stops once on target; False: the numpy loop, every configuration stepping until all are).
    """

    def __init__(
        self,
        model: Model,
        validator: MotionValidator,
        max_obstacles: int,
        *,
        margin: float | None = None,
        tip_tolerance: float = 1e-3,
        max_iter: int = 60,
        push_rounds: int = 12,
        rescue_starts: int = 0,
        compiled: bool = True,
    ) -> None:
        self.model = model
        self.validator = validator
        self.robot = model.robot
        self.max_obstacles = int(max_obstacles)
        self.margin = validator.resolution / 2.0 + 0.25 if margin is None else float(margin)
        self.tip_tolerance = float(tip_tolerance)
        self.max_iter = int(max_iter)
        self.push_rounds = int(push_rounds)
        # IPOPT solves (stage 3) since construction: a statistic (the benchmarks report how often it runs)
        self.nlp_solves = 0
        self.rescue = IKRescue(self, self.robot.nx, rescue_starts)
        self._solver: ca.Function | None = None
        self._lbg = self._ubg = np.zeros(0)
        # the scene's other shapes (boxes, meshes, ...) in the NLP, with their poses as parameters: the NLP
        # is rebuilt only when a query brings other shapes (`_shape_terms`)
        self._terms = ShapeTerms(())
        self._terms_key: tuple[int, ...] = ()
        self._box = self.robot.config_box()
        Mx = validator.metric_matrix
        self._W_inv = np.linalg.inv(Mx.T @ Mx)
        # finite-difference step per coordinate: PUSH_FD mm of body motion
        self._fd = PUSH_FD / np.linalg.norm(Mx, axis=0)
        self._damping = 1e-3
        self._step = 150.0  # mm of tip error removed per Newton step at most
        self.compiled = bool(compiled)
        self._tips = TipJacobians(model, validator, self.compiled)
        self._limits = ProjectionLimits.of(self.robot)
        self._steps = ProjectionSteps(np.ascontiguousarray(self._W_inv), self._damping, self._step, self.tip_tolerance)
        self._direction: DirectionProjection | None = None

    @property
    def direction(self) -> DirectionProjection:
        """The projection onto a tip position and direction cone (built on first use)."""
        if self._direction is None:
            self._direction = DirectionProjection(
                self.model, self._W_inv, self._damping, self._step, self.validator.project_limits
            )
        return self._direction

    @property
    def solver(self) -> ca.Function:
        """The IPOPT NLP (built on first use, then reused for every solve)."""
        if self._solver is None:
            self._solver = self._build()
        return self._solver

    def _build(self) -> ca.Function:
        solver, self._lbg, self._ubg = build_nlp(
            self.model, self.validator, self.max_obstacles, self._terms, self.max_iter
        )
        return solver

    def project(self, target: np.ndarray, seeds: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
        """Batch damped-Newton projection of every seed onto tip(x) = target, ignoring obstacles.

        Each step is the smallest body motion (metric M) that removes the tip
        error (at most `step` mm of it), then the configuration is projected
        back into the bending discs and z stroke. All seeds move at once:
        one CasADi call per iteration evaluates every tip and Jacobian.
        Returns (configurations (S, nx), tip errors (S,) mm). With `compiled` and a compiled kernel the
        loop runs in C (`ValidityKernel.project`), each configuration stopping once its tip is on target.
        """
        kernel = self.validator.state.kernel if self.compiled else None
        if kernel is not None:
            return kernel.project(np.atleast_2d(seeds), target, iterations, self._limits, self._steps)
        X = np.atleast_2d(np.asarray(seeds, dtype=float)).copy()
        S = X.shape[0]
        err = np.full(S, np.inf)
        for _ in range(iterations + 1):
            P, J = self._tips.tip_jacobian(X)
            e = target - P
            err = np.linalg.norm(e, axis=1)
            if _ == iterations or np.all(err < self.tip_tolerance):
                break
            e *= np.minimum(1.0, self._step / np.maximum(err, 1e-300))[:, None]
            X = self.validator.project_limits(X + self._tip_move(J, e))
        return X, err

    def _tip_move(self, J: np.ndarray, r: np.ndarray) -> np.ndarray:
        """The smallest body motions dx (S, nx) (metric W = M^T M, damped) with J dx = r: tip Jacobians J
        (S, 3, nx), tip changes r (S, 3) mm. dx = W^-1 J^T (J W^-1 J^T + damping I)^-1 r."""
        JW = J @ self._W_inv
        A = JW @ np.transpose(J, (0, 2, 1)) + self._damping * np.eye(3)
        return np.einsum("nij,ni->nj", JW, np.linalg.solve(A, r[..., None])[..., 0])

    def push_out(
        self,
        target: np.ndarray,
        X: np.ndarray,
        *,
        required: float,
        rounds: int,
        validator: MotionValidator,
        t_check: tuple[float, float],
        tol: float,
        enough: int,
        must: int = 0,
        deadline: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Move on-target configurations X (S, nx) whose clearance (validator, mm) is below `required` until
        they clear it, keeping the tip on `target` (mm).

        Each round, every configuration still short steps along the null space
        of its tip Jacobian (metric M, the smallest body motion for a given
        clearance gain) up the forward-difference gradient of the validator's
        clearance over `t_check`, asking the linear model for the missing
        clearance plus PUSH_EXTRA mm (at most PUSH_STEP mm of body motion),
        back into the limits and onto the target (PUSH_NEWTON Newton steps).
        A configuration that loses the target (tip error > tol mm) drops out
        with clearance -inf. Stops after `rounds` rounds, when none is short,
        or once `enough` of them clear `required` and none of the first `must`
        is still short, or once `time.perf_counter()` passes `deadline`.
        Returns (X, clearances), both new arrays.
        """
        # Clearances enter the arithmetic only rounded to 1e-9 mm: the compiled and the interpreted
        # clearance differ by ~1e-14 mm, and rounding keeps their plans identical bit for bit.
        X = np.array(X, dtype=float)
        clear = np.round(validator.clearance(X, t_check[0], t_check[1]), 9)  # the finite differences' base
        short = np.flatnonzero(clear < required)
        for _ in range(rounds):
            if not len(short) or (np.count_nonzero(clear >= required) >= enough and short[0] >= must):
                break
            if deadline is not None and time.perf_counter() > deadline:
                break
            Xn, err = self._push_step(target, X[short], clear[short], required, validator, t_check)
            on = err <= tol
            cn = np.full(len(short), -np.inf)
            if on.any():
                cn[on] = np.round(validator.clearance(Xn[on], t_check[0], t_check[1]), 9)
            X[short], clear[short] = Xn, cn
            short = short[on & (cn < required)]
        return X, clear

    def _push_step(
        self,
        target: np.ndarray,
        Xa: np.ndarray,
        ca_: np.ndarray,
        required: float,
        validator: MotionValidator,
        t_check: tuple[float, float],
    ) -> tuple[np.ndarray, np.ndarray]:
        """One push-out step of configurations Xa (K, nx) with clearances ca_ (K,) mm (`push_out`):
        (the new configurations, their tip errors (mm))."""
        nx = Xa.shape[1]
        steps = np.diag(self._fd)
        probe = (Xa[:, None, :] + steps[None]).reshape(-1, nx)
        cp = np.round(validator.clearance(probe, t_check[0], t_check[1]), 9).reshape(len(Xa), nx)
        grad = (cp - ca_[:, None]) / self._fd
        # ascent direction in the null space of the tip Jacobian, metric W = M^T M: the steepest
        # ascent W^-1 g minus the smallest motion that undoes its tip change
        J = self._tips.push_jacobian(Xa)
        Wg = grad @ self._W_inv
        d = Wg - self._tip_move(J, np.einsum("nij,nj->ni", J, Wg))
        gain = np.einsum("ni,ni->n", grad, d)  # predicted clearance gain (mm) per unit step
        move = validator.motion_bound(d)
        alpha = np.minimum((required + PUSH_EXTRA - ca_) / np.maximum(gain, 1e-12), PUSH_STEP / np.maximum(move, 1e-12))
        return self.project(target, validator.project_limits(Xa + alpha[:, None] * d), PUSH_NEWTON)

    def tips(self, v: MotionValidator, X: np.ndarray) -> np.ndarray:
        """Tip positions (N, 3) mm of X (N, nx): with `compiled`, the validator's (its kernel's), else the model's."""
        return self._tips.tips(v, X)

    def solve(
        self,
        target: np.ndarray,
        scene_pack: np.ndarray | Callable[[], np.ndarray],
        seeds: np.ndarray,
        *,
        t_check: tuple[float, float] = (0.0, 0.0),
        want: int | None = None,
        newton_iterations: int = 15,
        dedup: float = 5.0,
        deadline: float | None = None,
        validator: MotionValidator | None = None,
        tip_tolerance: float | None = None,
        max_nlp: int | None = None,
        always: tuple[int, ...] = (),
        push_rounds: int | None = None,
        direction: TipGoal | None = None,
    ) -> IKBatch:
        """Safe configurations with the tip on `target` (mm), from seed configurations (S, nx).

        Stage 1 projects every seed onto the tip constraint at once
        (`project`) and keeps the projections that the validator finds safe
        with the NLP's margin. Stage 2, while fewer than `want` distinct safe
        configurations exist (or an `always` seed is not safe), pushes the
        on-target projections out of the obstacles (`push_out`). Stage 3, while
        still fewer exist, solves the safety-constrained NLP with IPOPT from
        the remaining configurations (most promising first: highest clearance,
        then smallest tip error). scene_pack: `Scene.pack` / `Scene.pack_over`
        output for the NLP's obstacles, or a function that returns it (called only when an NLP is solved, which
        is rare); t_check: the time window (s) the
        validator re-verifies every solution over. dedup: solutions closer
        than this body motion (mm) to a kept one are dropped. deadline: a
        `time.perf_counter()` value after which no further NLP is started.
        validator: the scene to check against (default: the one given at construction;
        it must share the robot, check points and resolution). tip_tolerance:
        largest accepted tip error (mm; default the one given at construction).
        max_nlp: at most this many NLP solves (default: one per remaining seed).
        always: seed indices whose projection, if not safe, is pushed out
        and then gets an NLP solve first, even when enough configurations exist (e.g. the start
        configuration as a seed: the safe goal configuration nearest to it).
        push_rounds: rounds of the push-out stage (default the one given at construction; 0 skips it).
        direction: a goal whose direction cone the tip tangent must keep (its position must be `target`; a
        goal without a direction, or None, asks for the position only).
        """
        t_start = time.perf_counter()
        v = self.validator if validator is None else validator
        tol = self.tip_tolerance if tip_tolerance is None else float(tip_tolerance)
        seeds = np.atleast_2d(np.asarray(seeds, dtype=float))
        want = len(seeds) if want is None else int(want)
        # the NLP keeps `margin`; allow for its tolerance
        goal = direction if direction is not None and direction.has_direction else None
        run = IKRun(np.asarray(target, dtype=float), seeds, v, t_check, tol, self.margin - 0.25, want, dedup)
        if goal is not None:
            run.aim(goal, self.direction.tangents)
        self._project_stage(run, newton_iterations)
        run.statuses["projection"] = int(run.good.sum())
        forced = [i for i in always if 0 <= i < len(seeds) and not run.good[i]]
        rounds = self.push_rounds if push_rounds is None else int(push_rounds)
        if rounds > 0 and (len(run.kept) < want or forced):
            self._push_stage(run, forced, rounds, deadline)
        self._nlp_stage(run, [i for i in forced if not run.good[i]], scene_pack, max_nlp, deadline)
        safe = np.array(run.kept) if run.kept else np.zeros((0, self.robot.nx))
        return IKBatch(tuple(run.sols), safe, time.perf_counter() - t_start, run.statuses)

    def _project_stage(self, run: IKRun, newton_iterations: int) -> None:
        """Stage 1: project in blocks of Newton steps, stopping as soon as enough safe configurations exist."""
        v, t_check, done_it = run.v, run.t_check, 0
        if run.goal is not None:  # the cone needs more steps than the position alone
            newton_iterations += DIRECTION_ITERATIONS
        while True:
            block = min(6 if done_it == 0 else 3, newton_iterations - done_it)
            if run.goal is None:
                run.X, run.err = self.project(run.target, run.X, block)
                aimed = np.ones(len(run.X), dtype=bool)
            else:
                run.X, run.err, angle = self.direction.project(run.goal, run.X, block, run.tol)
                aimed = angle <= run.goal.cone
            done_it += block
            new = ~run.checked & (run.err <= run.tol) & aimed
            if new.any():
                idx = np.flatnonzero(new)
                run.clear[idx] = v.clearance(run.X[idx], t_check[0], t_check[1])
                ok = v.within_limits(run.X[idx]) & (run.clear[idx] >= run.required)
                run.good[idx] = ok
                run.checked[idx] = True
                X, e, c = run.X, run.err, run.clear
                sols = [IKSolution(X[i], "projection", True, float(e[i]), float(c[i]), True, 0.0) for i in idx[ok]]
                run.add_all(sols)
            if len(run.kept) >= run.want or done_it >= newton_iterations:
                break

    def _push_stage(self, run: IKRun, forced: list[int], rounds: int, deadline: float | None) -> None:
        """Stage 2: push out the on-target projections that came too close: the forced ones first, then
        (while configurations are missing) the others, most promising (highest clearance) first."""
        X, clear, err, good = run.X, run.clear, run.err, run.good
        near = run.checked & ~good & (err <= run.tol)
        is_forced = np.zeros(len(X), dtype=bool)
        is_forced[forced] = True
        others = np.flatnonzero(near & ~is_forced) if len(run.kept) < run.want else np.zeros(0, dtype=int)
        others = others[np.argsort(-clear[others], kind="stable")]
        front = [i for i in forced if near[i]]
        cand = np.concatenate([front, others]).astype(int)
        if not len(cand):
            return
        X[cand], clear[cand] = self.push_out(
            run.target,
            X[cand],
            required=run.required,
            rounds=rounds,
            validator=run.v,
            t_check=run.t_check,
            tol=run.tol,
            enough=max(run.want - len(run.kept), 0),
            must=len(front),
            deadline=deadline,
        )
        err[cand] = np.linalg.norm(self.tips(run.v, X[cand]) - run.target, axis=1)
        ok = (clear[cand] >= run.required) & (err[cand] <= run.tol) & run.v.within_limits(X[cand])
        ok &= run.in_cone(X[cand])
        good[cand] = ok
        for i in cand[ok]:
            run.add(IKSolution(X[i], "push-out", True, float(err[i]), float(clear[i]), True, 0.0))
        run.statuses["push-out"] = int(ok.sum())

    def _nlp_stage(
        self,
        run: IKRun,
        forced: list[int],
        scene_pack: np.ndarray | Callable[[], np.ndarray],
        max_nlp: int | None,
        deadline: float | None,
    ) -> None:
        """Stage 3: the safety-constrained NLP from the remaining configurations, the forced ones first,
        then the converged ones by clearance, then by tip error; until enough exist or time runs out."""
        if (not forced and len(run.kept) >= run.want) or max_nlp == 0:
            return  # no solve would start: the loop below would stop at once
        if callable(scene_pack):
            scene_pack = scene_pack()
        X, clear, err = run.X, run.clear, run.err
        converged = err <= run.tol
        rest = np.flatnonzero(~run.good)
        order = rest[np.lexsort((err[rest], -np.where(converged[rest], clear[rest], -np.inf)))]
        order = np.concatenate([forced, [i for i in order if i not in forced]]).astype(int)
        inflate = run.v.inflate + self.margin
        shape_values = self._shape_terms(run.v.scene, run.t_check)
        if max_nlp is not None:
            order = order[: max(0, int(max_nlp))]
        for i in order:
            if i not in forced and len(run.kept) >= run.want:
                break
            if deadline is not None and time.perf_counter() > deadline:
                break
            rescued = self.rescue.solve(run, i, deadline)
            if rescued is not None:
                run.add(IKSolution(rescued[0], "rescue", True, rescued[1], rescued[2], True, 0.0))
                run.statuses["rescue"] = run.statuses.get("rescue", 0) + 1
                continue
            # start from the projection, stay close to the seed itself
            p = np.concatenate([run.target, scene_pack, run.seeds[i], [inflate], shape_values, run.cone_parameters()])
            sol = self._nlp_solve(run, X[i], p)
            run.sols.append(sol)
            if sol.safe and sol.clearance >= run.required:
                run.keep(sol.x)

    def _shape_terms(self, scene: Any, t_check: tuple[float, float]) -> np.ndarray:
        """The NLP's shape parameters for `scene` over t_check (s); the NLP is rebuilt when the scene's shapes
        are not the ones it was built for."""
        shapes = tuple(getattr(scene, "shapes", ()))
        key = tuple(id(ms) for ms in shapes)
        if key != self._terms_key:
            self._terms, self._terms_key, self._solver = ShapeTerms(shapes), key, None
        origin = scene.time_origin
        return self._terms.values(t_check[0] + origin, t_check[1] + origin)

    def _nlp_solve(self, run: IKRun, x0: np.ndarray, p: np.ndarray) -> IKSolution:
        """One NLP solve from x0 with parameters p, checked (tip error, limits, clearance over t_check)."""
        v, t_check = run.v, run.t_check
        t1 = time.perf_counter()
        self.nlp_solves += 1
        r = self.solver(x0=x0, p=p, lbx=self._box[0], ubx=self._box[1], lbg=self._lbg, ubg=self._ubg)
        check_interrupt()  # CasADi turns a Ctrl-C into a stopped solve: stop here (crtraj.core.interrupt)
        st = self.solver.stats()
        # IPOPT meets the limits to its tolerance (~1e-8); put the result exactly inside
        xs = self.validator.project_limits(np.asarray(r["x"], dtype=float).reshape(1, -1))[0]
        status = str(st.get("return_status", "unknown"))
        run.statuses[status] = run.statuses.get(status, 0) + 1
        ok = bool(st.get("success", False)) and bool(np.all(np.isfinite(xs)))
        tip_err = float(np.linalg.norm(self.model.tip_position(xs) - run.target)) if ok else np.inf
        ok = ok and tip_err <= run.tol and bool(run.in_cone(xs[None])[0])
        ins = bool(v.within_limits(xs[None])[0]) if ok else False
        c = float(v.clearance(xs[None], t_check[0], t_check[1])[0]) if ok else -np.inf
        return IKSolution(xs, status, ok, tip_err, c, ins, time.perf_counter() - t1)
