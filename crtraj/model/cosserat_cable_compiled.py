"""The cable-length (displacement) mode of the Cosserat rod as generated C, solved by the chord Newton.

`crtraj.model.cosserat_cables.CableDrivenRod` solves for z = (base wrench w, tendon tensions tau) with the
residual F(z) = (r(w, tau), c(z)): r the rod's tip residual, and per tendon c_i = P_i(w, tau) -
l_i (1 + tau_i / EA_t) when taut, c_i = tau_i when slack (the module docstring there). Interpreted, that
is CasADi's Newton rootfinder on one inlined SX graph. Here:

- F comes from the tension mode's compiled ``rod_shape`` (`crtraj.model.cosserat_compiled`; the very
  library, same cache entry): it gives r and the paths P at (w, p = (tau, loads)), and c is a few numpy
  operations on them;
- the exact Jacobian dF/dz comes from a second library, ``cable_jac`` (w, p) -> (r, P, dr/d(w, tau),
  dP/d(w, tau)): forward mode with 6 + n_tendons tangents through every RK4 step and disc (-O0, as the
  tension mode's Jacobian, for the same compile-time reason), the c rows assembled in numpy;
- the iteration is `CompiledShooting.chord_newton` on z, unchanged (warm Jacobian kept between solves
  with the same active set, Broyden updates, exact Jacobian when a step does not contract).

The active set (which tendons are taut) stays a parameter, as in the interpreted path: the slack and
complementarity handling is the one `CableDrivenRod` documents, whichever path evaluates F.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache
from crtraj.model.codegen import compiled_functions
from crtraj.model.cosserat_compiled import CompiledShooting, build_key, shape_function
from crtraj.model.cosserat_rod import RodPieces, rod_pieces
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot


def _tangent(f: ca.Function, name: str, dp: ca.DM) -> ca.Function:
    """(y, D, p) -> (f's first output, its forward tangents along (D, dp)): y moves along D, p along the constant dp."""
    y, p = f.sx_in(0), f.sx_in(1)
    D = ca.SX.sym("D", y.numel(), dp.shape[1])
    out = f.call([y, p])[0]
    return ca.Function(name, [y, D, p], [out, ca.jtimes(out, ca.vertcat(y, p), ca.vertcat(D, dp))])


def cable_jac_function(pieces: RodPieces, nt: int) -> ca.Function:
    """cable_jac (w, p) -> (r, P, dr/dz, dP/dz) with z = (w, tau): 6 + nt forward tangents through every step."""
    nz = 6 + nt
    dp = ca.DM.zeros(nt + 9, nz)
    dp[:nt, 6:] = ca.DM.eye(nt)  # the tensions are p's first nt entries; the loads do not move
    w, p = ca.MX.sym("w", 6), ca.MX.sym("p", nt + 9)
    steps = [_tangent(s, f"cable_dstep{k}", dp) for k, s in enumerate(pieces.steps)]
    jumps = [_tangent(j, f"cable_djump{k}", dp) for k, j in enumerate(pieces.jumps)]
    tip = _tangent(pieces.tip, "cable_dtip", dp)
    wi = pieces.init.sx_in(0)
    y0 = pieces.init.call([wi])[0]
    init = ca.Function("cable_dinit", [wi], [y0, ca.horzcat(ca.jacobian(y0, wi), ca.SX.zeros(y0.numel(), nt))])
    y, dy = init(w)
    for k, step in enumerate(steps):
        for _ in range(pieces.n_steps):
            y, dy = step(y, dy, p)
        if k < len(jumps):
            y, dy = jumps[k](y, dy, p)
    r, dr = tip(y, dy, p)
    outs = [r, y[18:], dr, dy[18:, :]]
    return ca.Function("cable_jac", [w, p], outs, ["w", "p"], ["r", "paths", "dr", "dpaths"])


class CompiledCables(CompiledShooting):
    """F(z; q) and dF/dz of the cable-length mode on the compiled libraries, q = (lengths, taut, loads);
    `chord_newton` (inherited) then solves F = 0 for z = (w, tau)."""

    def __init__(self, shape: ca.Function, jac: ca.Function, tendon_stiffness: float, nt: int) -> None:
        # not CompiledShooting.__init__: `resjac` is a method here, assembling dF/dz around `jac`
        self.shape, self._jac = shape, jac
        self.stiffness, self.nt = float(tendon_stiffness), nt

    @classmethod
    def load_cables(cls, robot: Robot, mech: Mechanics, cache: BuildCache) -> CompiledCables | None:
        """From the build cache (generated and compiled on a miss); None without a C compiler."""
        if not cache.available():
            return None
        nt = 3 * robot.n_segments
        pieces: list[RodPieces] = []

        def made() -> RodPieces:  # built only on a miss, once for both libraries
            if not pieces:
                pieces.append(rod_pieces(robot, mech))
            return pieces[0]

        fast, slow = ("-O2",), ("-O0",)
        shape_key = build_key("crtraj_rod_shape", robot, mech, fast)  # the tension mode's library
        jac_key = build_key("crtraj_cable_jac", robot, mech, slow, extra=("cosserat_cable_compiled.py",))
        shape = compiled_functions(cache, shape_key, ["rod_shape"], lambda: [shape_function(made(), nt)], fast)
        jac = compiled_functions(cache, jac_key, ["cable_jac"], lambda: [cable_jac_function(made(), nt)], slow)
        if shape is None or jac is None:
            return None
        return cls(shape["rod_shape"], jac["cable_jac"], mech.tendon_stiffness, nt)

    def _split(self, z: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        nt = self.nt
        return z[6:], q[:nt], q[nt : 2 * nt], np.concatenate([z[6:], q[2 * nt :]])

    def residual(self, w: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, list[Any]]:
        """F (6 + nt,) at z = w, q = p, and the shape outputs (points, R_tip, turn, paths)."""
        tau, ell, taut, rod_p = self._split(w, p)
        out = self.shape(w[:6], rod_p)
        paths = np.asarray(out[4]).ravel()
        cable = taut * (paths - ell * (1.0 + tau / self.stiffness)) + (1.0 - taut) * tau
        return np.concatenate([np.asarray(out[0]).ravel(), cable]), out[1:]

    def jacobian(self, z: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, dF/dz) at z, exact (forward mode through the compiled steps)."""
        tau, ell, taut, rod_p = self._split(z, q)
        r, paths, dr, dpaths = (np.asarray(x) for x in self._jac(z[:6], rod_p))
        paths = paths.ravel()
        cable = taut * (paths - ell * (1.0 + tau / self.stiffness)) + (1.0 - taut) * tau
        dcable = taut[:, None] * dpaths
        dcable[:, 6:] += np.diag(taut * (-ell / self.stiffness) + (1.0 - taut))
        return np.concatenate([r.ravel(), cable]), np.vstack([dr, dcable])

    def resjac(self, w: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # type: ignore[override]
        """What `chord_newton` calls for the exact Jacobian."""
        return self.jacobian(w, p)
