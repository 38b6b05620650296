"""Cable-displacement input for the Cosserat rod: commanded tendon lengths, slack tendons by an active set.

A servo does not set a tension; it sets how much tendon lies between the base disc and the tendon's end
disc: the commanded length l_i (mm, unstretched). Under tension tau_i the tendon stretches to
``l_i (1 + tau_i / EA_t)`` (EA_t: `Mechanics.tendon_stiffness`, N), and a taut tendon fills exactly its
path P_i through the deformed rod (`crtraj.model.cosserat._statics.build_shooting`'s ``paths``). A tendon
cannot push: when its path is shorter than l_i it is slack and carries no tension. So each tendon is
either taut (``P_i = l_i (1 + tau_i / EA_t)``, tau_i >= 0) or slack (tau_i = 0, P_i <= l_i).

Solved by an active-set iteration around one Newton rootfinder (built once) on the unknowns
(base wrench, tensions): start with every tendon taut; after each solve, release the taut tendons
whose tension came out negative and take up the slack tendons whose path came out longer than their
commanded length; stop when neither happens. The active set is a parameter of the rootfinder.
The rootfinder runs in generated C when a compiler is found (`crtraj.model.cosserat._cable_compiled`),
in CasADi's interpreter otherwise.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, check_array
from crtraj.core.interrupt import check as check_interrupt
from crtraj.model.cosserat._cable_compiled import CompiledCables
from crtraj.model.cosserat._statics import (
    NO_LOAD,
    RodLoad,
    RodSolution,
    RodStatics,
    build_shooting,
    load_vector,
    newton_options,
    solution_status,
    straight_guess,
)

log = logging.getLogger(__name__)

# Path length tolerance (mm) of the slack test: far below any servo's resolution.
SLACK_TOLERANCE = 1e-9


@dataclass(frozen=True)
class CableSolution:
    """A displacement-mode solve: the rod's shape, the tensions it took (N), each tendon's path (mm),
    which tendons went slack, and the active-set rounds used."""

    rod: RodSolution
    tensions: np.ndarray
    paths: np.ndarray
    slack: np.ndarray
    rounds: int

    def is_success(self) -> bool:
        return self.rod.is_success()


class CableDrivenRod(RodStatics):
    """Statics of one robot under commanded tendon lengths (mm), in the robot's cable order.

    compiled: evaluate the residual and its Jacobian in generated C through the build cache and solve
    with the chord Newton (`crtraj.model.cosserat._cable_compiled`; the first use per robot compiles for
    some seconds) when a C compiler is found; False, or no compiler: CasADi's Newton rootfinder in the
    interpreter. Same active set, same root to the tolerance. build_cache: where the libraries go.
    """

    def _setup(self) -> None:
        self._jac_taut: np.ndarray | None = None  # the active set the last Jacobian belongs to

    def _load_compiled(self, cache: BuildCache) -> CompiledCables:
        return CompiledCables.load_cables(self.robot, self.mech, cache)

    def _interpreted(self) -> ca.Function:
        """CasADi's Newton rootfinder on the inlined SX residual F(z; q), built on first use."""
        if self._newton is None:
            nt = self.n_tendons
            shooting = build_shooting(self.robot, self.mech)
            z = ca.SX.sym("z", 6 + nt)
            q = ca.SX.sym("q", 2 * nt + 9)
            lengths, taut, loads = q[:nt], q[nt : 2 * nt], q[2 * nt :]
            tau = z[6:]
            res, pts, R, _, turn, paths = shooting(z[:6], ca.vertcat(tau, loads))
            stretched = lengths * (1.0 + tau / self.mech.tendon_stiffness)
            cable = taut * (paths - stretched) + (1.0 - taut) * tau
            outs = [ca.vertcat(res, cable), pts, R, res, turn, paths]
            g = ca.Function("cable_shooting", [z, q], outs)
            self._newton = ca.rootfinder("cable_statics", "newton", g, newton_options(self.mech))
        return self._newton

    def solve(self, lengths: Any, load: RodLoad = NO_LOAD) -> CableSolution:
        """Shape and tensions under commanded tendon lengths (mm); warm-started from the last solve, and
        started again from the straight rod with every tendon taut when the warm start fails (a warm start
        from a pose with a slack tendon can lead Newton out of the rod's domain)."""
        check_interrupt()  # a safe point between rod solves (crtraj.core.interrupt)
        ell = check_array(np.asarray(lengths, dtype=float), "lengths", (self.n_tendons,), limit=MAX_LENGTH)
        bad = np.flatnonzero(ell <= 0)
        if bad.size:
            raise InputError(f"lengths[{bad[0]}]: must be > 0 mm, got {ell[bad[0]]}")
        loads = load_vector(self.mech, load)
        starts = [] if self._warm is None else [(self._warm, self._warm[6:] > 0.0)]
        starts.append((self._cold(loads), np.ones(self.n_tendons, dtype=bool)))
        for z, taut in starts:
            out = self._active_set(ell, loads, z, taut)
            if out.is_success():
                self._warm = np.concatenate([out.rod.base_force, out.rod.base_moment, out.tensions])
                return out
        log.info("cable-displacement solve failed: %s", out.rod.status)
        self._warm = None
        return out

    def _active_set(self, ell: np.ndarray, loads: np.ndarray, z: np.ndarray, taut: np.ndarray) -> CableSolution:
        """The active-set iteration (the module docstring) from unknowns z and taut set `taut`."""
        for rounds in range(1, 2 * self.n_tendons + 3):
            sol, z, paths = self._attempt(z, np.concatenate([ell, taut.astype(float), loads]))
            if not sol.is_success():
                break
            tau = z[6:]
            release = taut & (tau < 0.0)
            take_up = ~taut & (paths > ell + SLACK_TOLERANCE)
            if not release.any() and not take_up.any():
                return CableSolution(sol, np.where(taut, tau, 0.0), paths, ~taut, rounds)
            taut = (taut & ~release) | take_up
            # restart from the straight rod holding the kept tensions: the last base wrench balanced
            # tendons that pushed, and can be far from the new set's solution
            kept = np.where(taut, np.maximum(tau, 0.0), 0.0)
            z = np.concatenate([straight_guess(self.robot, kept, loads), kept])
        else:
            sol = _failed(sol, "active_set")
        nan = np.full(self.n_tendons, np.nan)
        return CableSolution(sol, nan, nan, np.zeros(self.n_tendons, dtype=bool), rounds)

    def _cold(self, loads: np.ndarray) -> np.ndarray:
        """The straight rod without tension under the loads."""
        zero = np.zeros(self.n_tendons)
        return np.concatenate([straight_guess(self.robot, zero, loads), zero])

    def _attempt(self, z0: np.ndarray, q: np.ndarray) -> tuple[RodSolution, np.ndarray, np.ndarray]:
        """One Newton run from z0 with the active set in q: compiled (chord Newton, starting from the last
        Jacobian when the active set is the last one's) or interpreted; the same root either way."""
        tol = self.mech.tolerance
        if self._compiled is not None:
            taut = q[self.n_tendons : 2 * self.n_tendons]
            same = self._jac_taut is not None and np.array_equal(taut, self._jac_taut)
            jac0 = self._jac if same else None
            z, res, shape, self._jac, stats = self._compiled.chord_newton(z0, q, jac0, tol, self.mech.max_iter)
            if not stats.success and jac0 is not None:  # the kept Jacobian led astray: again from z0 with a fresh one
                z, res, shape, self._jac, stats = self._compiled.chord_newton(z0, q, None, tol, self.mech.max_iter)
            self._jac_taut = taut.copy()
            pts, R, turn, paths = shape
            sol = solution_status(stats.as_dict(), z[:6], pts, R, res[:6], turn, tol)
            return sol, z, np.asarray(paths).ravel()
        newton = self._interpreted()
        z_dm, pts, R, res, turn, paths = newton(z0, q)
        z = np.asarray(z_dm).ravel()
        sol = solution_status(newton.stats(), z[:6], pts, R, res, turn, tol)
        return sol, z, np.asarray(paths).ravel()


def _failed(sol: RodSolution, status: str) -> RodSolution:
    """`sol` with `status` and no shape."""
    return RodSolution(
        status,
        np.full_like(sol.points, np.nan),
        sol.tip_rotation,
        sol.base_force,
        sol.base_moment,
        sol.residual,
        sol.iterations,
    )
