"""Options of the steer step (the ``[steer]`` section) and the solvers' default settings (units mm, rad, s).

`SteerOptions` is read from a problem file or built in Python; `IPOPT_DEFAULTS` and `SQP_DEFAULTS` are the raw
solver options the steer's backends start from (`planning.steer_backends`), overridden by ``[steer.ipopt]`` and
``[steer.sqp]``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.core.options import Options, option
from crtraj.model.robot import MAX_COLLISION_POINTS

SOLVERS = ("ipopt", "sqp", "dls")
QP_SOLVERS = ("daqp", "qrqp", "qpoases", "osqp", "proxqp", "highs")

# Default IPOPT options (overridable from [steer.ipopt]; tol and max_iter
# come from [steer]). The NLP is tiny (nx = 2n + 1 variables), so IPOPT's
# per-iteration overhead dominates: the exact Hessian (SX) keeps iterations
# at 5-8; the adaptive barrier took fewer iterations than monotone in our
# measurements; bound_push/frac 1e-8 keep the warm start where it is; mumps
# is the linear solver bundled with CasADi.
IPOPT_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {
        "print_level": 0,
        "sb": "yes",
        "linear_solver": "mumps",
        "hessian_approximation": "exact",
        "acceptable_tol": 1e-6,
        "acceptable_iter": 5,
        "constr_viol_tol": 1e-8,
        "mu_strategy": "adaptive",
        "mu_init": 1e-2,
        "bound_push": 1e-8,
        "bound_frac": 1e-8,
    }
)

# Default sqpmethod options (overridable from [steer.sqp]).
SQP_DEFAULTS: Mapping[str, Any] = MappingProxyType(
    {
        "hessian_approximation": "exact",
        # "regularize" shifts the whole spectrum and made steps crawl (linear
        # convergence, > 50 iterations); reflecting the negative eigenvalues of the
        # 5 x 5 Hessian keeps Newton steps (~6 iterations) and, unlike clipping
        # them to ~0, no near-flat direction sends the QP step to the bounds
        "convexify_strategy": "eigen-reflect",
        # CasADi's symmetric eigen solver stops after max_iter_eig sweeps and the
        # SQP then aborts; 50 (the default) failed on 7% of the benchmark steers,
        # 5000 on none, and converged cases stop early anyway
        "max_iter_eig": 5000,
        "tol_pr": 1e-8,
        "tol_du": 1e-6,
        "min_step_size": 1e-12,
    }
)


# Most raw solver options per [steer.ipopt] / [steer.sqp] table (each solver knows a few hundred).
MAX_SOLVER_OPTIONS = 1000


def _bad_solver_value(v: Any) -> str | None:
    """Why `v` is not a raw solver option value (a string, a finite number or a boolean), or None."""
    if not isinstance(v, (bool, int, float, str)):
        return f"expected a string, number or boolean, got {v!r:.60}"
    if isinstance(v, float) and not math.isfinite(v):
        return f"must be finite, got {v}"
    # solver options are counts, levels and tolerances; IPOPT's own "infinity" is 1e19
    if isinstance(v, (int, float)) and not isinstance(v, bool) and abs(v) > 1e20:
        return f"must be within +-1e20, got {float(v):g}"
    if isinstance(v, str) and len(v) > 1000:
        return "longer than 1000 characters"
    return None


def _pairs(t: Table) -> tuple[tuple[str, Any], ...]:
    """Solver option overrides read from a TOML table: every value a string, number or boolean."""
    keys = t.keys()
    if len(keys) > MAX_SOLVER_OPTIONS:
        raise InputError(f"{t.path}: at most {MAX_SOLVER_OPTIONS} solver options, got {len(keys)}")
    out = []
    for key in keys:
        v = t.raw(key)
        problem = _bad_solver_value(v)
        if problem is not None:
            raise t.error(key, problem)
        out.append((key, v))
    t.finish()
    return tuple(out)


def _check_pairs(pairs: Any, name: str) -> tuple[tuple[str, Any], ...]:
    """The same rules for overrides given in Python, as a sequence of (name, value) pairs."""
    if not isinstance(pairs, (tuple, list)) or len(pairs) > MAX_SOLVER_OPTIONS:
        raise InputError(f"{name}: expected at most {MAX_SOLVER_OPTIONS} (name, value) pairs, got {pairs!r:.60}")
    out = []
    for i, pair in enumerate(pairs):
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2 and isinstance(pair[0], str)):
            raise InputError(f"{name}[{i}]: expected a (name, value) pair, got {pair!r:.60}")
        key, v = pair
        if not key or len(key) > 200 or not key.isprintable():
            raise InputError(f"{name}[{i}]: an option name is 1 to 200 printable characters, got {key!r:.60}")
        problem = _bad_solver_value(v)
        if problem is not None:
            raise InputError(f"{name}.{key}: {problem}")
        out.append((key, v))
    return tuple(out)


@dataclass(frozen=True)
class SteerOptions(Options):
    """Options of the ``[steer]`` section (units mm, rad, s).

    solver: "ipopt" (default), "sqp" (CasADi sqpmethod + `qpsol`, the fast
    path) or "dls" (iterated damped least squares, eq. 17, no hard
    constraints). damping, obstacle_coefficient: the paper's lambda and mu;
    damping_scale, obstacle_scale: their mapping to NLP weights (module
    docstring). max_step: bound on ``|S (x - x_prev)|_inf`` (mm). tolerance:
    tip error (mm) counted as reached. margin: extra keep-out (mm) added to
    every obstacle in the hard constraints. n_points: constrained backbone
    points (default the robot's collision_points). max_iter, tol: solver
    iteration cap and tolerance (IPOPT `tol`; sqpmethod `tol_pr`; its
    `tol_du` is 1e-6 in SQP_DEFAULTS). qpsol: QP solver of the sqp path.
    jit: compile the NLP functions with gcc through CasADi's shell compiler
    (falls back to no jit, with `SteerSolver.jit_message` saying why).
    compiled: with solver "sqp" and qpsol daqp or qrqp, generate C for the
    whole step (DLS predictor, sqpmethod with its QP solver, the re-check's
    tip, points and limits, the KKT residuals), compile it once (cached) and
    call it through ctypes: one foreign call per steer. Its convergence is
    judged from the KKT residuals it returns (sqpmethod's own test,
    tol_pr/tol_du); the generated code reports no iteration count
    (`SteerResult.iterations` is -1). Without a C compiler, or with another
    qpsol, the interpreted solver runs (`SteerSolver.compiled_message` says so).
    warm_start: start from the previous successful solve's multipliers
    (default None = on for sqp, where it saved iterations, off for IPOPT,
    where warm_start_init_point cost more time than the iteration it
    saved). fallback: when the sqp path does not converge, re-solve with
    IPOPT (result.solver is then "sqp>ipopt"). predictor: start from one
    DLS step instead of x_prev. feasibility_tolerance: constraint slack (mm)
    accepted by the re-check. dls_gain, dls_iterations: K_P and iterations
    of the dls path. ipopt, sqp: raw solver options overriding the defaults
    (``[steer.ipopt]`` / ``[steer.sqp]`` tables; (name, value) pairs in Python).
    """

    SECTION: ClassVar[str] = "steer"

    solver: str = option("ipopt", choices=SOLVERS)
    damping: float = option(0.3, ge=0.0)
    obstacle_coefficient: float = option(20.0, ge=0.0)
    damping_scale: float = option(0.02, gt=0.0)
    obstacle_scale: float = option(0.02, gt=0.0)
    max_step: float = option(100.0, gt=0.0, limit=MAX_LENGTH)
    tolerance: float = option(0.5, gt=0.0, limit=MAX_LENGTH)
    margin: float = option(0.0, ge=0.0, limit=MAX_LENGTH)
    n_points: int | None = option(None, ge=2, le=MAX_COLLISION_POINTS)
    max_iter: int = option(100, ge=1, le=100_000)
    tol: float = option(1e-6, gt=0.0)
    qpsol: str = option("daqp", choices=QP_SOLVERS)
    jit: bool = option(False)
    compiled: bool = option(False)
    warm_start: bool | None = option(None)
    fallback: bool = option(True)
    predictor: bool = option(True)
    feasibility_tolerance: float = option(1e-5, ge=0.0)
    dls_gain: float = option(1.0, gt=0.0, le=1.0)
    dls_iterations: int = option(200, ge=1, le=100_000)
    ipopt: tuple[tuple[str, Any], ...] = option((), read=False)
    sqp: tuple[tuple[str, Any], ...] = option((), read=False)

    def _check(self) -> None:
        object.__setattr__(self, "ipopt", _check_pairs(self.ipopt, "steer.ipopt"))
        object.__setattr__(self, "sqp", _check_pairs(self.sqp, "steer.sqp"))

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        return {"ipopt": _pairs(t.table("ipopt")), "sqp": _pairs(t.table("sqp"))}

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the ``[steer]`` schema (round-trips through `from_table`).

        Own override: the raw solver options are sub-tables in the file (``[steer.ipopt]``), not the
        list of pairs the base would write; empty ones are left out.
        """
        d = super().to_dict()
        for key in ("ipopt", "sqp"):
            pairs = d.pop(key)
            if pairs:
                d[key] = {k: v for k, v in pairs}
        return d

    @property
    def uses_warm_start(self) -> bool:
        """The warm_start setting resolved per solver."""
        return self.warm_start if self.warm_start is not None else self.solver == "sqp"

    @property
    def damping_weight(self) -> float:
        """w_d = (damping * damping_scale)^2, weight of |S dx|^2 (mm^2)."""
        return (self.damping * self.damping_scale) ** 2

    @property
    def obstacle_weight(self) -> float:
        """w_o = (obstacle_coefficient * obstacle_scale)^2, weight of the eq. 18 sum (mm^2)."""
        return (self.obstacle_coefficient * self.obstacle_scale) ** 2
