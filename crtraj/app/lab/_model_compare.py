"""Use case: how far is the PCC model from Cosserat-rod statics? (`crtraj model compare`).

For N random configurations within the robot's limits (seeded), the rod is driven to each PCC
configuration in the robot file's actuation mode (`crtraj.model.cosserat.RodDrive`, ``[robot.mechanics]
actuation``: the servos' commanded cable lengths, or the tensions that hold the PCC bending on a weightless
rod) and solved without and with gravity (`crtraj.model.cosserat._statics`). The mode is printed with the figures.
Reported per case: the tip discrepancy and the whole-body discrepancy (the largest distance between the two
backbones at the rod's integration nodes), each as RMS, 95th percentile and maximum over the configurations, in mm.
The plot (--plot, PNG, written atomically) shows the sorted discrepancies and the worst
configuration's two backbones.
"""

from __future__ import annotations

import argparse
import io
import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_bytes, check_output_file, check_outputs_not_inputs
from crtraj.io.problem import load_robot
from crtraj.model.cosserat import RodDrive, pcc_nodes, sample_within_limits
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

log = logging.getLogger(__name__)

MAX_SAMPLES = 100_000
# N in every tendon at the straight pose (the smallest tension of each segment), as the plant's
PRETENSION = 1.0


@dataclass(frozen=True)
class Spread:
    """RMS, 95th percentile and maximum of a set of distances (mm); NaN when the set is empty."""

    rms: float
    p95: float
    max: float

    @classmethod
    def of(cls, d: np.ndarray) -> Spread:
        if d.size == 0:
            return cls(float("nan"), float("nan"), float("nan"))
        return cls(float(np.sqrt(np.mean(d**2))), float(np.percentile(d, 95)), float(np.max(d)))

    def text(self) -> str:
        return f"RMS {self.rms:.3f}, p95 {self.p95:.3f}, max {self.max:.3f} mm"


@dataclass(frozen=True)
class Comparison:
    """PCC against the rod over `configs` (N, nx). Per configuration (NaN where the rod failed):
    tip and whole-body discrepancy (mm) without gravity (`*_free`) and with it (`*_gravity`).
    worst: (PCC points, rod points with gravity) of the configuration with the largest body error.
    actuation: the rod's actuation mode ("cable_length" or "tension")."""

    configs: np.ndarray
    tip_free: np.ndarray
    body_free: np.ndarray
    tip_gravity: np.ndarray
    body_gravity: np.ndarray
    worst: tuple[np.ndarray, np.ndarray] | None
    actuation: str

    @property
    def failures(self) -> int:
        """Configurations where a rod solve did not converge."""
        return int(np.sum(~np.isfinite(self.body_free) | ~np.isfinite(self.body_gravity)))

    def spread(self, name: str) -> Spread:
        d = np.asarray(getattr(self, name))
        return Spread.of(d[np.isfinite(d)])


def sample_configs(robot: Robot, n: int, rng: np.random.Generator) -> np.ndarray:
    """n configurations (n, nx) drawn uniformly from the configuration box, kept if within the limits."""
    return sample_within_limits(robot, n, rng)


def _distances(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(tip distance, largest node distance) of two backbones (mm)."""
    d = np.linalg.norm(a - b, axis=1)
    return float(d[-1]), float(np.max(d))


def compare_models(robot: Robot, mech: Mechanics, configs: np.ndarray) -> Comparison:
    """PCC against Cosserat-rod statics at each configuration, in `mech`'s actuation mode (the module docstring)."""
    model = Model(robot)
    free_rod = RodDrive(robot, mech, pretension=PRETENSION, gravity=False)
    heavy_rod = RodDrive(robot, mech, pretension=PRETENSION, gravity=True)
    n = len(configs)
    res = np.full((4, n), np.nan)
    worst: tuple[np.ndarray, np.ndarray] | None = None
    worst_body = -1.0
    for i, x in enumerate(configs):
        at_origin = np.array(x, dtype=float)
        at_origin[-1] = 0.0  # pcc_nodes puts the base at the origin: so does the rod
        pcc = pcc_nodes(model, x, mech.steps)
        free, heavy = free_rod.shape_config(at_origin), heavy_rod.shape_config(at_origin)
        if free.is_success():
            res[0, i], res[1, i] = _distances(free.points, pcc)
        if heavy.is_success():
            res[2, i], res[3, i] = _distances(heavy.points, pcc)
            if res[3, i] > worst_body:
                worst, worst_body = (pcc, heavy.points), res[3, i]
    return Comparison(np.asarray(configs), res[0], res[1], res[2], res[3], worst, mech.actuation)


def plot_comparison(cmp: Comparison, robot: Robot, path: str | os.PathLike[str]) -> Path:
    """PNG: sorted tip and body discrepancies with and without gravity; the worst case's backbones."""
    fig = Figure(figsize=(10.0, 4.4), dpi=110)
    ax1, ax2 = fig.subplots(1, 2)
    rank = np.arange(1, len(cmp.configs) + 1)
    for name, label, style in (
        ("tip_free", "tip, no gravity", "C0--"),
        ("body_free", "body, no gravity", "C0-"),
        ("tip_gravity", "tip, gravity", "C3--"),
        ("body_gravity", "body, gravity", "C3-"),
    ):
        ax1.semilogy(rank, np.maximum(np.sort(getattr(cmp, name)), 1e-6), style, label=label)
    ax1.set_xlabel("configurations, sorted")
    ax1.set_ylabel("PCC - rod distance (mm)")
    ax1.grid(alpha=0.3, which="both")
    ax1.legend(fontsize=8)
    if cmp.worst is not None:
        pcc, rod = cmp.worst
        ax2.plot(pcc[:, 0], pcc[:, 2], "C0.-", label="PCC")
        ax2.plot(rod[:, 0], rod[:, 2], "C3.-", label="Cosserat rod, gravity")
        ax2.set_aspect("equal", adjustable="datalim")
        ax2.set_xlabel("x (mm)")
        ax2.set_ylabel("z (mm, from the base)")
        ax2.legend(fontsize=8)
    ax2.set_title("largest body discrepancy", fontsize=9)
    ax2.grid(alpha=0.3)
    fig.suptitle(
        f"{robot.name}: PCC against Cosserat-rod statics (actuation {cmp.actuation}), "
        f"{len(cmp.configs)} configurations",
        fontsize=10,
    )
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return atomic_write_bytes(path, buf.getvalue())


def model_compare_command(args: argparse.Namespace) -> int:
    """`crtraj model compare ROBOT ...` (arguments from `crtraj.cli`); returns the exit code."""
    if not 1 <= args.samples <= MAX_SAMPLES:
        raise InputError(f"--samples: must be in [1, {MAX_SAMPLES}], got {args.samples}")
    if args.seed < 0:
        raise InputError(f"--seed: must be >= 0, got {args.seed}")
    if args.plot is not None:
        check_outputs_not_inputs({"--plot": args.plot}, {"ROBOT": args.robot})
        check_output_file(args.plot, "--plot")
    robot = load_robot(args.robot)
    mech = Mechanics.from_robot(robot)
    configs = sample_configs(robot, args.samples, np.random.default_rng(args.seed))
    cmp = compare_models(robot, mech, configs)
    print(
        f"robot '{robot.name}': PCC against Cosserat rod (actuation {cmp.actuation}), {len(configs)} configurations "
        f"(seed {args.seed})"
    )
    print(f"  no gravity: tip {cmp.spread('tip_free').text()}; body {cmp.spread('body_free').text()}")
    print(f"  gravity:    tip {cmp.spread('tip_gravity').text()}; body {cmp.spread('body_gravity').text()}")
    if cmp.failures:
        print(f"  rod solves that did not converge: {cmp.failures} configurations (left out)")
    if args.plot is not None:
        print(f"  plot: {plot_comparison(cmp, robot, args.plot)}")
    if cmp.failures == len(configs):
        print(
            f"crtraj: model compare failed: no rod solve converged ({cmp.failures} configurations); check "
            f"[robot.mechanics] in {args.robot}: youngs_modulus {mech.youngs_modulus:g} MPa (too soft to carry "
            "the robot's weight?), tolerance, max_iter",
            file=sys.stderr,
        )
        return 1
    return 0
