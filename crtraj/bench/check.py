"""The independent dense check: the only judge of a benchmark run's success (see `crtraj.bench.runner`).

It shares nothing with the planners' validity checker except the robot
model's points and the obstacle definition. Units mm, s.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.planning.result import PlanResult
from crtraj.world.geometry import exact_min_clearance
from crtraj.world.scene import Scene

# Dense samples are checked in chunks of this many (memory ~ chunk * points * obstacles * 24 bytes).
_CHUNK = 256
# A path may start this far (rad / mm, per entry) from the scenario's start configuration.
_START_TOL = 1e-6
# Limit violations below this count as round-off (same units as Robot.limit_violation).
_LIMIT_TOL = 1e-6


class CheckStatus(str, enum.Enum):
    """Verdict of the dense check."""

    VERIFIED = "verified"  # the path passes every test
    REJECTED = "rejected"  # it fails one (the check's `reason` says which)

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class DenseCheck:
    """Verdict of the independent dense check on one returned path.

    status: VERIFIED when the path passes every test (`is_success()`), else
    REJECTED. reason: why not ("" when verified).
    min_clearance: smallest body-surface to sphere-surface distance (mm).
    t_worst: when it occurs (s). length: tip travel (mm). goal_error: final
    tip to goal (mm). samples: dense samples checked.
    """

    status: CheckStatus
    reason: str
    min_clearance: float
    t_worst: float
    length: float
    goal_error: float
    samples: int

    def is_success(self) -> bool:
        return self.status is CheckStatus.VERIFIED


def _dense_samples(T: np.ndarray, X: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (S,), configurations (S, nx) and straight-motion index (S,) with n[i] steps on motion i."""
    K = len(T)
    if K == 1:
        return T.copy(), X.copy(), np.zeros(1, dtype=int)
    seg = np.repeat(np.arange(K - 1), n)
    starts = np.concatenate([[0], np.cumsum(n)[:-1]])
    tau = (np.arange(n.sum()) - np.repeat(starts, n)) / n[seg]
    times = np.concatenate([T[seg] + tau * (T[seg + 1] - T[seg]), T[-1:]])
    configs = np.concatenate([X[seg] + tau[:, None] * (X[seg + 1] - X[seg]), X[-1:]])
    return times, configs, np.concatenate([seg, [K - 2]])


def _dense_path(
    model: Model, T: np.ndarray, X: np.ndarray, n_points: int, dt: float, ds: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Dense (times, configurations, backbone points): consecutive samples at most dt apart in time
    and ds apart in every backbone point (refined until true, at most 4 passes, then kept as is)."""
    if len(T) == 1:
        return T.copy(), X.copy(), model.points(X, n_points)
    n = np.maximum(1, np.ceil(np.diff(T) / dt)).astype(int)
    for _ in range(4):
        times, configs, seg = _dense_samples(T, X, n)
        pts = model.points(configs, n_points)  # (S, n_points, 3)
        move = np.linalg.norm(np.diff(pts, axis=0), axis=-1).max(axis=-1)  # (S-1,), step k in motion seg[k]
        worst = np.zeros(len(n))
        np.maximum.at(worst, seg[:-1], move)
        factor = np.ceil(worst / ds).astype(int)
        if np.all(factor <= 1):
            break
        n = n * np.maximum(factor, 1)
    return times, configs, pts


def _clearance_and_length(
    model: Model, scene: Scene, times: np.ndarray, points: np.ndarray
) -> tuple[float, float, float]:
    """(smallest body-surface to sphere-surface distance (mm), when (s), tip travel (mm)) over dense samples.

    Each backbone chord is checked as a segment against every sphere at the sample's own time, and each
    backbone point against every other shape by brute force (`crtraj.world.geometry.exact_min_clearance`).
    """
    nan = float("nan")
    min_clr, t_worst = math.inf, nan
    length = 0.0
    prev_tip: np.ndarray | None = None
    body = model.robot.body_radius
    for a in range(0, len(times), _CHUNK):
        tc, pts = times[a : a + _CHUNK], points[a : a + _CHUNK]  # (C,), (C, n, 3)
        tips = pts[:, -1, :]
        steps = np.linalg.norm(np.diff(tips, axis=0), axis=-1).sum()
        if prev_tip is not None:
            steps += np.linalg.norm(tips[0] - prev_tip)
        length += float(steps)
        prev_tip = tips[-1]
        if scene.shapes:  # other shapes: brute-force distances to their triangles and points, at the points
            tt = tc + scene.time_origin
            d = np.min([exact_min_clearance(ms, pts, tt) for ms in scene.shapes], axis=0) - body
            i = int(np.argmin(d))
            if d[i] < min_clr:
                min_clr, t_worst = float(d[i]), float(tc[i])
        if scene.n_obstacles == 0:
            continue
        centers, radii = scene.states(tc)  # (C, M, 3), (C, M)
        A = pts[:, :-1, None, :]  # (C, n-1, 1, 3)
        AB = pts[:, 1:, None, :] - A
        AC = centers[:, None, :, :] - A  # (C, n-1, M, 3)
        den = np.maximum(np.einsum("...k,...k->...", AB, AB), 1e-300)
        u = np.clip(np.einsum("...k,...k->...", AC, AB) / den, 0.0, 1.0)
        dist = np.linalg.norm(AC - u[..., None] * AB, axis=-1)  # (C, n-1, M)
        clr = (dist.min(axis=1) - radii).min(axis=-1) - body  # (C,)
        i = int(np.argmin(clr))
        if clr[i] < min_clr:
            min_clr, t_worst = float(clr[i]), float(tc[i])
    return min_clr, t_worst, length


def dense_check(
    model: Model,
    scene: Scene,
    result: PlanResult,
    start: np.ndarray,
    goal: np.ndarray,
    *,
    goal_tolerance: float = 1.0,
    n_points: int = 128,
    dt: float = 0.01,
    step: float = 1.0,
    margin: float = 0.0,
    t0: float = 0.0,
) -> DenseCheck:
    """Check a returned path independently of any planner (module docstring)."""
    nan = float("nan")

    def fail(reason: str, clr: float = nan, tw: float = nan, length: float = nan, ge: float = nan, s: int = 0):
        return DenseCheck(CheckStatus.REJECTED, reason, clr, tw, length, ge, s)

    T = np.asarray(result.t, dtype=float).reshape(-1)
    X = np.asarray(result.configs, dtype=float)
    if len(T) == 0 or X.ndim != 2 or X.shape[0] != len(T) or X.shape[1] != model.nx:
        return fail(f"no usable path ({len(T)} times, configs of shape {X.shape})")
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(X))):
        return fail("path contains NaN or infinity")
    if np.any(np.diff(T) < 0.0):
        return fail("waypoint times decrease")
    if abs(T[0] - t0) > 1e-9:
        return fail(f"path starts at t = {T[0]:.6g} s, not at {t0:g} s")
    if np.max(np.abs(X[0] - np.asarray(start, dtype=float))) > _START_TOL:
        return fail("path does not start at the start configuration")
    times, configs, points = _dense_path(model, T, X, n_points, dt, step)
    limit = model.robot.limit_violation(configs)
    if np.max(limit) > _LIMIT_TOL:
        i = int(np.argmax(limit))
        return fail(f"out of the robot's limits at t = {times[i]:.3f} s (violation {limit[i]:.3g})", s=len(times))
    min_clr, t_worst, length = _clearance_and_length(model, scene, times, points)
    goal_error = float(np.linalg.norm(model.tip_position(X[-1]) - np.asarray(goal, dtype=float)))
    if min_clr <= margin:
        what = "collides with an obstacle" if min_clr <= 0.0 else f"comes within {margin:g} mm of an obstacle"
        return fail(
            f"{what} at t = {t_worst:.3f} s (clearance {min_clr:.3f} mm)",
            min_clr,
            t_worst,
            length,
            goal_error,
            len(times),
        )
    if goal_error > goal_tolerance + 1e-9:
        return fail(
            f"ends {goal_error:.3f} mm from the goal (tolerance {goal_tolerance:g} mm)",
            min_clr,
            t_worst,
            length,
            goal_error,
            len(times),
        )
    return DenseCheck(CheckStatus.VERIFIED, "", min_clr, t_worst, length, goal_error, len(times))


@dataclass(frozen=True)
class PaperCheck:
    """Verdict of the paper's own check (sec. IV-B) on one returned path, for comparison with `DenseCheck`.

    passed: the path reaches the goal and its collision points keep D_sf at every step end.
    clearance: smallest point clearance beyond D_sf over the step ends (mm). times: step ends checked.
    """

    passed: bool
    clearance: float
    times: int


def paper_check(
    model: Model,
    scene: Scene,
    result: PlanResult,
    goal: np.ndarray,
    *,
    goal_tolerance: float = 1.0,
    step: float = 1.0,
) -> PaperCheck:
    """The paper's check: at t = 0, step, 2 step, ... up to the arrival, and at the arrival itself, the
    robot's `collision_points` backbone points (discs of the body radius) keep D_sf from every sphere
    as it is at that time (mm, s). Written apart from `crtraj.planning.validity._paper_check` on purpose: the
    configurations come from interpolating the waypoints here, the distances from `Scene.states`."""
    T = np.asarray(result.t, dtype=float).reshape(-1)
    X = np.asarray(result.configs, dtype=float)
    if len(T) == 0 or X.ndim != 2 or X.shape[0] != len(T) or not np.all(np.isfinite(X)):
        return PaperCheck(False, float("nan"), 0)
    times = np.append(np.arange(0.0, T[-1], step), T[-1]) if T[-1] > 0 else T[-1:]
    configs = np.stack([np.interp(times, T, X[:, j]) for j in range(X.shape[1])], axis=-1)
    pts = model.points(configs, model.robot.collision_points)  # (S, n, 3)
    clr = math.inf
    if scene.n_obstacles:
        centers, radii = scene.states(times)  # (S, M, 3), (S, M)
        d = np.linalg.norm(pts[:, :, None, :] - centers[:, None, :, :], axis=-1)  # (S, n, M)
        clr = float((d - radii[:, None, :]).min()) - model.robot.body_radius - scene.safety_distance
    goal_error = float(np.linalg.norm(pts[-1, -1] - np.asarray(goal, dtype=float)))
    return PaperCheck(clr >= 0.0 and goal_error <= goal_tolerance + 1e-9, clr, len(times))
