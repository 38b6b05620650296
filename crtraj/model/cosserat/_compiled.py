"""The Cosserat rod's shooting as generated C, and a warm-started Newton (chord) iteration on it.

`crtraj.model.cosserat._statics` inlines the whole shooting (two segments of 20 RK4 steps, each with a 6x6
elimination) into one SX graph and runs CasADi's Newton rootfinder on it in the SX virtual machine:
about 13 ms per warm solve. Here the same `RodPieces` are chained in an MX graph that *calls* them, so
the generated C holds each piece once, and two libraries go through the build cache
(`crtraj.core.build_cache`):

- ``rod_shape`` (w, p) -> (r, points, R_tip, turn, paths), at -O2: about 0.05 ms; small, compiles in
  seconds;
- ``rod_resjac`` (w, p) -> (r, dr/dw), the exact Jacobian by forward mode through every step (six
  tangents), at -O0: ten times the code, which gcc -O1 takes minutes over; -O0 compiles in seconds and
  the Jacobian is needed rarely (below).

The cable-length mode (`crtraj.model.cosserat._cable_compiled`) reuses ``rod_shape`` (the same cache entry),
the forward-mode march (`tangent_march`, there with tangents in the tensions too), the loader (`load_pair`)
and the iteration.

The iteration (`chord_newton`): Newton's method on r(w) = 0 that keeps the Jacobian of the previous
solve (a warm start is near it), corrects it by Broyden's rank-one secant update after each step, and
takes residual-only steps while they contract (each step at least halves max |r|); when one does not,
or none is kept, it evaluates the exact Jacobian at the current point and continues with full Newton
steps, as CasADi's Newton rootfinder does. A chord converges linearly, so it does not stop at the
tolerance (the rootfinder's ``abstol``) but goes on to the rounding floor: it stops when max |r| <=
`POLISH` x the tolerance, or <= the tolerance and a step no longer halves it (or after max_iter steps).
Its answer is then as exact as a full Newton step's, which lands far below the tolerance: the same
root as the interpreted path's.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache, BuildKey
from crtraj.model.codegen import compiled_functions
from crtraj.model.cosserat._equations import RodPieces, march, rod_pieces
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

log = logging.getLogger(__name__)

# A residual-only step must shrink max |r| at least this much, or the Jacobian is re-evaluated.
CONTRACTION = 0.5
# Below this fraction of the tolerance the answer is at the rounding floor: stop without another step.
POLISH = 1e-3
# Bumped whenever the generated functions change meaning (the sources' hash is in the key too).
GENERATOR = 1
_SOURCES = ("_equations.py", "_compiled.py")


def _tangent(f: ca.Function, name: str, dp: ca.DM) -> ca.Function:
    """(y, D, p) -> (f's first output, its forward tangents along (D, dp)): y moves along D, p along the
    constant dp (zero: derivatives with respect to y only)."""
    y, p = f.sx_in(0), f.sx_in(1)
    D = ca.SX.sym("D", y.numel(), dp.shape[1])
    out = f.call([y, p])[0]
    return ca.Function(name, [y, D, p], [out, ca.jtimes(out, ca.vertcat(y, p), ca.vertcat(D, dp))])


def tangent_march(pieces: RodPieces, w: ca.MX, p: ca.MX, dp: ca.DM, prefix: str) -> tuple[Any, Any, Any, Any]:
    """Integrate from w to the tip in forward mode: (r, tip state y, dr, dy) with respect to
    (w, the directions dp (n_p x k) of p): 6 + k tangents through every step, jump and the tip."""
    steps = [_tangent(s, f"{prefix}_dstep{k}", dp) for k, s in enumerate(pieces.steps)]
    jumps = [_tangent(j, f"{prefix}_djump{k}", dp) for k, j in enumerate(pieces.jumps)]
    tip = _tangent(pieces.tip, f"{prefix}_dtip", dp)
    wi = pieces.init.sx_in(0)
    y0 = pieces.init.call([wi])[0]
    dy0 = ca.horzcat(ca.jacobian(y0, wi), ca.SX.zeros(y0.numel(), dp.shape[1] - 6))
    y, dy = ca.Function(f"{prefix}_dinit", [wi], [y0, dy0])(w)
    for k, step in enumerate(steps):
        for _ in range(pieces.n_steps):
            y, dy = step(y, dy, p)
        if k < len(jumps):
            y, dy = jumps[k](y, dy, p)
    r, dr = tip(y, dy, p)
    return r, y, dr, dy


def shape_function(pieces: RodPieces, nt: int) -> ca.Function:
    """rod_shape (w, p) -> (r, points, R_tip, turn, paths) as an MX graph calling the pieces."""
    w, p = ca.MX.sym("w", 6), ca.MX.sym("p", nt + 9)
    res, points, y, turn = march(pieces, w, p)
    outs = [res, points, ca.reshape(y[3:12], 3, 3), turn, y[18:]]
    return ca.Function("rod_shape", [w, p], outs, ["w", "p"], ["r", "points", "R_tip", "turn", "paths"])


def resjac_function(pieces: RodPieces, nt: int) -> ca.Function:
    """rod_resjac (w, p) -> (r, dr/dw): forward mode with six tangents through every step."""
    w, p = ca.MX.sym("w", 6), ca.MX.sym("p", nt + 9)
    r, _, dr, _ = tangent_march(pieces, w, p, ca.DM.zeros(nt + 9, 6), "rod")
    return ca.Function("rod_resjac", [w, p], [r, dr], ["w", "p"], ["r", "J"])


def build_key(
    name: str, robot: Robot, mech: Mechanics, flags: tuple[str, ...], extra: tuple[str, ...] = ()
) -> BuildKey:
    """Cache key: the robot's description, the stiffness and steps, the flags and the generating sources' hash
    (this package's `_SOURCES` and the `extra` files beside them)."""
    here = Path(__file__).resolve().parent
    digest = hashlib.sha256(b"".join((here / f).read_bytes() for f in (*_SOURCES, *extra))).hexdigest()
    robot_spec = {k: v for k, v in robot.to_dict().items() if k not in ("description", "actuators")}
    spec = {
        "robot": robot_spec,
        # what the generated code bakes in; loads, tolerances and masses are parameters or Python's
        "mechanics": {k: getattr(mech, k) for k in ("youngs_modulus", "shear_modulus", "backbone_radius", "steps")},
        "flags": list(flags),
        "generator": GENERATOR,
        "sources": digest,
    }
    return BuildKey(name, spec)


def load_pair(
    robot: Robot,
    mech: Mechanics,
    cache: BuildCache,
    jac_name: str,
    jac_function: Callable[[RodPieces, int], ca.Function],
    extra: tuple[str, ...] = (),
) -> tuple[ca.Function, ca.Function] | None:
    """(rod_shape at -O2, the Jacobian function `jac_name` = jac_function(pieces, nt) at -O0) from the build
    cache, generated and compiled on a miss; None without a C compiler. `extra`: further generating sources
    (beside this module) whose hash goes into the Jacobian's key."""
    if not cache.available():
        return None
    nt = 3 * robot.n_segments
    pieces: list[RodPieces] = []

    def made() -> RodPieces:  # built only on a miss, once for both libraries
        if not pieces:
            pieces.append(rod_pieces(robot, mech))
        return pieces[0]

    fast, slow = ("-O2",), ("-O0",)
    shape_key = build_key("crtraj_rod_shape", robot, mech, fast)
    jac_key = build_key(f"crtraj_{jac_name}", robot, mech, slow, extra)
    shape = compiled_functions(cache, shape_key, ["rod_shape"], lambda: [shape_function(made(), nt)], fast)
    jac = compiled_functions(cache, jac_key, [jac_name], lambda: [jac_function(made(), nt)], slow)
    if shape is None or jac is None:
        return None
    return shape["rod_shape"], jac[jac_name]


@dataclass(frozen=True)
class NewtonStats:
    """success: max |r| <= tolerance; iter_count: Newton steps taken; jacobians: exact Jacobians evaluated."""

    success: bool
    iter_count: int
    jacobians: int

    def as_dict(self) -> dict[str, Any]:
        return {"success": self.success, "iter_count": self.iter_count, "jacobians": self.jacobians}


class CompiledShooting:
    """The two compiled functions of one robot and the chord-Newton iteration on them."""

    def __init__(self, shape: ca.Function, resjac: ca.Function) -> None:
        self.shape, self.resjac = shape, resjac

    @classmethod
    def load(cls, robot: Robot, mech: Mechanics, cache: BuildCache) -> CompiledShooting | None:
        """From the build cache (generated and compiled on a miss); None without a C compiler."""
        pair = load_pair(robot, mech, cache, "rod_resjac", resjac_function)
        return None if pair is None else cls(*pair)

    def residual(self, w: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, list[Any]]:
        """r (6,) at w, and the shape outputs (points, R_tip, turn, paths)."""
        out = self.shape(w, p)
        return np.asarray(out[0]).ravel(), out[1:]

    def chord_newton(
        self,
        w0: np.ndarray,
        p: np.ndarray,
        jac: np.ndarray | None,
        tolerance: float,
        max_iter: int,
        polish: float = POLISH,
    ) -> tuple[np.ndarray, np.ndarray, list[Any], np.ndarray | None, NewtonStats]:
        """(w, r, shape outputs, Jacobian kept, stats) of the iteration from w0 (module docstring);
        `jac` is the Jacobian to start with (the last solve's) or None; `polish` (<= 1) replaces `POLISH`
        (1: stop as soon as max |r| <= tolerance, one residual evaluation fewer on a warm path)."""
        w = np.asarray(w0, dtype=float).copy()
        r, shape = self.residual(w, p)
        fresh, n_jac, it = False, 0, 0
        while it < max_iter:
            err = float(np.max(np.abs(r)))
            if not np.isfinite(err) or err <= polish * tolerance:
                break
            if jac is None or not np.all(np.isfinite(jac)):
                _, jac_dm = self.resjac(w, p)
                jac, fresh, n_jac = np.asarray(jac_dm), True, n_jac + 1
            try:
                w_new = w - np.linalg.solve(jac, r)
            except np.linalg.LinAlgError:
                break
            r_new, shape_new = self.residual(w_new, p)
            err_new = float(np.max(np.abs(r_new)))
            if not (err_new <= CONTRACTION * err):
                if err <= tolerance:  # at the rounding floor: done
                    break
                if not fresh:  # stale Jacobian: refresh it here and step again
                    jac = None
                    continue
            # Broyden's rank-one update: the secant along the step, so the chord converges superlinearly
            dw, dr = w_new - w, r_new - r
            jac = jac + np.outer(dr - jac @ dw, dw) / float(dw @ dw) if float(dw @ dw) > 0.0 else jac
            w, r, shape, fresh, it = w_new, r_new, shape_new, False, it + 1
        err = float(np.max(np.abs(r)))
        ok = bool(np.isfinite(err) and err <= tolerance)
        return w, r, shape, jac, NewtonStats(ok, it, n_jac)
