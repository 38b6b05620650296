"""What the page shows beside the scene, per waypoint: clearances, closest approach, tip error, timing, events.

`build_timeline` reads a validated `Result` (and the per-waypoint fields its document records: step status, tip
error, iteration time) and measures the rest from the recorded configurations with the robot's model: the
clearance of the body to each obstacle (distance to the sphere's surface minus the body radius and D_sf, as the
loop defines it), then to each of the scene's other shapes (the true distance to its surface), and where the closest
approach is: its line ends on the nearest obstacle's surface. Lengths in mm, times in s.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from crtraj.io.results import Result
from crtraj.model.kinematics import Model
from crtraj.world.geometry import MovingShape, nearest_surface_points

# backbone points measured per configuration for the clearance (4 mm apart on a 400 mm robot: the distance to a
# sphere of 20 mm radius or more is then within 0.1 mm)
CLEARANCE_POINTS = 101
# step statuses that are events on the time axis (the others, move and suboptimal, are the normal case)
EVENT_STATUSES = ("fallback", "hold", "unsafe", "stale", "estop")


@dataclasses.dataclass(frozen=True)
class Event:
    """One marker on the time axis: kind (replan, hold, fallback, deadline, estop, dropout, ...) at t (s)."""

    kind: str
    t: float
    text: str


@dataclasses.dataclass(frozen=True)
class Timeline:
    """Per-waypoint numbers of a run (N waypoints, m obstacles); NaN where the result records none.

    t (N,) s from the first waypoint. status (N,) step status ("" where none). clearance (N, m + k) mm to each
    sphere obstacle, then each of the k other shapes (negative: closer than D_sf). near (N,) column of the
    nearest (-1 without obstacles).
    body_point, obstacle_point (N, 3) mm: the closest pair between the body's surface and the nearest obstacle.
    tip_error (N,) mm. iteration (N,) s per loop iteration; deadline s (NaN: none). velocity, acceleration
    (N,) largest actuator fraction of its limit. safety_distance D_sf mm. events: markers on the time axis.
    """

    t: np.ndarray
    status: tuple[str, ...]
    clearance: np.ndarray
    near: np.ndarray
    body_point: np.ndarray
    obstacle_point: np.ndarray
    tip_error: np.ndarray
    iteration: np.ndarray
    deadline: float
    velocity: np.ndarray
    acceleration: np.ndarray
    safety_distance: float
    events: tuple[Event, ...]

    @property
    def closest_index(self) -> int:
        """The waypoint where the body came closest to any obstacle (0 without obstacles)."""
        if self.clearance.shape[1] == 0:
            return 0
        return int(np.nanargmin(np.nanmin(self.clearance, axis=1)))


def closest_approach(
    model: Model,
    x: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    safety: float,
    shapes: Sequence[MovingShape] = (),
    t: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Clearance (N, m + k) mm of configurations x (N, nx) to spheres (N, m, 3)/(N, m) and then to the `shapes`
    (k, each at the times t (N,) s, absolute), the nearest obstacle (N,) (a column of the clearance), and the
    closest points (N, 3) mm on the body's surface and on that obstacle's surface (a shape's nearest surface
    point, `crtraj.world.geometry.nearest_surface_points`)."""
    n, m = x.shape[0], centers.shape[1]
    P = np.asarray(model.points(x, CLEARANCE_POINTS)).reshape(n, -1, 3)
    if m + len(shapes) == 0:
        nan = np.full((n, 3), np.nan)
        return np.zeros((n, 0)), np.full(n, -1), nan, nan.copy()
    body = model.robot.body_radius
    rows = np.arange(n)
    columns, pairs = [], []  # per obstacle: clearance (N,), and (backbone point, surface point) (N, 3) each
    if m:
        d = np.linalg.norm(P[:, :, None, :] - centers[:, None, :, :], axis=-1)  # (N, P, m)
        gap = d - radii[:, None, :]  # backbone point to sphere surface
        k = np.argmin(gap, axis=1)  # (N, m): the backbone point closest to each sphere
        for j in range(m):
            p, c, r = P[rows, k[:, j]], centers[:, j], radii[:, j]
            u = c - p  # toward the centre: the sphere's surface point nearest p is c - r u
            u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            columns.append(gap[rows, k[:, j], j])
            pairs.append((p, c - r[:, None] * u))
    times = np.zeros(n) if t is None else np.asarray(t, dtype=float)
    for ms in shapes:
        gap, q = _shape_gaps(ms, P, times)
        k = np.argmin(gap, axis=1)
        columns.append(gap[rows, k])
        pairs.append((P[rows, k], q[rows, k]))
    gaps = np.stack(columns, axis=1)
    clearance = gaps - body - safety
    near = np.argmin(clearance, axis=1)
    p = np.stack([pr[0] for pr in pairs])[near, rows]
    q = np.stack([pr[1] for pr in pairs])[near, rows]
    # the body's surface point toward the obstacle: toward its surface point from outside, away from it from
    # inside (a sphere's: toward its centre either way)
    u = (q - p) * np.where(gaps[rows, near] < 0.0, -1.0, 1.0)[:, None]
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    return clearance, near, p + body * u, q


def _shape_gaps(ms: MovingShape, P: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distances (N, P) mm, nearest surface points (N, P, 3) mm) of backbone points P (N, P, 3) to the shape,
    row i at time t[i] (s); a shape that neither moves nor breathes at once."""
    n, k = P.shape[:2]
    if ms.static:
        d, q = nearest_surface_points(ms, P.reshape(-1, 3), 0.0)
        return d.reshape(n, k), q.reshape(n, k, 3)
    d, q = np.empty((n, k)), np.empty((n, k, 3))
    for i in range(n):
        d[i], q[i] = nearest_surface_points(ms, P[i], float(t[i]))
    return d, q


def _waypoint_field(doc: Mapping[str, Any], name: str, n: int) -> np.ndarray:
    """A numeric per-waypoint field of the document (NaN where a waypoint has none)."""
    wps = doc.get("waypoints") or []
    out = np.full(n, np.nan)
    for i, w in enumerate(wps[:n]):
        v = w.get(name) if isinstance(w, Mapping) else None
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            out[i] = float(v)
    return out


def _statuses(doc: Mapping[str, Any], n: int) -> tuple[str, ...]:
    wps = doc.get("waypoints") or []
    out = [""] * n
    for i, w in enumerate(wps[:n]):
        s = w.get("status") if isinstance(w, Mapping) else None
        out[i] = str(s)[:20] if s is not None else ""
    return tuple(out)


def _fractions(run: Result, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest |velocity| and |acceleration| fraction of the actuator limits, sampled at times t (s)."""
    limits = run.robot.actuator_limits()
    nan = np.full(len(t), np.nan)
    if limits is None:
        return nan, nan.copy()
    if run.executed is not None:
        t0, period, q = run.executed
        ts = t0 + period * np.arange(len(q)) - run.t[0]
    elif run.q is not None:
        ts, q = t, run.q
    else:
        return nan, nan.copy()
    if len(q) < 3:
        return nan, nan.copy()
    _, rest = run.robot.cable_matrix()
    values = limits.command(np.asarray(q, dtype=float), np.asarray(rest, dtype=float))
    dt = np.maximum(np.diff(ts), 1e-9)
    V = np.diff(values, axis=0) / dt[:, None]
    A = np.diff(V, axis=0) / dt[1:, None]
    vf = np.max(np.abs(V) / limits.vmax, axis=1)
    af = np.max(np.abs(A) / limits.amax, axis=1)
    return _window_max(ts[1:], vf, t), _window_max(ts[2:], af, t)


def _window_max(ts: np.ndarray, f: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The largest f over the samples (times ts) of each step (t[k-1], t[k]] (the first: up to t[0]); where a step
    holds no sample, f interpolated at t[k]."""
    out = np.interp(t, ts, f)
    hi = np.searchsorted(ts, t, side="right")
    lo = np.concatenate([[0], hi[:-1]])
    full = hi > lo
    if full.any():
        # consecutive windows: reduceat from each non-empty window's start runs to the next one's start
        out[full] = np.maximum.reduceat(f[: hi[-1]], lo[full])
    return out


def _events(doc: Mapping[str, Any], t: np.ndarray, status: tuple[str, ...], iteration: np.ndarray, deadline: float):
    """Replans, status changes into an abnormal step, deadline misses and feed events, in time order."""
    out: list[Event] = []
    t0 = float(t[0]) if len(t) else 0.0
    for ref in doc.get("references") or []:
        if isinstance(ref, Mapping) and isinstance(ref.get("t"), (int, float)) and ref.get("step", 0):
            out.append(Event("replan", float(ref["t"]) - t0, f"new reference at step {ref.get('step')}"))
    for i, s in enumerate(status):
        if s in EVENT_STATUSES and (i == 0 or status[i - 1] != s):
            out.append(Event("dropout" if s == "stale" else s, float(t[i]), f"step status {s}"))
        if math.isfinite(deadline) and iteration[i] > deadline:
            out.append(Event("deadline", float(t[i]), f"iteration {iteration[i] * 1e3:.1f} ms > {deadline * 1e3:g} ms"))
    feed = doc.get("feed")
    for e in feed.get("events", []) if isinstance(feed, Mapping) else []:
        if isinstance(e, Mapping) and isinstance(e.get("t"), (int, float)):
            out.append(Event("dropout", float(e["t"]) - t0, str(e.get("kind", e.get("reason", "feed event")))[:60]))
    return tuple(sorted(out, key=lambda e: e.t))


def build_timeline(run: Result, model: Model) -> Timeline:
    """The page's per-waypoint numbers of `run` (a validated result drawn with `model`)."""
    doc = run.data
    n = len(run.t)
    t = run.t - run.t[0]
    safety = run.scene.safety_distance if run.scene is not None else 0.0
    shapes = run.scene.shapes if run.scene is not None else ()
    origin = run.scene.time_origin if run.scene is not None else 0.0
    clearance, near, body_point, obstacle_point = closest_approach(
        model, run.x, run.centers, run.radii, safety, shapes, run.t + origin
    )
    summary = doc.get("summary") if isinstance(doc.get("summary"), Mapping) else {}
    deadline = summary.get("step_deadline_s")
    deadline = float(deadline) if isinstance(deadline, (int, float)) and deadline > 0 else math.nan
    status = _statuses(doc, n)
    iteration = _waypoint_field(doc, "iteration_time", n)
    velocity, acceleration = _fractions(run, t)
    return Timeline(
        t=t,
        status=status,
        clearance=clearance,
        near=near,
        body_point=body_point,
        obstacle_point=obstacle_point,
        tip_error=_waypoint_field(doc, "tip_error", n),
        iteration=iteration,
        deadline=deadline,
        velocity=velocity,
        acceleration=acceleration,
        safety_distance=float(safety),
        events=_events(doc, t, status, iteration, deadline),
    )
