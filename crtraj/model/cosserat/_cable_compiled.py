"""The cable-length (displacement) mode of the Cosserat rod as generated C, solved by the chord Newton.

`crtraj.model.cosserat.CableDrivenRod` solves for z = (base wrench w, tendon tensions tau) with the
residual F(z) = (r(w, tau), c(z)): r the rod's tip residual, and per tendon c_i = P_i(w, tau) -
l_i (1 + tau_i / EA_t) when taut, c_i = tau_i when slack (the module docstring there). Interpreted, that
is CasADi's Newton rootfinder on one inlined SX graph. Here:

- F comes from the tension mode's compiled ``rod_shape`` (`crtraj.model.cosserat._compiled`; the very
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
from crtraj.model.cosserat._compiled import CompiledShooting, load_pair, tangent_march
from crtraj.model.cosserat._equations import RodPieces
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot


def cable_jac_function(pieces: RodPieces, nt: int) -> ca.Function:
    """cable_jac (w, p) -> (r, P, dr/dz, dP/dz) with z = (w, tau): 6 + nt forward tangents through every step."""
    dp = ca.DM.zeros(nt + 9, 6 + nt)
    dp[:nt, 6:] = ca.DM.eye(nt)  # the tensions are p's first nt entries; the loads do not move
    w, p = ca.MX.sym("w", 6), ca.MX.sym("p", nt + 9)
    r, y, dr, dy = tangent_march(pieces, w, p, dp, "cable")
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
        pair = load_pair(robot, mech, cache, "cable_jac", cable_jac_function, ("_cable_compiled.py",))
        return None if pair is None else cls(*pair, mech.tendon_stiffness, 3 * robot.n_segments)

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
