"""The body the rod takes as the planner's model: PCC plus a fitted correction (``[planner] model = "rod"``).

`crtraj.model.cosserat._surrogate.RodSurrogate` tabulates the rod's correction Delta = rod - PCC at the collision
points and interpolates it by a cubic B-spline. CasADi evaluates that spline only on MX graphs, while every
consumer of the `Model` (the checker and its generated C, the safe IK, the steer and horizon NLPs) builds SX
expressions. `RodModel` therefore carries the correction as a polynomial of total degree ``degree`` in the
normalised bending vectors w_k = u_bar_k / theta_max_k (2 n_segments variables, each in the unit disc),

    Delta(x) ~= mean + sum_r V_r sum_m c_mr w^e_m   (3 x P, mm; P collision points, the last the tip),

fitted by least squares to the spline at ``samples`` seeded random configurations within the limits. The 3 P
numbers of Delta move together (the rod's sag is one smooth shape along the arc), so the fit is made on the
``modes`` leading principal directions V_r of the samples (their SVD) and costs ``modes`` polynomials instead
of 3 P: on cdsr2 (30 numbers) 14 modes give the same held-out error as all 30, at less than half the
operations in every consumer. Each monomial is one product of a lower one and one variable. It is a plain SX
expression of x: exact Jacobians and Hessians, and it generates to C with the rest of a checker.

Between the collision points the correction is interpolated linearly along the arc (hat functions of the arc
length), so every body function of the Model (``backbone``, ``backbone_function(n)``, ``points``,
``segment_point_function``, ``tip``, ``jac_tip``) is the rod's body; the tip frame's rotation stays PCC's.

Its error. The fit, the spline and the interpolation along the arc all err; what counts is the body the planner
sees against the rod. After the fit, ``holdout`` seeded random configurations within the limits (not the fit's)
are solved fresh (`RodSampler`, the robot file's actuation mode, gravity) and compared with the model at every
integration node of the rod (``steps`` per segment, the nodes `crtraj verify --model cosserat` checks): the
largest distance (body) and the tip's are the model's error, and ``BOUND_FACTOR`` times the body's is its
stated bound, which the planner adds to D_sf (`planning_margin`).

The cache. The coefficients and the measured error are kept beside the surrogate's table, under a key of the
surrogate's digest (the robot file, its mechanics and the surrogate's options), these options and this
source's hash: a changed robot file is a new entry, never a stale one.

Units: mm, rad.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import default_root
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_json, read_json
from crtraj.model.cosserat._surrogate import (
    BOUND_FACTOR,
    RodSampler,
    RodSurrogate,
    SurrogateError,
    SurrogateOptions,
    sample_within_limits,
)
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

log = logging.getLogger(__name__)

# Layout of a cache entry (a change makes every old entry foreign).
FORMAT = 2
MAX_DEGREE = 14
MAX_MODES = 3 * 200
MAX_SAMPLES = 200_000
MAX_HOLDOUT = 100_000
# Largest cache entry read (bytes): a degree-14 fit of 4 variables at 21 points is about 2 MB of JSON.
_MAX_ENTRY_BYTES = 64 * 1024 * 1024


@dataclass(frozen=True)
class RodModelOptions:
    """How the rod's body model is made. degree: total degree of the correction's polynomials. modes: how many
    principal directions of Delta are fitted (at most 3 x collision points; all of them: one polynomial per
    coordinate). samples: random
    configurations the polynomial is fitted on (the spline's values there). holdout: fresh rod solves the
    error is measured on. seed: of both draws. surrogate: the tabulated surrogate's options."""

    degree: int = 10
    modes: int = 14
    samples: int = 20_000
    holdout: int = 200
    seed: int = 0
    surrogate: SurrogateOptions = field(default_factory=SurrogateOptions)

    def __post_init__(self) -> None:
        if not 1 <= int(self.degree) <= MAX_DEGREE:
            raise InputError(f"rod model degree: must be in [1, {MAX_DEGREE}], got {self.degree}")
        if not 1 <= int(self.modes) <= MAX_MODES:
            raise InputError(f"rod model modes: must be in [1, {MAX_MODES}], got {self.modes}")
        if not 1 <= int(self.samples) <= MAX_SAMPLES:
            raise InputError(f"rod model samples: must be in [1, {MAX_SAMPLES}], got {self.samples}")
        if not 1 <= int(self.holdout) <= MAX_HOLDOUT:
            raise InputError(f"rod model holdout: must be in [1, {MAX_HOLDOUT}], got {self.holdout}")

    def to_dict(self) -> dict[str, Any]:
        s = self.surrogate
        sur = {"grid": int(s.grid), "holdout": int(s.holdout), "seed": int(s.seed), "pretension": s.pretension}
        return {"degree": int(self.degree), "modes": int(self.modes), "samples": int(self.samples)} | {
            "holdout": int(self.holdout),
            "seed": int(self.seed),
            "surrogate": sur,
        }


def exponents(n_vars: int, degree: int) -> np.ndarray:
    """Every exponent vector (M, n_vars) of total degree <= `degree`, in a fixed order."""
    return np.array([e for e in itertools.product(range(degree + 1), repeat=n_vars) if sum(e) <= degree], dtype=int)


def monomials(w: np.ndarray, exps: np.ndarray) -> np.ndarray:
    """The monomials w^e (N, M) of points w (N, n_vars)."""
    return np.prod(w[:, None, :] ** exps[None, :, :], axis=2)


def power_products(w: np.ndarray, exps: np.ndarray) -> np.ndarray:
    """The monomials w^e (N, M) of points w (N, n_vars) as `monomials`, by table look-ups instead of powers: the
    powers of each variable by repeated products, then per pair of variables the table of their products, and
    each monomial the product of its pairs' entries (a fifth of `monomials`' time on 10 points of 1001)."""
    w = np.atleast_2d(np.asarray(w, dtype=float))
    exps = np.asarray(exps, dtype=int)
    n, nv = w.shape
    D = int(exps.max()) + 1 if exps.size else 1
    pw = np.empty((n, nv, D))
    pw[:, :, 0] = 1.0
    pw[:, :, 1:] = w[:, :, None]
    np.cumprod(pw, axis=2, out=pw)  # w_j^k
    phi = np.ones((n, len(exps)))
    for j in range(0, nv, 2):
        if j + 1 < nv:
            table, idx = (pw[:, j, :, None] * pw[:, j + 1, None, :]).reshape(n, -1), exps[:, j] * D + exps[:, j + 1]
        else:
            table, idx = pw[:, j], exps[:, j]
        phi *= np.take(table, idx, axis=1)
    return phi


class Correction:
    """Delta(w) (3 x P, mm) as polynomials in the normalised bending vectors w (the module docstring).

    exps: (M, 2 n_segments) exponents; coef: (M, R) coefficients of the R modes; basis: (R, 3 P) the modes,
    column 3 j + i the coordinate i of point j (None: the identity, R = 3 P); mean: (3 P,) mm (None: zeros);
    arcs: (P,) the points' arc lengths (mm from the base)."""

    def __init__(
        self,
        robot: Robot,
        exps: np.ndarray,
        coef: np.ndarray,
        arcs: np.ndarray,
        basis: np.ndarray | None = None,
        mean: np.ndarray | None = None,
    ) -> None:
        self.robot = robot
        self.exps = np.asarray(exps, dtype=int)
        self.coef = np.asarray(coef, dtype=float)
        self.arcs = np.asarray(arcs, dtype=float)
        width = 3 * len(self.arcs)
        self.basis = np.eye(width) if basis is None else np.asarray(basis, dtype=float)
        self.mean = np.zeros(width) if mean is None else np.asarray(mean, dtype=float)
        self.scale = np.repeat([1.0 / s.theta_max for s in robot.segments], 2)
        R = self.basis.shape[0]
        if self.basis.shape != (R, width) or self.mean.shape != (width,) or self.coef.shape != (len(self.exps), R):
            raise ValueError(
                f"coefficients {self.coef.shape}, modes {self.basis.shape}, mean {self.mean.shape}: expected "
                f"({len(self.exps)}, R), (R, {width}), ({width},)"
            )

    @classmethod
    def fit(cls, sur: RodSurrogate, degree: int, modes: int, samples: int, rng: np.random.Generator) -> Correction:
        """Least-squares fit of `modes` principal directions to the spline `sur` at `samples` random
        configurations within the limits."""
        r = sur.robot
        xs = sample_within_limits(r, samples, rng)
        delta = np.asarray(sur.function.map(len(xs))(xs.T))  # (3, P * N), configuration-major columns
        y = delta.T.reshape(len(xs), -1)  # (N, 3 P): point j's coordinates at columns 3 j .. 3 j + 2
        mean = y.mean(axis=0)
        basis = np.linalg.svd(y - mean, full_matrices=False)[2][: int(modes)]  # (R, 3 P), orthonormal rows
        exps = exponents(2 * r.n_segments, degree)
        scale = np.repeat([1.0 / s.theta_max for s in r.segments], 2)
        phi = monomials(r.bending(xs).reshape(len(xs), -1) * scale, exps)
        coef, *_ = np.linalg.lstsq(phi, (y - mean) @ basis.T, rcond=None)
        return cls(r, exps, coef, Model(r, sur.n_points).arc_positions(sur.n_points), basis, mean)

    def terms(self, ub: Any) -> Any:
        """The monomials (M,) as an SX/MX expression of the effective bending vectors ub (2 n_segments,) rad,
        each one product of a lower monomial and one variable."""
        n = len(self.scale)
        w = [ub[i] * float(self.scale[i]) for i in range(n)]
        mono: dict[tuple[int, ...], Any] = {(0,) * n: 1.0}
        for e in sorted(map(tuple, self.exps.tolist()), key=sum):
            if e not in mono:
                i = max(j for j in range(n) if e[j])  # the last variable with a nonzero exponent
                lower = (*e[:i], e[i] - 1, *e[i + 1 :])
                mono[e] = mono[lower] * w[i] if lower in mono else self._monomial(w, e)
        return ca.vertcat(*[mono[tuple(e)] for e in self.exps.tolist()])

    def expr(self, terms: Any) -> Any:
        """Delta (3 x P) from the monomials `terms` (`Correction.terms`): the modes' polynomials, then the modes."""
        flat = ca.DM(self.mean) + ca.mtimes(ca.DM(self.basis.T), ca.mtimes(ca.DM(self.coef.T), terms))  # (3 P,)
        return ca.reshape(flat, 3, len(self.arcs))

    def tip_expr(self, terms: Any) -> Any:
        """Delta at the tip (3,) from the monomials: one polynomial per coordinate (the modes folded into the
        coefficients), which costs 3 and not R polynomials where only the tip is wanted (the safe IK's tip and
        Jacobian, the horizon's tip terms)."""
        return ca.DM(self.mean[-3:]) + ca.mtimes(ca.DM((self.coef @ self.basis[:, -3:]).T), terms)

    @staticmethod
    def _monomial(w: list[Any], e: tuple[int, ...]) -> Any:
        t: Any = 1.0
        for i, p in enumerate(e):
            for _ in range(p):
                t = t * w[i]
        return t

    def values(self, ub: np.ndarray) -> np.ndarray:
        """Delta (N, P, 3) mm in numpy at effective bending vectors ub (N, 2 n_segments) rad."""
        phi = monomials(np.atleast_2d(np.asarray(ub, dtype=float)) * self.scale, self.exps)
        return (self.mean + (phi @ self.coef) @ self.basis).reshape(len(phi), -1, 3)

    def weights(self, arcs: np.ndarray) -> np.ndarray:
        """Linear interpolation weights (len(arcs), P) of the correction at arc lengths `arcs` (mm)."""
        return np.stack([np.interp(np.asarray(arcs, dtype=float), self.arcs, np.eye(len(self.arcs))[j]) for j in
                         range(len(self.arcs))], axis=1)  # fmt: skip

    def at_arc(self, delta: Any, s: Any) -> Any:
        """The correction (3,) at a symbolic arc length s (mm): hat functions of the arc between the points."""
        h = np.diff(self.arcs)
        col: Any = 0.0
        for j, a in enumerate(self.arcs):
            left = h[j - 1] if j > 0 else h[0]
            right = h[j] if j < len(h) else h[-1]
            up = ca.fmax(0.0, ca.fmin(1.0 + (s - a) / left, 1.0 - (s - a) / right))
            if j == 0:
                up = ca.if_else(s <= a, 1.0, up)
            if j == len(self.arcs) - 1:
                up = ca.if_else(s >= a, 1.0, up)
            col = col + up * delta[:, j]
        return col

    def to_dict(self) -> dict[str, Any]:
        return {"exponents": self.exps.tolist(), "coef": self.coef.tolist(), "arcs": self.arcs.tolist()} | {
            "basis": self.basis.tolist(),
            "mean": self.mean.tolist(),
        }


class RodModel(Model):
    """The robot's `Model` whose body is the rod's (PCC plus `Correction`, the module docstring).

    error: the measured error against the rod (mm); identity: what it was made from (the surrogate's digest,
    the options), recorded with a plan and keyed into compiled kernels."""

    def __init__(
        self,
        robot: Robot,
        correction: Correction,
        error: SurrogateError,
        identity: dict[str, Any],
        n_points: int | None = None,
    ) -> None:
        self.correction, self.error, self._identity = correction, error, dict(identity)
        self._delta: Any = None
        self._mono: Any = None
        self._tip_numbers: tuple[ca.Function, np.ndarray, np.ndarray] | None = None  # `tip_position`'s
        super().__init__(robot, n_points)

    def identity(self) -> dict[str, Any] | None:
        """What makes this model's body differ from PCC's (keys compiled kernels and results)."""
        return dict(self._identity)

    @property
    def planning_margin(self) -> float:
        """mm the planner adds to D_sf: the stated bound of the body's error (`BOUND_FACTOR` x measured)."""
        return float(self.error.body_bound)

    def describe(self) -> dict[str, Any]:
        """The model as recorded with a plan: kind, identity, the measured error and the margin (mm)."""
        e = self.error
        return {"kind": "rod", **self._identity, "planning_margin_mm": self.planning_margin} | {
            "error_mm": {"body_max": e.body_max, "body_p95": e.body_p95, "tip_max": e.tip_max, "samples": e.samples}
        }

    def tip_position(self, x: Any) -> np.ndarray:
        """Tip position(s) (mm): (3,) or (N, 3). PCC's tip plus the tip's own polynomials (`Correction.tip_expr`)
        in numpy: the interpreted SX tip costs about 30 us a configuration (the closed loop takes a reference
        path's tips inside a step), this a few us for a whole path; the same polynomials, to 1e-12 mm."""
        X, single = self._as_batch(x)
        if self._tip_numbers is None:
            c = self.correction
            order = np.argsort(c.exps.sum(axis=1), kind="stable")
            pcc = ca.Function("pcc_tip", [self._x], [Model._frame_expr(self)[:3, 3]])
            self._tip_numbers = (pcc, c.exps[order], (c.coef @ c.basis[:, -3:])[order])
        pcc, exps, coef = self._tip_numbers
        w = self.robot.bending(X).reshape(len(X), -1) * self.correction.scale
        out = self._eval(pcc, X, 3, 1)[:, 0, :] + self.correction.mean[-3:] + power_products(w, exps) @ coef
        return out[0] if single else out

    def _terms(self) -> Any:
        if self._mono is None:
            self._mono = self.correction.terms(self._ub)
        return self._mono

    def _correction_expr(self) -> Any:
        if self._delta is None:
            self._delta = self.correction.expr(self._terms())
        return self._delta

    def _frame_expr(self, frac_total: float | None = None) -> ca.SX:
        T = super()._frame_expr(frac_total)
        T[:3, 3] = T[:3, 3] + self.correction.tip_expr(self._terms())
        return T

    def _points_expr(self, arcs: np.ndarray) -> ca.SX:
        w = self.correction.weights(np.asarray(arcs, dtype=float))  # (n, P)
        return super()._points_expr(arcs) + ca.mtimes(self._correction_expr(), ca.DM(w.T))

    def segment_point_function(self) -> ca.Function:
        """As `Model.segment_point_function`, with each segment's point moved by the correction at its arc."""
        base = super().segment_point_function()
        f = ca.SX.sym("f")
        pts = base(self._x, f)
        starts = np.cumsum([0.0] + [s.length for s in self.robot.segments])
        d = self._correction_expr()
        cols = [pts[:, k] + self.correction.at_arc(d, starts[k] + f * seg.length) for k, seg in
                enumerate(self.robot.segments)]  # fmt: skip
        return ca.Function("segment_points", [self._x, f], [ca.horzcat(*cols)], {"cse": True})

    def points_at_arcs(self, arcs: np.ndarray) -> ca.Function:
        """CasADi function x -> points (3 x len(arcs)) at arc lengths `arcs` (mm from the base)."""
        return ca.Function("points_at_arcs", [self._x], [ca.densify(self._points_expr(np.asarray(arcs)))])


def measure(model: RodModel, mech: Mechanics, options: RodModelOptions) -> SurrogateError:
    """The model's body against fresh rod solves at every rod node, on `options.holdout` held-out configurations
    (their own seed stream, not the fit's)."""
    sampler = RodSampler(model.robot, mech, options.surrogate.pretension)
    f = model.points_at_arcs(sampler.node_arcs)
    xs = sample_within_limits(model.robot, options.holdout, np.random.default_rng([options.seed, 1]))
    body, tip = [], []
    for x in xs:
        shape = sampler.drive.shape_config(x)
        if not shape.is_success():
            raise InputError(f"rod model: the rod's solve failed at held-out configuration {np.round(x, 4).tolist()}")
        d = np.linalg.norm(np.asarray(f(x)).T - shape.points, axis=1)
        body.append(d.max())
        tip.append(d[-1])
    b, t = np.array(body), np.array(tip)
    return SurrogateError(
        float(b.max()), float(np.percentile(b, 95)), float(t.max()), float(np.percentile(t, 95)), len(xs)
    )


def _key(sur: RodSurrogate, options: RodModelOptions) -> dict[str, Any]:
    src = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
    return {"format": FORMAT, "surrogate": sur.digest, "options": options.to_dict(), "source": src}


def _digest(key: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(key, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


def _read(path: Path, robot: Robot, key: dict[str, Any]) -> tuple[Correction, SurrogateError] | None:
    """The cached correction and error of `key` at `path`, or None (missing or not checking out: rebuilt)."""
    if not path.is_file():
        return None
    try:
        man = read_json(path, _MAX_ENTRY_BYTES)
        if not isinstance(man, dict) or man.get("key") != json.loads(json.dumps(key)):
            raise ValueError("key")
        c = man["correction"]
        corr = Correction(robot, *(np.array(c[k]) for k in ("exponents", "coef", "arcs", "basis", "mean")))
        if not all(np.all(np.isfinite(a)) for a in (corr.coef, corr.basis, corr.mean)):
            raise ValueError("coefficients")
        e = man["error_mm"]
        err = SurrogateError(*(float(e[k]) for k in ("body_max", "body_p95", "tip_max", "tip_p95")), int(e["samples"]))
    except (InputError, OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("rod model: cache entry %s is unusable (%s); rebuilding it", path.name, exc)
        return None
    return corr, err


def load_rod_model(
    robot: Robot, options: RodModelOptions | None = None, *, cache_dir: str | Path | None = None
) -> RodModel:
    """The rod's body model of `robot` (its ``[robot.mechanics]``; `InputError` naming the table when it has
    none): from the cache when its entry checks out, else the surrogate loaded or built, the correction fitted,
    its error measured and all stored (the module docstring)."""
    options = RodModelOptions() if options is None else options
    mech = Mechanics.from_robot(robot)
    root = Path(cache_dir) if cache_dir is not None else default_root()
    sur = RodSurrogate.load(robot, mech, options.surrogate, cache_dir=root)
    key = _key(sur, options)
    digest = _digest(key)
    path = root / f"rod_model-{digest[:24]}.json"
    identity = {"surrogate": sur.digest[:24], "rod_model": digest[:24], "actuation": mech.actuation}
    found = _read(path, robot, key)
    if found is not None:
        return RodModel(robot, found[0], found[1], identity)
    start = time.perf_counter()
    corr = Correction.fit(sur, options.degree, options.modes, options.samples, np.random.default_rng([options.seed, 0]))
    model = RodModel(robot, corr, SurrogateError(0.0, 0.0, 0.0, 0.0, 0), identity)
    model.error = measure(model, mech, options)
    log.info("rod model of %s: fitted and measured in %.1f s; %s", robot.name, time.perf_counter() - start,
             model.error.text())  # fmt: skip
    e = model.error
    entry = {"key": key, "correction": corr.to_dict()} | {
        "error_mm": {"body_max": e.body_max, "body_p95": e.body_p95, "tip_max": e.tip_max, "tip_p95": e.tip_p95}
        | {"samples": e.samples, "bound_factor": BOUND_FACTOR}
    }
    atomic_write_json(path, entry)
    return model
