"""The calibration's excitation motion: a smooth path that covers the workspace within the robot's limits.

Each segment's commanded bending vector traces a rosette, ``u_k(s) = A_k e(s) (cos 2 pi f_k s,
sin 2 pi f_k s)`` with coprime turn counts f_k (so every relative orientation of the segments occurs), the
base sweeps its stroke, and the envelope ``e(s) = sin^2(pi s)`` starts and ends the path at rest in the
straight pose. The amplitudes keep every effective bending angle within `fraction` of its theta_max
through the coupling (|u_bar_k| <= sum_j |c|^(j-k) A_j). The path is geometric (s in [0, 1]); the caller
times it within the actuators' speed and acceleration limits, and admission verifies it like any motion.
Units: rad, mm.
"""

from __future__ import annotations

import math

import numpy as np

from crtraj.core.errors import InputError
from crtraj.model.robot import Robot

TURNS = (3, 5, 7, 11, 13, 17, 19, 23)  # rosette turns per segment (coprime)
MAX_POINTS = 100_000


def excitation_path(
    robot: Robot, n: int = 2000, fraction: float = 0.7, z_turns: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """(s (n,), configurations (n, nx)) of the excitation path; see the module docstring."""
    if not 10 <= n <= MAX_POINTS:
        raise InputError(f"excitation points: must be in [10, {MAX_POINTS}], got {n}")
    if not 0 < fraction < 1:
        raise InputError(f"excitation fraction: must be in (0, 1), got {fraction}")
    ns = robot.n_segments
    s = np.linspace(0.0, 1.0, n)
    env = np.sin(math.pi * s) ** 2
    c = abs(robot.coupling)
    x = np.zeros((n, robot.nx))
    for k, seg in enumerate(robot.segments):
        # |u_bar_k| <= A (1 + c + c^2 + ...) over the segments from k on: share the bend limit equally
        gain = sum(c**j for j in range(ns - k))
        tmax = min(seg.theta_max, robot.cable_stroke(k) / robot.cable_radius)
        amp = fraction * tmax / (gain * ns) * (ns - k) if ns > 1 else fraction * tmax
        amp = min(amp, fraction * tmax / gain)
        f = TURNS[k % len(TURNS)]
        x[:, 2 * k] = amp * env * np.cos(2 * math.pi * f * s)
        x[:, 2 * k + 1] = amp * env * np.sin(2 * math.pi * f * s)
    lo, hi = robot.z_range
    z0 = robot.straight()[-1]
    half = fraction * min(z0 - lo, hi - z0, (hi - lo) / 2)
    x[:, -1] = z0 + half * np.sin(math.pi * s) * np.sin(2 * math.pi * z_turns * s)
    return s, x
