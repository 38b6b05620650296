"""The parameter vector of a calibration: options, the known hardware constants and the layout (mm, rad)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from crtraj.core.options import Options, option
from crtraj.model.robot import Robot


@dataclass(frozen=True)
class CalibrateOptions(Options):
    """The ``[calibrate]`` section. loss_scale: pseudo-Huber delta (mm): residuals beyond it pull with a
    bounded force. holdout: fraction of samples kept out of the fit to test it. seed: the split's seed.
    max_iter: IPOPT iterations. tol: IPOPT's tolerance. identifiability_tol: smallest relative part of a
    parameter's (unit) Jacobian column outside the span of the columns before it. length_bound,
    radius_bound: largest relative change of a segment length and of the cable radius.
    hessian: "gauss-newton" (robust-weighted J^T J of the exact residual Jacobians) or "exact". coupling_bound:
    largest |c - prior|. offset_bound: largest |zero offset - prior| (rad). base_z_bound: mm."""

    SECTION: ClassVar[str] = "calibrate"

    loss_scale: float = option(1.0, gt=0.0, le=1000.0)
    holdout: float = option(0.2, ge=0.0, le=0.9)
    seed: int = option(0, ge=0, le=2**31 - 1)
    max_iter: int = option(200, ge=1, le=10_000)
    tol: float = option(1e-10, gt=0.0, le=1.0)
    identifiability_tol: float = option(1e-6, gt=0.0, lt=1.0)
    length_bound: float = option(0.3, gt=0.0, lt=1.0)
    radius_bound: float = option(0.5, gt=0.0, lt=1.0)
    coupling_bound: float = option(1.0, gt=0.0, le=10.0)
    offset_bound: float = option(0.5, gt=0.0, le=math.pi)
    base_z_bound: float = option(100.0, gt=0.0, le=1e4)
    hessian: str = option("gauss-newton", choices=("gauss-newton", "exact"))


@dataclass(frozen=True)
class Hardware:
    """The known actuator constants (not fitted): spool radii (3n,) mm, signs (nq,) +-1."""

    spool_radius: np.ndarray
    sign: np.ndarray


@dataclass(frozen=True)
class Layout:
    """Names, groups, units, priors and bounds of the parameter vector theta (see the module docstring)."""

    n_segments: int
    actuator_names: tuple[str, ...]
    names: tuple[str, ...]
    groups: tuple[str, ...]
    units: tuple[str, ...]
    prior: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    scale: np.ndarray  # typical size of a parameter's change, for the solver's variable scaling

    @property
    def n(self) -> int:
        return len(self.names)

    def index(self, group: str) -> np.ndarray:
        """Positions of the parameters of `group`."""
        return np.array([i for i, g in enumerate(self.groups) if g == group], dtype=int)

    @classmethod
    def build(
        cls,
        robot: Robot,
        zero_offsets: np.ndarray,
        capture: np.ndarray,
        options: CalibrateOptions,
    ) -> Layout:
        """The layout of `robot` with its current values as prior. zero_offsets: (nq,) the actuators' zero
        offsets (rad, the stage's in mm last). capture: (6,) rotation vector (rad) and translation (mm)."""
        n = robot.n_segments
        act = tuple(f"s{k + 1}c{i + 1}" for k in range(n) for i in range(3))
        names: list[str] = []
        groups: list[str] = []
        units: list[str] = []
        prior: list[float] = []
        lo: list[float] = []
        hi: list[float] = []
        sc: list[float] = []

        def add(name: str, group: str, unit: str, value: float, low: float, high: float, s: float) -> None:
            names.append(name)
            groups.append(group)
            units.append(unit)
            prior.append(float(value))
            lo.append(float(low))
            hi.append(float(high))
            sc.append(s)

        o = options
        for k, seg in enumerate(robot.segments):
            L = seg.length
            add(f"segment[{k}].length", "lengths", "mm", L, L * (1 - o.length_bound), L * (1 + o.length_bound), 1.0)
        c = robot.coupling
        add("coupling", "coupling", "", c, c - o.coupling_bound, c + o.coupling_bound, 0.01)
        r = robot.cable_radius
        add("cable_radius", "cable_radius", "mm", r, r * (1 - o.radius_bound), r * (1 + o.radius_bound), 0.01)
        for i, a in enumerate(act):
            a0 = float(zero_offsets[i])
            add(f"{a}.zero_offset", "zero_offsets", "rad", a0, a0 - o.offset_bound, a0 + o.offset_bound, 1e-3)
        z0 = float(zero_offsets[-1])
        add("z.zero_offset", "base_z", "mm", z0, z0 - o.base_z_bound, z0 + o.base_z_bound, 1.0)
        for j, ax in enumerate("xyz"):
            add(f"capture.rotation_{ax}", "capture_frame", "rad", capture[j], -2 * math.pi, 2 * math.pi, 1e-3)
        for j, ax in enumerate("xyz"):
            add(f"capture.translation_{ax}", "capture_frame", "mm", capture[3 + j], -1e5, 1e5, 1.0)
        return cls(
            n,
            (*act, "z"),
            tuple(names),
            tuple(groups),
            tuple(units),
            np.array(prior),
            np.array(lo),
            np.array(hi),
            np.array(sc),
        )
