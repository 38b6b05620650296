"""The steer step's backends, one class per way of solving the `SteerNLP` (`NLPBackend[SteerQuery, SteerSolution]`).

- `DlsBackend`: iterated damped least squares (paper eq. 17), no hard constraints;
- `IpoptBackend`: CasADi's IPOPT (with a second instance that starts from the previous multipliers);
- `SqpBackend`: CasADi's sqpmethod with a QP solver (daqp by default), optionally jit-compiled with gcc;
- `RescuedBackend`: one backend, and IPOPT re-solving the same problem when it does not converge ("sqp>ipopt");
- `planning.steer_compiled.CompiledBackend`: the whole step as generated C.

`SteerSolver` picks one when it is built. `SolverFactory` builds the CasADi solvers with the options of the
``[steer]`` section; `WarmStart` holds the multipliers the backends of one solver share.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any, Protocol

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.interrupt import check as check_interrupt
from crtraj.planning.nlp import NLPBackend
from crtraj.planning.steer._nlp import NlpCall, SteerNLP, SteerQuery, SteerSolution
from crtraj.planning.steer._options import IPOPT_DEFAULTS, SQP_DEFAULTS, SteerOptions

_JIT_KEYS = ("jit", "compiler", "jit_options")


class SteerBackend(NLPBackend[SteerQuery, SteerSolution], Protocol):
    """An `NLPBackend` of the steer step. recheck_in_scene: whether `assess` measures the clearance in the
    query's scene (False: against the packed spheres, as the compiled step does)."""

    recheck_in_scene: bool

    def reset_warm_start(self) -> None:
        """Forget the multipliers of the previous solve."""
        ...


class WarmStart:
    """The multipliers (lam_g, lam_x) of the last successful solve, shared by the backends of one solver.

    enabled: whether a solve starts from them (`SteerOptions.uses_warm_start`); they are kept either way.
    """

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.lam_g: np.ndarray | None = None
        self.lam_x: np.ndarray | None = None

    @property
    def ready(self) -> bool:
        """Enabled, and a successful solve left multipliers."""
        return self.enabled and self.lam_g is not None

    def keep(self, lam_g: np.ndarray, lam_x: np.ndarray) -> None:
        """Remember the multipliers of a successful solve."""
        self.lam_g, self.lam_x = lam_g, lam_x

    def reset(self) -> None:
        """Forget the multipliers."""
        self.lam_g = self.lam_x = None


class DlsBackend:
    """Iterate eq. 17 from x_prev inside the step bounds; stop at 1/100 of the tolerance or when the step
    stalls (the closest point DLS can reach)."""

    name = "dls"
    recheck_in_scene = True

    def __init__(self, nlp: SteerNLP) -> None:
        self.nlp = nlp

    def solve(self, query: SteerQuery) -> SteerSolution:
        nlp, o = self.nlp, self.nlp.options
        xp, tg, lo, hi = query.x_prev, query.target, query.lbx, query.ubx
        tip, J, pts0, g0 = nlp.evaluate(xp)
        if query.check_start:
            nlp.check_start(query, pts0, g0)
        x = xp
        for it in range(o.dls_iterations):
            if np.linalg.norm(tg - tip) <= 0.01 * o.tolerance:
                return SteerSolution(x, True, "Solve_Succeeded", it, self.name)
            xn = nlp.dls_update(x, tip, J, tg, lo, hi)
            if np.max(np.abs((xn - x) * nlp.scale)) < 1e-9:
                return SteerSolution(xn, True, "Stalled_At_Closest_Point", it + 1, self.name)
            x = xn
            tip, J, _, _ = nlp.evaluate(x)
        return SteerSolution(x, False, "Maximum_Iterations_Exceeded", o.dls_iterations, self.name)

    def reset_warm_start(self) -> None:
        """Nothing to forget: each DLS solve starts from x_prev."""


class NlpsolBackend:
    """A CasADi ``nlpsol`` solving the NLP from the DLS predictor (or the query's guess) within the step
    bounds. warm_solver: the instance used when starting from the previous multipliers (None: `solver`)."""

    recheck_in_scene = True

    def __init__(
        self, name: str, nlp: SteerNLP, solver: ca.Function, warm: WarmStart, warm_solver: ca.Function | None = None
    ) -> None:
        self.name = name
        self.nlp = nlp
        self.solver = solver
        self.warm = warm
        self.warm_solver = warm_solver

    def solve(self, query: SteerQuery) -> SteerSolution:
        return self.run(self.prepare(query), warm=True)

    def prepare(self, query: SteerQuery) -> NlpCall:
        """The start check (if asked), then the numeric inputs of the solve."""
        nlp = self.nlp
        xp, tg, lbx, ubx = query.x_prev, query.target, query.lbx, query.ubx
        tip0, J0, pts0, g0 = nlp.evaluate(xp)
        if query.check_start:
            nlp.check_start(query, pts0, g0)
        guess = query.guess
        if guess is None:
            guess = nlp.dls_update(xp, tip0, J0, tg, lbx, ubx) if nlp.options.predictor else xp
        p = nlp.parameters(xp, tg, query.packed, query.dsf, query.damping_weight, query.obstacle_weight)
        lbg = nlp.lbg_for(query.packed)
        return NlpCall(p, lbg, np.clip(guess, lbx, ubx), lbx, ubx)

    def run(self, call: NlpCall, warm: bool) -> SteerSolution:
        """Solve from call.x0 (and, with `warm` and a warm start ready, the previous multipliers)."""
        S, solver, lbx, ubx = self.nlp.scale, self.solver, call.lbx, call.ubx
        args: dict[str, Any] = {
            "x0": call.x0 * S,
            "p": call.p,
            "lbx": lbx * S,
            "ubx": ubx * S,
            "lbg": call.lbg,
            "ubg": self.nlp.ubg,
        }
        if warm and self.warm.ready:
            args["lam_g0"] = self.warm.lam_g
            args["lam_x0"] = self.warm.lam_x
            if self.warm_solver is not None:
                solver = self.warm_solver
        try:
            sol = solver(**args)
        except RuntimeError as exc:  # evaluation errors (NaN) inside CasADi
            check_interrupt()  # or what CasADi made of a Ctrl-C (crtraj.core.interrupt)
            self.warm.reset()
            return SteerSolution(call.x0.copy(), False, f"Evaluation_Error: {last_line(str(exc))}", 0, self.name)
        check_interrupt()  # CasADi turns a Ctrl-C into a stopped solve: stop here (crtraj.core.interrupt)
        stats = solver.stats()
        # IPOPT relaxes bounds by ~1e-8 relative; project back so the re-check
        # judges the configuration that is actually returned
        x = np.clip(np.asarray(sol["x"], dtype=float).reshape(-1) / S, lbx, ubx)
        ok = bool(stats.get("success", False)) and bool(np.all(np.isfinite(x)))
        if ok:
            self.warm.keep(
                np.asarray(sol["lam_g"], dtype=float).reshape(-1), np.asarray(sol["lam_x"], dtype=float).reshape(-1)
            )
        else:
            self.warm.reset()
        status, iters = str(stats.get("return_status", "unknown")), int(stats.get("iter_count", -1))
        return SteerSolution(x, ok, status, iters, self.name, call=None if ok else call)

    def reset_warm_start(self) -> None:
        """Forget the multipliers of the previous solve."""
        self.warm.reset()


class IpoptBackend(NlpsolBackend):
    """IPOPT (`IPOPT_DEFAULTS`, ``[steer.ipopt]``); with warm starts, a second instance with
    warm_start_init_point starts from the previous multipliers."""

    @classmethod
    def build(cls, factory: SolverFactory, warm: WarmStart, *, rescue: bool = False) -> IpoptBackend:
        """Build and probe the options on one solve. rescue: the IPOPT of a `RescuedBackend`, which always
        starts cold, built without jit: rare sqp failures (a QP solver's inexact multipliers stall the dual
        test) are re-solved by it."""
        ip = factory.ipopt_options()
        common = factory.plain if rescue else factory.common
        solver = factory.nlpsol("ipopt", {**common, "ipopt": ip}, "steer.ipopt")
        warm_solver = None
        if factory.options.uses_warm_start and not rescue:
            ws = {**ip, "warm_start_init_point": "yes"}
            warm_solver = factory.nlpsol("ipopt", {**common, "ipopt": ws}, "steer.ipopt")
        backend = cls("ipopt", factory.nlp, solver, warm, warm_solver)
        backend.probe()  # IPOPT reads its options at the first solve: surface bad ones now
        return backend

    def probe(self) -> None:
        """One solve at the straight configuration; `InputError` when IPOPT rejected an option."""
        nlp = self.nlp
        x0 = nlp.robot.straight()
        tip = np.asarray(nlp.model.tip(x0), dtype=float).reshape(-1)
        p = nlp.parameters(x0, tip, nlp.padding(), 0.0)
        lbx, ubx = nlp.step_bounds(x0)
        for solver in (self.solver, self.warm_solver):
            if solver is None:
                continue
            S = nlp.scale
            solver(x0=x0 * S, p=p, lbx=lbx * S, ubx=ubx * S, lbg=nlp.lbg, ubg=nlp.ubg)
            if solver.stats().get("return_status", "") == "Invalid_Option":
                keys = ", ".join(k for k, _ in nlp.options.ipopt) or "(defaults)"
                raise InputError(f"steer.ipopt: IPOPT rejected an option (given: {keys})")


class SqpBackend(NlpsolBackend):
    """CasADi's sqpmethod (`SQP_DEFAULTS`, ``[steer.sqp]``) with the QP solver `qpsol`, jit-compiled when
    the factory compiles."""

    @classmethod
    def build(cls, factory: SolverFactory, warm: WarmStart) -> SqpBackend:
        solver = factory.nlpsol("sqpmethod", {**factory.common, **factory.sqp_options()}, "steer.sqp")
        return cls("sqp", factory.nlp, solver, warm)


class RescuedBackend:
    """`primary`, and when it does not converge, `rescue` (IPOPT, cold) on the same NLP inputs; the
    result then says "sqp>ipopt" and why."""

    name = "sqp>ipopt"

    def __init__(self, primary: SteerBackend, rescue: NlpsolBackend) -> None:
        self.primary = primary
        self.rescue = rescue
        self.recheck_in_scene = primary.recheck_in_scene

    def solve(self, query: SteerQuery) -> SteerSolution:
        first = self.primary.solve(query)
        if first.converged or first.call is None:
            return first
        second = self.rescue.run(first.call, warm=False)
        if first.iterations >= 0:
            note = f"sqp: {first.status} after {first.iterations} iterations; re-solved by IPOPT. "
            iters = first.iterations + second.iterations
        else:  # the compiled step reports no iteration count
            note = f"sqp: {first.status}; re-solved by IPOPT. "
            iters = second.iterations
        return SteerSolution(second.x, second.converged, second.status, iters, self.name, note)

    def reset_warm_start(self) -> None:
        """Forget the multipliers of the previous solve (shared by both backends)."""
        self.primary.reset_warm_start()
        self.rescue.reset_warm_start()


class SolverFactory:
    """Builds CasADi solvers of one `SteerNLP` with the options of ``[steer]``.

    With `jit`, the interpreted solvers are compiled with gcc into a folder owned by the factory (removed
    with it); `jit_message` says how that went ("" without jit).
    """

    def __init__(self, nlp: SteerNLP) -> None:
        self.nlp = nlp
        self.options: SteerOptions = nlp.options
        self.jit_message = ""
        self.jit_dir: tempfile.TemporaryDirectory[str] | None = None
        self.common: dict[str, Any] = {"print_time": False, "error_on_fail": False, "calc_lam_p": False}
        if self.options.jit:
            self._setup_jit()

    def _setup_jit(self) -> None:
        if shutil.which("gcc") is None:
            self.jit_message = "jit requested but gcc was not found: running without jit"
            return
        # CasADi's shell compiler writes its C and object files to the working
        # directory unless told otherwise; keep them in a folder owned by this solver,
        # which removes it (so CasADi's own clean-up is off: it would warn at exit).
        self.jit_dir = tempfile.TemporaryDirectory(prefix="crtraj-jit-")
        jit_opts = {"compiler": "gcc", "flags": ["-O2"], "directory": self.jit_dir.name + "/", "cleanup": False}
        self.common.update({"jit": True, "compiler": "shell", "jit_options": jit_opts, "jit_cleanup": False})
        self.jit_message = "jit: compiled with gcc -O2"

    @property
    def plain(self) -> dict[str, Any]:
        """The common options without jit."""
        return {k: v for k, v in self.common.items() if k not in _JIT_KEYS}

    def ipopt_options(self) -> dict[str, Any]:
        """IPOPT_DEFAULTS, then tol and max_iter, then ``[steer.ipopt]``."""
        o = self.options
        ip = dict(IPOPT_DEFAULTS)
        ip.update({"tol": o.tol, "max_iter": o.max_iter})
        ip.update(dict(o.ipopt))
        return ip

    def sqp_options(self) -> dict[str, Any]:
        """SQP_DEFAULTS, then max_iter, tol and qpsol (quiet), then ``[steer.sqp]``."""
        o = self.options
        sq = dict(SQP_DEFAULTS)
        sq.update({"max_iter": o.max_iter, "tol_pr": o.tol, "qpsol": o.qpsol})
        sq.update({"qpsol_options": _qp_options(o.qpsol), "print_header": False})
        sq.update({"print_iteration": False, "print_status": False})
        sq.update(dict(o.sqp))
        return sq

    def nlpsol(self, plugin: str, opts: dict[str, Any], field_name: str) -> ca.Function:
        """``nlpsol`` of the NLP; a failing jit falls back to no jit, rejected options raise `InputError`."""
        try:
            solver = ca.nlpsol(f"steer_{plugin}", plugin, self.nlp.problem, opts)
        except RuntimeError as exc:
            text = str(exc)
            if opts.get("jit"):
                # a broken compiler must not make the steer unusable
                self.jit_message = f"jit failed ({last_line(text)}): running without jit"
                opts = {k: v for k, v in opts.items() if k not in _JIT_KEYS}
                return self.nlpsol(plugin, opts, field_name)
            raise InputError(f"{field_name}: solver rejected the options ({last_line(text)})") from None
        if opts.get("jit") and self.jit_dir is not None:
            _remove_stray_sources(Path(self.jit_dir.name))
        return solver


def _qp_options(qpsol: str) -> dict[str, Any]:
    """Silent, non-raising options of each QP solver."""
    quiet: dict[str, dict[str, Any]] = {
        "daqp": {},
        "qrqp": {"print_iter": False, "print_header": False, "print_info": False},
        "qpoases": {"printLevel": "none"},
        "osqp": {"osqp": {"verbose": False}},
        "proxqp": {"proxqp": {"verbose": False}},
        "highs": {"highs": {"output_flag": False}},
    }
    return {"error_on_fail": False, **quiet[qpsol]}


def _remove_stray_sources(private: Path) -> None:
    """Delete the jit's C sources that CasADi's nlpsol writes to the working directory.

    Measured with CasADi 3.8: an nlpsol built with jit reserves a unique name
    ``jit_tmpXXXXXX.c`` in the jit directory (an empty file) but writes the
    source under that name to the working directory (a plain Function honours
    the directory). The names are random and reserved in this solver's private
    folder, so a working-directory file of the same name is this build's source.
    """
    for reserved in private.glob("jit_tmp*.c"):
        try:
            (Path.cwd() / reserved.name).unlink(missing_ok=True)
        except OSError:  # a read-only or vanished working directory: nothing was written there
            continue


def last_line(text: str) -> str:
    """The last non-empty line of a (CasADi) error text."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else text
