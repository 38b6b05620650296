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
from crtraj.core.interrupt import check as check_interrupt
from crtraj.model.cosserat._compiled import POLISH, CompiledShooting
from crtraj.model.cosserat._equations import march, rod_pieces
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

log = logging.getLogger(__name__)

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


class RodStatics:
    """What every rod-statics solver of one robot shares: the robot, its mechanics, the optional generated C
    (loaded through the build cache by `_load_compiled`), the warm start and the last Jacobian.

    compiled: solve with generated C when a C compiler is found; False, or no compiler: CasADi's Newton
    rootfinder in the interpreter (same root to the same tolerance). build_cache: where the libraries go
    (None: the default cache).
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
        self._compiled: Any = self._load_compiled(build_cache or BuildCache()) if compiled else None
        self._warm: np.ndarray | None = None
        self._jac: np.ndarray | None = None  # the compiled path's last Jacobian (chord Newton)
        self._newton: ca.Function | None = None  # the interpreted rootfinder, built on first use
        self._setup()

    def _setup(self) -> None:
        """State of one kind of statics beyond the shared one."""

    def _load_compiled(self, cache: BuildCache) -> Any:
        """The generated solver of this kind of statics (None: interpret)."""
        return None

    @property
    def compiled(self) -> bool:
        """True when solves run the generated C."""
        return self._compiled is not None

    @property
    def n_tendons(self) -> int:
        return 3 * self.robot.n_segments


class CosseratRod(RodStatics):
    """Tendon-tension statics of one robot: build once, then `solve` many times (warm-started).

    solve(tensions, load) -> RodSolution. Tensions (N) are ordered as the robot's cables (segment by
    segment, cable 1..3), the order of the actuation vector q.

    compiled: solve with generated C through the build cache (`crtraj.model.cosserat._compiled`; about
    0.5 ms a warm solve instead of 13 ms; the first use per robot compiles for some seconds) when a C
    compiler is found; False, or no compiler: CasADi's Newton rootfinder in the interpreter. Both find
    the same root to the same tolerance. build_cache: where the libraries go (None: the default cache).
    """

    def _setup(self) -> None:
        self._shooting: ca.Function | None = None
        self._history: list[tuple[np.ndarray, np.ndarray]] = []  # the last two (parameters, base wrench)
        robot = self.robot
        log.debug("cosserat rod of %s built: %d segments, %d steps each", robot.name, robot.n_segments, self.mech.steps)

    def _load_compiled(self, cache: BuildCache) -> CompiledShooting:
        return CompiledShooting.load(self.robot, self.mech, cache)

    @property
    def shooting(self) -> ca.Function:
        """The SX shooting function (`build_shooting`), built on first use."""
        if self._shooting is None:
            self._shooting = build_shooting(self.robot, self.mech)
        return self._shooting

    def solve(self, tensions: Any, load: RodLoad = NO_LOAD, *, warm: bool = True) -> RodSolution:
        """Shape of the rod under tendon tensions (N) and `load`; starts from the last converged solve
        when `warm` (and from the straight rod if that fails)."""
        tau = check_tensions(tensions, self.n_tendons)
        return self._solve(tau, load_vector(self.mech, load), warm, POLISH)

    def solve_path(self, tensions: Any, load: RodLoad = NO_LOAD, *, polish: float = POLISH) -> list[RodSolution]:
        """`solve` (warm) for each row of tensions (N, 3 n_segments) N in turn, checked once: a path of
        nearby configurations. polish (<= 1): as `CompiledShooting.chord_newton`'s; 1 stops each compiled
        solve as soon as its residual is within the tolerance (every shape still to the tolerance)."""
        tau = np.asarray(tensions, dtype=float)
        if tau.ndim != 2 or tau.shape[1] != self.n_tendons:
            raise InputError(f"tensions: expected shape (N, {self.n_tendons}), got {tau.shape}")
        check_tensions(tau.ravel(), tau.size)
        loads = load_vector(self.mech, load)
        return [self._solve(row, loads, True, polish) for row in tau]

    def _solve(self, tau: np.ndarray, loads: np.ndarray, warm: bool, polish: float) -> RodSolution:
        """`solve` on checked tensions and load vector."""
        check_interrupt()  # a safe point between rod solves (crtraj.core.interrupt)
        p = np.concatenate([tau, loads])
        use_warm = warm and self._warm is not None
        for start in ("warm", "straight") if use_warm else ("straight",):
            w0 = self._predict(p) if start == "warm" else straight_guess(self.robot, tau, loads)
            sol = self._attempt(w0, p, start == "warm", polish)
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

    def _attempt(self, w0: np.ndarray, p: np.ndarray, keep_jacobian: bool, polish: float = POLISH) -> RodSolution:
        """One Newton run from w0: compiled (reusing the last Jacobian when `keep_jacobian`) or interpreted."""
        tol = self.mech.tolerance
        if self._compiled is not None:
            jac0 = self._jac if keep_jacobian else None
            w, res, shape, self._jac, stats = self._compiled.chord_newton(w0, p, jac0, tol, self.mech.max_iter, polish)
            pts, R, turn = shape[:3]
            return solution_status(stats.as_dict(), w, pts, R, res, turn, tol)
        if self._newton is None:
            self._newton = ca.rootfinder("rod_statics", "newton", self.shooting, newton_options(self.mech))
        w, pts, R, res, turn, _paths = self._newton(w0, p)
        return solution_status(self._newton.stats(), np.asarray(w).ravel(), pts, R, res, turn, tol)
