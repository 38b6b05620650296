"""Cosserat-rod statics of a multi-segment tendon-driven robot, solved by shooting in CasADi.

The model of Rucker and Webster ("Statics and dynamics of continuum robots with general tendon
routing and external loading", IEEE T-RO 27(6), 2011), for straight tendon routing: tendon i sits at
the constant body-frame position ``r_i = r (cos a_i, sin a_i, 0)`` (the robot's cable radius and
angles, three per segment 120 degrees apart) and runs from the base to the end disc of its segment.

State along the arc length s (mm) of the undeformed backbone: position p (mm), rotation R, and the
body-frame strains v (shear/extension, 1) and u (curvature/torsion, rad/mm). With the constitutive
laws ``n = R K_se (v - e3)``, ``m = R K_bt u`` (a straight, unstressed reference rod):

    p' = R v,  R' = R hat(u),
    [K_se + A, G; B, K_bt + H] [v'; u'] = [d; c]

where A, B, G, H, a, b sum the distributed loads of the tendons that pass through s (their tension
pressing on the discs where the tendon path curves), ``c = -u x K_bt u - v x K_se (v - e3) - b`` and
``d = -u x K_se (v - e3) - R^T f_e - a`` with the distributed external force f_e (gravity, N/mm).
At the end disc of each segment its tendons end: the internal force jumps by their tension along
their tangent, the moment by that force's moment about the backbone. At the tip the internal
force and moment equal the tip load plus the last segment's tendon terminations.

The unknown base force n(0) (N) and moment m(0) (N mm) are found by Newton's method (CasADi
``rootfinder``) on the tip residual; the rod ODE is integrated by RK4 over a fixed number of steps
per segment. Everything is built once per robot; tensions, the distributed force and the tip load
are parameters, and each solve starts from the previous solution.

Units: mm, N, rad; moduli N/mm^2 (MPa). Frames: the robot's base frame (z along the base axis), the
base at the origin (add the base translation z yourself).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_MAGNITUDE, check_array
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

log = logging.getLogger(__name__)

_E3 = ca.DM([0.0, 0.0, 1.0])
# Largest tension (N) accepted: far above any cable's breaking load; beyond it is a unit slip.
MAX_TENSION = 1e5
# Largest angle (rad) the rod may turn through in one RK4 step: beyond it the step is too coarse for
# the shape to be trusted (a step of 0.2 rad errs by about (0.2)^4 / 120 = 1e-5 of its length), and
# the solve says so ("under_resolved": raise [robot.mechanics] steps) instead of returning it.
MAX_TURN = 0.2
# The warm start extrapolates along the last two solutions when the new parameter step points within
# about 25 degrees of the last one (cosine above this), by at most this many last steps.
PREDICT_ALIGNMENT = 0.9
PREDICT_MAX = 2.0


def _hat(w: Any) -> Any:
    """Skew matrix of a 3-vector: hat(w) x = w x x."""
    return ca.vertcat(
        ca.horzcat(0, -w[2], w[1]),
        ca.horzcat(w[2], 0, -w[0]),
        ca.horzcat(-w[1], w[0], 0),
    )


@dataclass(frozen=True)
class RodLoad:
    """External loads in the base frame. tip_force (N), tip_moment (N mm), distributed: force per
    length along the backbone (N/mm); None means the robot's weight (`Mechanics.weight_per_length`)."""

    tip_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip_moment: tuple[float, float, float] = (0.0, 0.0, 0.0)
    distributed: tuple[float, float, float] | None = None


NO_LOAD = RodLoad(distributed=(0.0, 0.0, 0.0))


@dataclass(frozen=True)
class RodSolution:
    """One solve. status: "converged" or why not ("diverged", "not_finite", "under_resolved"). points: backbone
    positions (mm, base frame, base at the origin), (n_segments * steps + 1, 3), NaN unless converged.
    tip_rotation: R at the tip (3, 3). base_force (N), base_moment (N mm): internal force and moment
    at the base. residual: largest tip-residual entry (N). iterations: Newton iterations."""

    status: str
    points: np.ndarray
    tip_rotation: np.ndarray
    base_force: np.ndarray
    base_moment: np.ndarray
    residual: float
    iterations: int

    def is_success(self) -> bool:
        return self.status == "converged"

    @property
    def tip(self) -> np.ndarray:
        """Tip position (mm)."""
        return self.points[-1]


class _Rod:
    """The symbolic pieces of one robot's rod: stiffness, tendon positions, ODE, jumps, residual."""

    def __init__(self, robot: Robot, mech: Mechanics) -> None:
        self.robot, self.mech = robot, mech
        self.kse = ca.DM(mech.shear_extension())
        self.kbt = ca.DM(mech.bending_torsion())
        rc = robot.cable_radius
        self.r = [
            ca.DM([rc * np.cos(a), rc * np.sin(a), 0.0]) for k in range(robot.n_segments) for a in robot.cable_angles(k)
        ]

    def tangent(self, v: Any, u: Any, i: int) -> Any:
        """Unit tangent of tendon i in the body frame (p_i' / |p_i'|, R^T applied)."""
        pb = v + ca.cross(u, self.r[i])
        return pb / ca.norm_2(pb)

    def rhs(self, y: Any, tau: Any, tendons: range, fe: Any) -> Any:
        """dy/ds of the state y = (p, vec R, v, u, tendon path lengths) with the tendons `tendons`
        passing through (the others' path lengths stay put)."""
        R = ca.reshape(y[3:12], 3, 3)
        v, u = y[12:15], y[15:18]
        A = ca.SX.zeros(3, 3)
        B = ca.SX.zeros(3, 3)
        G = ca.SX.zeros(3, 3)
        H = ca.SX.zeros(3, 3)
        a = ca.SX.zeros(3)
        b = ca.SX.zeros(3)
        rates = ca.SX.zeros(len(self.r))
        for i in tendons:
            ri = _hat(self.r[i])
            pb = v + ca.cross(u, self.r[i])
            nrm = ca.norm_2(pb)
            rates[i] = nrm  # |p_i'|: the tendon's path length grows at this rate
            t = pb / nrm
            # -tau hat(pb)^2 / |pb|^3 = (tau / |pb|) (I - t t^T): the tension's projector off the tangent
            Ai = (tau[i] / nrm) * (ca.SX.eye(3) - t @ t.T)
            Bi = ri @ Ai
            A += Ai
            B += Bi
            G -= Ai @ ri
            H -= Bi @ ri
            ai = Ai @ ca.cross(u, pb)
            a += ai
            b += ri @ ai
        strain = self.kse @ (v - _E3)
        c = -ca.cross(u, self.kbt @ u) - ca.cross(v, strain) - b
        d = -ca.cross(u, strain) - R.T @ fe - a
        lhs = ca.vertcat(ca.horzcat(self.kse + A, G), ca.horzcat(B, self.kbt + H))
        dvu = _solve_dominant(lhs, ca.vertcat(d, c))
        return ca.vertcat(R @ v, ca.reshape(R @ _hat(u), 9, 1), dvu, rates)

    def terminations(self, y: Any, tau: Any, tendons: range) -> tuple[Any, Any]:
        """Force (N) and moment (N mm, about the backbone) that ending tendons apply to the disc."""
        R = ca.reshape(y[3:12], 3, 3)
        v, u = y[12:15], y[15:18]
        F = ca.SX.zeros(3)
        M = ca.SX.zeros(3)
        for i in tendons:
            Fi = -tau[i] * (R @ self.tangent(v, u, i))
            F += Fi
            M += ca.cross(R @ self.r[i], Fi)
        return F, M

    def internal(self, y: Any) -> tuple[Any, Any]:
        """Internal force n (N) and moment m (N mm) of the backbone, base frame."""
        R = ca.reshape(y[3:12], 3, 3)
        return R @ self.kse @ (y[12:15] - _E3), R @ self.kbt @ y[15:18]

    def strains(self, R: Any, n: Any, m: Any) -> tuple[Any, Any]:
        """Body strains (v, u) of internal force n and moment m (base frame) at rotation R."""
        return ca.solve(self.kse, R.T @ n) + _E3, ca.solve(self.kbt, R.T @ m)


def _solve_dominant(M: Any, rhs: Any) -> Any:
    """x with M x = rhs by Gaussian elimination without pivoting.

    M = [K_se + A, G; B, K_bt + H] is strongly diagonally dominant for any tension a backbone can bear
    (the tendon terms scale with tension, the diagonal with EA, GA, EI), so no pivoting is needed; this
    needs a few times fewer symbolic operations than a QR solve, which the Jacobian multiplies.
    """
    n = M.shape[0]
    a = [[M[i, j] for j in range(n)] for i in range(n)]
    b = [rhs[i] for i in range(n)]
    for k in range(n):
        for i in range(k + 1, n):
            f = a[i][k] / a[k][k]
            for j in range(k + 1, n):
                a[i][j] = a[i][j] - f * a[k][j]
            b[i] = b[i] - f * b[k]
    x: list[Any] = [None] * n
    for i in reversed(range(n)):
        acc = b[i]
        for j in range(i + 1, n):
            acc = acc - a[i][j] * x[j]
        x[i] = acc / a[i][i]
    return ca.vertcat(*x)


def _rk4(f: Any, y: Any, h: float) -> Any:
    """One classical Runge-Kutta step of dy/ds = f(y)."""
    k1 = f(y)
    k2 = f(y + 0.5 * h * k1)
    k3 = f(y + 0.5 * h * k2)
    k4 = f(y + h * k3)
    return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


@dataclass(frozen=True)
class RodPieces:
    """The rod's shooting as small CasADi Functions of the state y = (p, vec R, v, u, tendon paths) and
    the parameters p (see `build_shooting`): `init` w -> y(0); `steps[k]` one RK4 step of segment k,
    (y, p) -> (y after the step, the angle (rad) the rod turns through in it); `jumps[k]` the disc at
    the end of segment k < last, (y, p) -> y; `tip` (y, p) -> r, the tip residual. Chaining them gives
    the shooting function; calling them with SX inlines them, with MX keeps the graph small."""

    init: ca.Function
    steps: tuple[ca.Function, ...]
    jumps: tuple[ca.Function, ...]
    tip: ca.Function
    n_steps: int


def rod_pieces(robot: Robot, mech: Mechanics) -> RodPieces:
    """The `RodPieces` of one robot and its mechanics (built once; SX inside)."""
    rod = _Rod(robot, mech)
    n_seg, nt = robot.n_segments, 3 * robot.n_segments
    y = ca.SX.sym("y", 18 + nt)
    p = ca.SX.sym("p", nt + 9)
    tau, fe, f_tip, m_tip = p[:nt], p[nt : nt + 3], p[nt + 3 : nt + 6], p[nt + 6 : nt + 9]
    w = ca.SX.sym("w", 6)
    v0, u0 = rod.strains(ca.SX.eye(3), w[:3], w[3:])
    y0 = ca.vertcat(ca.SX.zeros(3), ca.reshape(ca.SX.eye(3), 9, 1), v0, u0, ca.SX.zeros(nt))
    steps, jumps = [], []
    for k, seg in enumerate(robot.segments):
        f = ca.Function("rod_rhs", [y, p], [rod.rhs(y, tau, range(3 * k, nt), fe)])
        h = seg.length / mech.steps
        y_next = _rk4(lambda z, f=f: f(z, p), y, h)
        steps.append(ca.Function(f"rod_step{k}", [y, p], [y_next, h * ca.norm_2(y[15:18])]))
        F, M = rod.terminations(y, tau, range(3 * k, 3 * k + 3))
        n, m = rod.internal(y)
        if k < n_seg - 1:  # the disc passes the internal wrench on, less what its tendons take
            v, u = rod.strains(ca.reshape(y[3:12], 3, 3), n - F, m - M)
            jumps.append(ca.Function(f"rod_jump{k}", [y, p], [ca.vertcat(y[:12], v, u, y[18:])]))
        else:
            res = ca.vertcat(n - F - f_tip, (m - M - m_tip) / robot.total_length)
    tip = ca.Function("rod_tip", [y, p], [res])
    return RodPieces(ca.Function("rod_init", [w], [y0]), tuple(steps), tuple(jumps), tip, mech.steps)


def march(pieces: RodPieces, w: Any, p: Any) -> tuple[Any, Any, Any, Any]:
    """Integrate from the base wrench w to the tip: (residual r, points 3 x (n_segments steps + 1),
    tip state y, largest turn per step); symbolic in whatever type w and p are (SX inlines, MX calls)."""
    y = pieces.init(w)
    cols, turns = [y[:3]], []
    for k, step in enumerate(pieces.steps):
        for _ in range(pieces.n_steps):
            y, turn = step(y, p)
            turns.append(turn)
            cols.append(y[:3])
        if k < len(pieces.jumps):
            y = pieces.jumps[k](y, p)
    return pieces.tip(y, p), ca.horzcat(*cols), y, ca.mmax(ca.vertcat(*turns))


def build_shooting(robot: Robot, mech: Mechanics) -> ca.Function:
    """The shooting function (w, p) -> (r, points, R_tip, r) of the unknown base wrench
    w = (n(0) N, m(0) N mm) and the parameters p = (tensions (3 n_segments) N, distributed force (3)
    N/mm, tip force (3) N, tip moment (3) N mm). r (6,): tip force error (N) and tip moment error /
    total length (N), twice: the rootfinder solves the first and returns the rest at the solution.
    points: 3 x (n_segments steps + 1) mm; R_tip: 3 x 3; turn: the largest angle (rad) the rod
    turns through within one step (taken at the start of each step); paths (3 n_segments,): each
    tendon's path length (mm) from the base to its end disc in the deformed rod."""
    nt = 3 * robot.n_segments
    w = ca.SX.sym("w", 6)
    p = ca.SX.sym("p", nt + 9)
    res, points, y, turn = march(rod_pieces(robot, mech), w, p)
    outs = [res, points, ca.reshape(y[3:12], 3, 3), res, turn, y[18:]]
    names = ["r", "points", "R_tip", "residual", "turn", "paths"]
    return ca.Function("rod_shooting", [w, p], outs, ["w", "p"], names)


def load_vector(mech: Mechanics, load: RodLoad) -> np.ndarray:
    """(distributed force N/mm, tip force N, tip moment N mm) of `load`, checked: the last 9 parameters."""
    fe = mech.weight_per_length() if load.distributed is None else load.distributed
    parts = {"distributed": fe, "tip_force": load.tip_force, "tip_moment": load.tip_moment}
    vecs = [check_array(np.asarray(v, dtype=float), f"load.{k}", (3,), limit=MAX_MAGNITUDE) for k, v in parts.items()]
    return np.concatenate(vecs)


def check_tensions(tensions: Any, n: int) -> np.ndarray:
    """n finite tensions >= 0 (N), or a one-line `InputError` naming the first bad one."""
    t = check_array(np.asarray(tensions, dtype=float), "tensions", (n,), limit=MAX_TENSION)
    bad = np.flatnonzero(t < 0)
    if bad.size:
        raise InputError(f"tensions[{bad[0]}]: a tendon cannot push; must be >= 0 N, got {t[bad[0]]}")
    return t


def straight_guess(robot: Robot, tensions: np.ndarray, loads: np.ndarray) -> np.ndarray:
    """Base wrench (n(0) N, m(0) N mm) of the straight rod under the tensions and loads: a cold start."""
    L = robot.total_length
    fe, f_tip, m_tip = loads[:3], loads[3:6], loads[6:9]
    e3 = np.array([0.0, 0.0, 1.0])
    n0 = f_tip + L * fe - tensions.sum() * e3
    m0 = m_tip + np.cross(L * e3, f_tip) + np.cross(0.5 * L * L * e3, fe)
    rc = robot.cable_radius
    angles = np.concatenate([robot.cable_angles(k) for k in range(robot.n_segments)])
    for tau, a in zip(tensions, angles, strict=True):
        m0 = m0 - tau * np.cross([rc * np.cos(a), rc * np.sin(a), 0.0], e3)
    return np.concatenate([n0, m0])


def newton_options(mech: Mechanics) -> dict[str, Any]:
    """Options of the shooting rootfinders."""
    # trial steps of the line search may leave the rod's domain (NaN); the status says if it failed
    return {"abstol": mech.tolerance, "max_iter": mech.max_iter, "error_on_fail": False, "show_eval_warnings": False}


def solution_status(stats: dict, w: np.ndarray, pts: Any, R: Any, res: Any, turn: Any, tolerance: float) -> RodSolution:
    """The `RodSolution` of a rootfinder's output: converged, or why not, and then no shape."""
    pts, R, res = np.asarray(pts), np.asarray(R), np.asarray(res)
    iters = int(stats.get("iter_count", -1))
    err = float(np.max(np.abs(res))) if np.all(np.isfinite(res)) else float("inf")
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(pts))):
        status = "not_finite"
    elif err > 10.0 * tolerance or not stats.get("success", False):
        status = "diverged"
    elif float(turn) > MAX_TURN:
        status = "under_resolved"
    else:
        status = "converged"
    if status != "converged":  # never hand out a wrong shape
        pts = np.full_like(pts, np.nan)
    return RodSolution(status, pts.T.copy(), R, w[:3].copy(), w[3:6].copy(), err, iters)


class CosseratRod:
    """Tendon-tension statics of one robot: build once, then `solve` many times (warm-started).

    solve(tensions, load) -> RodSolution. Tensions (N) are ordered as the robot's cables (segment by
    segment, cable 1..3), the order of the actuation vector q.

    compiled: solve with generated C through the build cache (`crtraj.model.cosserat_compiled`; about
    0.5 ms a warm solve instead of 13 ms; the first use per robot compiles for some seconds) when a C
    compiler is found; False, or no compiler: CasADi's Newton rootfinder in the interpreter. Both find
    the same root to the same tolerance. build_cache: where the libraries go (None: the default cache).
    """

    def __init__(
        self,
        robot: Robot,
        mech: Mechanics | None = None,
        *,
        compiled: bool = True,
        build_cache: BuildCache | None = None,
    ) -> None:
        self.robot = robot
        self.mech = Mechanics.from_robot(robot) if mech is None else mech
        self._shooting: ca.Function | None = None
        self._newton: ca.Function | None = None
        self._compiled = None
        if compiled:
            from crtraj.model.cosserat_compiled import CompiledShooting  # it builds on this module

            self._compiled = CompiledShooting.load(robot, self.mech, build_cache or BuildCache())
        self._warm: np.ndarray | None = None
        self._history: list[tuple[np.ndarray, np.ndarray]] = []  # the last two (parameters, base wrench)
        self._jac: np.ndarray | None = None
        log.debug("cosserat rod of %s built: %d segments, %d steps each", robot.name, robot.n_segments, self.mech.steps)

    @property
    def compiled(self) -> bool:
        """True when solves run the generated C."""
        return self._compiled is not None

    @property
    def shooting(self) -> ca.Function:
        """The SX shooting function (`build_shooting`), built on first use."""
        if self._shooting is None:
            self._shooting = build_shooting(self.robot, self.mech)
        return self._shooting

    @property
    def n_tendons(self) -> int:
        return 3 * self.robot.n_segments

    def solve(self, tensions: Any, load: RodLoad = NO_LOAD, *, warm: bool = True) -> RodSolution:
        """Shape of the rod under tendon tensions (N) and `load`; starts from the last converged solve
        when `warm` (and from the straight rod if that fails)."""
        tau = check_tensions(tensions, self.n_tendons)
        loads = load_vector(self.mech, load)
        p = np.concatenate([tau, loads])
        use_warm = warm and self._warm is not None
        for start in ("warm", "straight") if use_warm else ("straight",):
            w0 = self._predict(p) if start == "warm" else straight_guess(self.robot, tau, loads)
            sol = self._attempt(w0, p, start == "warm")
            if sol.is_success():
                self._warm = np.concatenate([sol.base_force, sol.base_moment])
                self._history = [*self._history[-1:], (p, self._warm)]
                return sol
        log.info("cosserat solve failed (%s, residual %.3g N)", sol.status, sol.residual)
        return sol

    def _predict(self, p: np.ndarray) -> np.ndarray:
        """Warm start for parameters p: the last solution, moved along the last two solutions' secant by
        the share of the last parameter step that the new step repeats (a sequence of nearby solves, as
        along a path, then starts second-order close); the last solution when the steps do not line up."""
        assert self._warm is not None
        if len(self._history) < 2:
            return self._warm
        (p0, w0), (p1, w1) = self._history
        old, new = p1 - p0, p - p1
        nn, no = float(new @ new), float(old @ old)
        if no == 0.0 or nn == 0.0:
            return self._warm
        along = float(new @ old)
        if along <= PREDICT_ALIGNMENT * np.sqrt(nn * no):
            return self._warm
        return w1 + min(along / no, PREDICT_MAX) * (w1 - w0)

    def _attempt(self, w0: np.ndarray, p: np.ndarray, keep_jacobian: bool) -> RodSolution:
        """One Newton run from w0: compiled (reusing the last Jacobian when `keep_jacobian`) or interpreted."""
        tol = self.mech.tolerance
        if self._compiled is not None:
            jac0 = self._jac if keep_jacobian else None
            w, res, shape, self._jac, stats = self._compiled.chord_newton(w0, p, jac0, tol, self.mech.max_iter)
            pts, R, turn = shape[:3]
            return solution_status(stats.as_dict(), w, pts, R, res, turn, tol)
        if self._newton is None:
            self._newton = ca.rootfinder("rod_statics", "newton", self.shooting, newton_options(self.mech))
        w, pts, R, res, turn, _paths = self._newton(w0, p)
        return solution_status(self._newton.stats(), np.asarray(w).ravel(), pts, R, res, turn, tol)
