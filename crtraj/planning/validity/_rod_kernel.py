"""The compiled validity kernel of a rod model: `ValidityKernel` plus the rod's tips alone and PCC's tip Jacobians.

`ValidityKernel.tip_jacobian` of a rod model evaluates the tip polynomials and their gradient (15 sums over the
monomials on cdsr2); a caller that wants the tips only (`MotionValidator.tip_position`: path lengths, the
retiming's tips) pays for 3 of them here (`crtraj_rod_tips`, the same numbers). The safe IK's push-out moves along
the null space of a tip Jacobian and projects back onto the target after every step
(`crtraj.planning.ik.SafeIK.push_out`): any Jacobian near the rod's gives a direction, and PCC's costs a
fortieth of the rod's (`pcc_tip_jacobian`). Units: mm, rad.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.planning.validity._compiled import ValidityKernel, _ptr

_P = ctypes.c_void_p


class RodKernel(ValidityKernel):
    """A loaded rod-model kernel (`ValidityKernel.load` of a rod model; see the module docstring)."""

    def __init__(self, library: Path, nx: int, check_points: int) -> None:
        super().__init__(library, nx, check_points)
        self._rod_tips = ctypes.CDLL(str(library)).crtraj_rod_tips
        self._rod_tips.argtypes = [ctypes.c_longlong, _P, _P, _P]
        self._rod_tips.restype = ctypes.c_int

    def tip_positions(self, X: Any) -> np.ndarray:
        """The rod's tips (N, 3) mm of configurations X (N, nx): `tip_jacobian`'s, without the Jacobian."""
        X = self._configs(X)
        P = np.empty((len(X), 3))
        self._check(self._rod_tips(len(X), _ptr(X), _ptr(P), None), "rod tips")
        return P

    def pcc_tip_jacobian(self, X: Any) -> np.ndarray:
        """PCC's tip Jacobians d tip / d x (N, 3, nx) of configurations X (N, nx), contiguous like
        `tip_jacobian`'s."""
        X = self._configs(X)
        P = np.empty((len(X), 3))
        Jt = np.empty((len(X), self.nx, 3))  # column-major 3 x nx per configuration
        self._check(self._rod_tips(len(X), _ptr(X), _ptr(P), _ptr(Jt)), "PCC tip Jacobian")
        return np.ascontiguousarray(np.swapaxes(Jt, 1, 2))
