"""Synthetic calibration data: a perturbed truth, workspace samples and simulated markers (mm, rad)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from crtraj.model.calibration._frames import rotation_matrix
from crtraj.model.calibration._layout import CalibrateOptions, Hardware, Layout
from crtraj.model.calibration._model import CalibrationModel
from crtraj.model.calibration._sites import MarkerSite
from crtraj.model.robot import Robot


def synthetic_values(robot: Robot, hw: Hardware, n: int, seed: int, *, planar_distal: bool = False) -> np.ndarray:
    """n actuator value samples (n, nq) spread over the workspace: random bending vectors within 60 % of
    each segment's theta_max (uniform over the disc), z over the middle of the stroke.
    planar_distal: keep the distal segment's cables at zero (its bending then comes only from offsets)."""
    rng = np.random.default_rng(seed)
    ns = robot.n_segments
    x = np.zeros((n, robot.nx))
    for k, seg in enumerate(robot.segments):
        if planar_distal and k == ns - 1:
            continue
        rad = 0.6 * seg.theta_max * np.sqrt(rng.random(n)) / max(1.0, 1.0 + abs(robot.coupling) * (ns - 1 - k))
        ang = rng.random(n) * 2 * math.pi
        x[:, 2 * k] = rad * np.cos(ang)
        x[:, 2 * k + 1] = rad * np.sin(ang)
    lo, hi = robot.z_range
    mid, half = (lo + hi) / 2, (hi - lo) / 4
    x[:, -1] = mid + half * (2 * rng.random(n) - 1)
    return servo_values(robot, hw, x)


def simulate_markers(
    robot: Robot,
    hw: Hardware,
    zero_offsets: np.ndarray,
    capture: np.ndarray,
    values: np.ndarray,
    sites: Sequence[MarkerSite],
    *,
    noise: float = 0.0,
    outliers: float = 0.0,
    outlier_size: float = 20.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic capture-frame marker positions (N, M, 3) mm of a robot with these true parameters, and
    the outlier mask (N, M).

    capture: (6,) true capture -> robot frame (rotation vector rad, translation mm). noise: standard
    deviation per axis (mm). outliers: fraction of marker observations displaced by a random vector of
    about outlier_size mm (a swapped or misidentified marker).
    """
    layout = Layout.build(robot, zero_offsets, capture, CalibrateOptions())
    cm = CalibrationModel(robot, hw, sites, layout)
    P = cm.predict(layout.prior, values)
    R = rotation_matrix(capture[:3])
    m = (P - capture[3:]) @ R  # p = R m + t  =>  m = R^T (p - t)
    rng = np.random.default_rng(seed)
    m = m + rng.normal(0.0, noise, m.shape)
    bad = rng.random(m.shape[:2]) < outliers
    m[bad] += rng.normal(0.0, outlier_size, (int(bad.sum()), 3))
    return m, bad


@dataclass(frozen=True)
class SyntheticTruth:
    """A robot perturbed from a nominal one, for synthetic calibration data: the true robot (lengths,
    coupling), the true zero offsets (nq,) and the true capture frame (6,) capture -> robot."""

    robot: Robot
    zero_offsets: np.ndarray
    capture: np.ndarray

    @property
    def theta(self) -> np.ndarray:
        """The true parameter vector in `Layout` order."""
        return Layout.build(self.robot, self.zero_offsets, self.capture, CalibrateOptions()).prior


def synthetic_truth(robot: Robot, zero_offsets: np.ndarray, seed: int = 0) -> SyntheticTruth:
    """The issue's synthetic ground truth: segment lengths +-5 %, coupling -0.8 (from -1), servo zero
    offsets uniform in +-0.05 rad, a capture frame rotated 10 degrees about a random axis and shifted
    50 mm in a random direction. Cable radius and the stage's zero offset stay nominal."""
    rng = np.random.default_rng(seed)
    segs = tuple(replace(s, length=s.length * (1 + 0.05 * rng.choice([-1.0, 1.0]))) for s in robot.segments)
    true_robot = replace(robot, segments=segs, coupling=-0.8)
    zo = np.asarray(zero_offsets, dtype=float).copy()
    zo[:-1] += rng.uniform(-0.05, 0.05, zo.size - 1)
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    cap = np.concatenate([math.radians(10) * axis / np.linalg.norm(axis), 50.0 * shift / np.linalg.norm(shift)])
    return SyntheticTruth(true_robot, zo, cap)


def synthetic_motion(robot: Robot, hw: Hardware, t: np.ndarray, seed: int) -> np.ndarray:
    """Actuator values (len(t), nq) of a smooth motion at times t (s): each bending vector component and the
    base a sum of three sinusoids (0.03 to 0.2 Hz, random phases), within 60 % of each segment's theta_max
    and the middle of the stroke. A record of it is a time series, as `crtraj record` writes one."""
    rng = np.random.default_rng(seed)
    ns = robot.n_segments
    x = np.zeros((t.size, robot.nx))

    def wave() -> np.ndarray:
        f = rng.uniform(0.03, 0.2, 3)
        ph = rng.uniform(0, 2 * math.pi, 3)
        return np.sum(np.sin(2 * math.pi * f[:, None] * t[None, :] + ph[:, None]), axis=0) / 3

    for k, seg in enumerate(robot.segments):
        amp = 0.6 * seg.theta_max / max(1.0, 1.0 + abs(robot.coupling) * (ns - 1 - k)) / math.sqrt(2)
        x[:, 2 * k] = amp * wave()
        x[:, 2 * k + 1] = amp * wave()
    lo, hi = robot.z_range
    x[:, -1] = (lo + hi) / 2 + (hi - lo) / 4 * wave()
    return servo_values(robot, hw, x)


def servo_values(robot: Robot, hw: Hardware, x: np.ndarray) -> np.ndarray:
    """The readings (rad for spools, mm for the stage) the servos give at configurations x (N, n_x)."""
    A, _ = robot.cable_matrix()
    dq = x @ A.T
    values = np.empty_like(dq)
    values[:, :-1] = hw.sign[:-1] * dq[:, :-1] / hw.spool_radius
    values[:, -1] = hw.sign[-1] * dq[:, -1]
    return values
