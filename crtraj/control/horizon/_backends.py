"""The ways one horizon NLP query is solved, one class each (`crtraj.planning.nlp.NLPBackend`).

`InterpretedBackend` calls a CasADi solver (IPOPT or sqpmethod) and looks at what it returned independently;
`CompiledBackend` calls the generated C of the sqpmethod solver and its KKT check; `ScreenedBackend` wraps
either with the screening of `closest_points` (the K backbone points nearest to each obstacle and step are the
QP's rows, every point is checked at the solution, and a solution that leaves an omitted point inside its sphere
is solved again from there). The `Replanner` chooses them once when it is built. Units: mm, rad, s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from crtraj.control.horizon._build import FUSED_OUT, CompiledParts
from crtraj.core.interrupt import check as check_interrupt
from crtraj.planning.nlp import CompiledFunction

# With `closest_points`, at most this many solves of the QP's NLP per query of `ScreenedBackend`: a solution that
# leaves an omitted point inside its sphere is solved again with the closest points there.
SCREEN_SOLVES = 3


@dataclass(frozen=True)
class ScreenStart:
    """What the screening knows of a start point: its obstacle rows (N, M, points) mm and the selection (N, M, K)
    whose multipliers the start's come with (either may be None)."""

    dist: np.ndarray | None = None
    sel: np.ndarray | None = None


def replace(obj: Any, /, **changes: Any) -> Any:
    """`dataclasses.replace` for `HorizonQuery` and `HorizonCall` (frozen, every field an __init__ argument, no
    __post_init__): a copy of the instance's fields with `changes`, at a quarter of the cost (a step makes about
    five). A name that is not a field is a TypeError, as there."""
    unknown = changes.keys() - obj.__dataclass_fields__.keys()
    if unknown:
        raise TypeError(f"{type(obj).__name__} has no field {sorted(unknown)[0]!r}")
    new = object.__new__(type(obj))
    new.__dict__.update(obj.__dict__)
    new.__dict__.update(changes)
    return new


@dataclass(frozen=True)
class HorizonQuery:
    """One solve of the horizon NLP: parameters p (the full NLP's; the screening appends its selection), start
    point x0 (N nx,), the start's multipliers (None: the solver's default) and what is known of the start
    for the screening (None: nothing)."""

    p: np.ndarray
    x0: np.ndarray
    lam_x0: np.ndarray | None = None
    lam_g0: np.ndarray | None = None
    start: ScreenStart | None = None


@dataclass(frozen=True)
class HorizonCall:
    """What one backend returned for a query, looked at independently.

    sol: the solver's outputs (x, f, g, lam_x, lam_g; the compiled path adds the tips and every obstacle row).
    x: (N nx,) its point. wall: s. finite: x and g are finite. violation: largest violation of the box and the
    rows (mixed units). status: the solver's own status text. ok: converged within the rows (1e-6).
    iterations (-1: not reported). cost. min_distance: the smallest obstacle row (mm; inf without). solves:
    solves of the QP's NLP. distances: (N, M, points) every obstacle row at x (screened), selection: (N, M, K)
    the screened points, both None otherwise.
    """

    sol: dict[str, Any]
    x: np.ndarray
    wall: float
    finite: bool
    violation: float
    status: str
    ok: bool
    iterations: int
    cost: float
    min_distance: float
    solves: int = 1
    distances: np.ndarray | None = field(default=None, repr=False)
    selection: np.ndarray | None = field(default=None, repr=False)


@dataclass(frozen=True)
class RowCheck:
    """The bounds a backend's solutions are checked against: the box (N nx,) and lbg <= g <= ubg; the rows
    after the first n_lin are obstacle rows when `obstacles`."""

    box_lo: np.ndarray
    box_hi: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    n_lin: int
    obstacles: bool

    def violation(self, xs: np.ndarray, gs: np.ndarray) -> float:
        """Largest violation of the box and of the rows lbg <= g <= ubg (mixed units; 0 when all hold)."""
        return max(
            float(np.max(self.lbg - gs, initial=0.0)),
            float(np.max(gs - self.ubg, initial=0.0)),
            float(np.max(self.box_lo - xs, initial=0.0)),
            float(np.max(xs - self.box_hi, initial=0.0)),
        )

    def args(self, query: HorizonQuery) -> dict[str, Any]:
        """A CasADi solver's arguments for `query` (no multipliers when the query has none)."""
        args: dict[str, Any] = {"p": query.p, "lbx": self.box_lo, "ubx": self.box_hi, "lbg": self.lbg, "ubg": self.ubg}
        args["x0"] = query.x0
        if query.lam_g0 is not None:
            args.update(lam_x0=query.lam_x0, lam_g0=query.lam_g0)
        return args

    def record(self, sol: dict[str, Any], stats: dict[str, Any], wall: float) -> HorizonCall:
        """The call's outputs and an independent look at them (the violation from stats when the call gave it)."""
        xs = np.asarray(sol["x"]).ravel()
        gs = np.asarray(sol["g"]).ravel()
        finite = bool(np.isfinite(xs).all() and np.isfinite(gs).all())
        if not finite:
            viol = math.inf
        elif "violation" in stats:
            viol = stats["violation"]  # the compiled call's own check, of the same point and rows
        else:
            viol = self.violation(xs, gs)
        return HorizonCall(
            sol=sol,
            x=xs,
            wall=wall,
            finite=finite,
            violation=viol,
            status=str(stats.get("return_status", "unknown")),
            ok=bool(stats.get("success", False)) and finite and viol <= 1e-6,
            iterations=int(stats.get("iter_count", -1)),
            cost=float(sol["f"]) if finite else math.inf,
            # the smallest obstacle row (of the full NLP; `ScreenedBackend` checks every point after a QP NLP)
            min_distance=float(np.min(gs[self.n_lin :])) if (self.obstacles and finite) else math.inf,
        )


class InterpretedBackend:
    """A CasADi solver (IPOPT or sqpmethod, interpreted) of one NLP: one call per query."""

    def __init__(self, name: str, solver: Any, check: RowCheck) -> None:
        """solver: anything with CasADi's `call(args)` and `stats()` (normally the `casadi.nlpsol`)."""
        self.name = name
        self.solver = solver
        self.check = check

    def solve(self, query: HorizonQuery) -> HorizonCall:
        """One solver call and an independent look at what it returned."""
        t_start = time.perf_counter()
        sol = self.solver.call(self.check.args(query))
        check_interrupt()  # CasADi turns a Ctrl-C into a stopped solve: stop here (crtraj.core.interrupt)
        st = self.solver.stats()
        return self.check.record(sol, st, time.perf_counter() - t_start)


class CompiledBackend:
    """The sqpmethod solver as generated C (`CompiledParts`): one call of it and of its KKT check per query.

    Success is sqpmethod's own test recomputed at the returned point: primal violation < 1e-7 and dual residual
    < tol. The generated code reports no iteration count (-1)."""

    name = "compiled"

    def __init__(self, parts: CompiledParts, check: RowCheck, tol: float) -> None:
        self.parts = parts
        self.check = check
        self.tol = tol

    def solve(self, query: HorizonQuery) -> HorizonCall:
        """One call of the compiled solver and its KKT check (one foreign call with `CompiledParts.fused`)."""
        t_start = time.perf_counter()
        if self.parts.fused is not None:
            sol, st = self._fused(query)
        else:
            sol, st = self._call(self.check.args(query))
        return self.check.record(sol, st, time.perf_counter() - t_start)

    def _fused(self, query: HorizonQuery) -> tuple[dict[str, Any], dict[str, Any]]:
        """`_call` as one call of the fused function (solver, KKT check and row check in C; the bounds are its
        constants): the same outputs and the same test of success."""
        lam_x0 = None if query.lam_g0 is None else query.lam_x0  # as `RowCheck.args`: both or neither
        out = self.parts.fused(query.x0, query.p, lam_x0, query.lam_g0)  # type: ignore[misc]
        sol = {k: a.copy() for k, a in zip(FUSED_OUT, out, strict=True)}
        du, pr = float(sol.pop("du")[0]), float(sol.pop("violation")[0])
        sol["f"] = float(sol["f"][0])
        return sol, self._stats(pr, du)

    def _stats(self, pr: float, du: float) -> dict[str, Any]:
        """The stats sqpmethod would give for a point of primal violation pr and dual residual du."""
        ok = math.isfinite(du) and math.isfinite(pr) and pr < 1e-7 and du < self.tol
        status = "Solve_Succeeded" if ok else f"Not_Converged (compiled sqpmethod: primal {pr:.2g}, dual {du:.2g})"
        return {"success": ok, "return_status": status, "iter_count": -1, "violation": pr}

    def _call(self, args: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        """The compiled solver's outputs and the stats sqpmethod would give."""
        names = ("x0", "p", "lbx", "ubx", "lbg", "ubg", "lam_x0", "lam_g0")
        out = self.parts.step(*[args.get(n) for n in names])
        sol = dict(zip(("x", "f", "g", "lam_x", "lam_g", "lam_p"), (a.copy() for a in out), strict=True))
        sol["f"] = float(sol["f"][0])
        du_, distances, tips = self.parts.kkt(sol["x"], args["p"], sol["lam_g"], sol["lam_x"])
        du = float(du_[0])
        sol["distances"], sol["tips"] = distances.copy(), tips.copy()
        return sol, self._stats(self.check.violation(sol["x"], sol["g"]), du)


class ObstacleRows:
    """Every obstacle row of the full NLP at given configurations (by the compiled function when there is one)."""

    def __init__(
        self, all_distance: ca.Function, compiled: CompiledFunction | None, shape: tuple[int, int, int]
    ) -> None:
        """all_distance: (X, O) -> the rows as a CasADi function; compiled: the same as generated C (or None);
        shape: (N, M, points) of the rows."""
        self.all_distance = all_distance
        self.compiled = compiled
        self.shape = shape

    def __call__(self, xs: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """(N, M, points) mm: distance of each backbone point of each step from the obstacle slot's centre minus
        its inflated radius, at configurations xs (N nx,)."""
        if self.compiled is not None:
            d = self.compiled(xs, obstacles)[0]
        else:
            d = np.asarray(self.all_distance(xs, obstacles)).ravel(order="F")
        return d.reshape(self.shape)


class PointScreen:
    """The selection of the K backbone points per obstacle and step that the QP's NLP keeps as rows."""

    def __init__(self, K: int, slot_table: np.ndarray, n_lin: int) -> None:
        """slot_table: (points, segments + 1) per backbone point its one-hot segment and arc fraction. n_lin:
        the rows before the obstacle rows."""
        self.K = K
        self.slot_table = slot_table
        self.n_lin = n_lin

    def nearest(self, d: np.ndarray) -> np.ndarray:
        """Indices (N, M, K) of the K points with the smallest obstacle rows d (N, M, points), ascending (so the
        same set gives the same slots, and the warm start's multipliers stay with their points)."""
        return np.sort(np.argsort(d, axis=-1, kind="stable")[..., : self.K], axis=-1)

    def parameter(self, selection: np.ndarray) -> np.ndarray:
        """The selection parameter of the QP's NLP: per slot, a one-hot column over the segments and the fraction
        of that segment's arc where the selected backbone point lies."""
        return self.slot_table[selection].ravel()

    def keep_multipliers(self, lam_g: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """lam_g with the multipliers of the obstacle slots whose point changed set to zero."""
        lam = np.array(lam_g, dtype=float)
        lam[self.n_lin :].reshape(old.shape)[old != new] = 0.0
        return lam


class ScreenedBackend:
    """A backend of the QP's NLP whose obstacle rows are the `closest_points` nearest points (`PointScreen`),
    with every point checked at the solution.

    A solution that leaves an omitted point inside its sphere is solved again, from there, with the closest points
    there (at most `SCREEN_SOLVES` solves); if one still does, the result is not ok. A solution whose omitted
    points all hold is a KKT point of the full NLP too (their multipliers are zero), so "ok" means what it means
    without screening. closest: (xs, obstacles) -> the (N, M, K) selection at configurations xs.
    """

    def __init__(
        self,
        inner: InterpretedBackend | CompiledBackend,
        screen: PointScreen,
        rows: ObstacleRows,
        closest: Callable[[np.ndarray, np.ndarray], np.ndarray],
        n_obstacle_p: int,
    ) -> None:
        self.name = inner.name
        self.inner = inner
        self.screen = screen
        self.rows = rows
        self.closest = closest
        self.n_obstacle_p = n_obstacle_p

    def solve(self, query: HorizonQuery) -> HorizonCall:
        """Solves of the QP's NLP until every omitted point holds (or `SCREEN_SOLVES`). The query's start: the
        shifted previous solve or the previous call's iterate, whose selection its multipliers belong to and
        whose obstacle rows give the first selection (none: the closest points at x0)."""
        t_start = time.perf_counter()
        p, O = query.p, query.p[len(query.p) - self.n_obstacle_p :]
        w = query.start
        known = w is not None and w.dist is not None
        sel = self.screen.nearest(w.dist) if known else self.closest(query.x0, O)  # type: ignore[union-attr,arg-type]
        if query.lam_g0 is not None and w is not None and w.sel is not None:
            query = replace(query, lam_g0=self.screen.keep_multipliers(query.lam_g0, w.sel, sel))
        solves = 0
        while True:
            r = self.inner.solve(replace(query, p=np.concatenate([p, self.screen.parameter(sel)]), start=None))
            solves += 1
            if not r.finite:
                break
            r, dmin = self._checked(r, O)
            if dmin >= -1e-6 or solves >= SCREEN_SOLVES:
                if dmin < -1e-6:
                    r = replace(r, status=r.status + f"; an omitted point stays {-dmin:.3g} mm inside its sphere")
                break
            # an omitted point entered its sphere: again, with the closest points of this solution
            new = self.closest(r.x, O)
            lam_g = self.screen.keep_multipliers(np.asarray(r.sol["lam_g"]).ravel(), sel, new)
            query = replace(query, x0=r.x, lam_x0=np.asarray(r.sol["lam_x"]).ravel(), lam_g0=lam_g)
            sel = new
        return replace(r, selection=sel, solves=solves, wall=time.perf_counter() - t_start)

    def _checked(self, r: HorizonCall, obstacles: np.ndarray) -> tuple[HorizonCall, float]:
        """(r with every obstacle row of the full NLP at its point: the smallest row, sphere or shape, and the
        violation and "ok" with them; the smallest sphere row). The QP's shape rows are the full NLP's, and its
        sphere rows are among the full ones, so the smaller of r's own smallest row and the full sphere rows'
        is the full NLP's."""
        D = r.sol["distances"] if "distances" in r.sol else self.rows(r.x, obstacles)
        dmin = float(np.min(D))
        violation = max(r.violation, -dmin)
        checked = replace(
            r,
            distances=D.reshape(self.rows.shape),
            min_distance=min(dmin, r.min_distance),
            violation=violation,
            ok=r.ok and violation <= 1e-6,
        )
        return checked, dmin
