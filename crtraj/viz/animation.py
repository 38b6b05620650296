"""The replay of a run as a meshcat animation: key frames on every moving node, at the waypoints the eye needs.

Key times are the waypoints' times t (s) from the first. `key_frames` keeps a waypoint only when the page's
straight-line interpolation between the keys around it would miss a drawn point by more than a tolerance (plus the
first, the last and the moment the page points at), so a 100 Hz plan does not carry 1,400 keys that look the same.
The robot's chords and discs, its base and tip marker, the obstacles with their D_sf shells, and the
closest-approach line move with the page's clock. Positions in metres (three.js), quaternions in three.js order
(x, y, z, w).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

from crtraj.io.results import Result
from crtraj.viz.geometry import M_PER_MM, RobotPoses, cylinder_quat, unit
from crtraj.viz.scene import SceneBuilder
from crtraj.viz.shapes import shape_tracks
from crtraj.viz.timeline import Timeline

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    from meshcat.animation import Animation, AnimationClip, AnimationTrack

# A waypoint whose drawn points all lie within this (mm) of the page's interpolation between the keys around it
# is dropped: on a 400 mm robot filling the window, 0.5 mm is under a pixel.
KEY_TOLERANCE_MM = 0.5
# chords whose length varies less than this fraction over the run keep one length (no scale track)
_FIXED_LENGTH = 1e-3


def _xyzw(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) from (w, x, y, z) to three.js order (x, y, z, w)."""
    return q[..., [1, 2, 3, 0]]


def key_frames(
    t: np.ndarray, points_mm: np.ndarray, must: Sequence[int] = (), tol: float = KEY_TOLERANCE_MM
) -> np.ndarray:
    """Indices of the waypoints to key: the first, the last, `must`, and as few others as keep every point of
    points_mm (N, P, 3) within tol (mm) of the straight-line interpolation the page makes between keys at t (N,) s.
    """
    n = len(points_mm)
    forced = np.zeros(n, dtype=bool)
    forced[[0, n - 1]] = True
    forced[[i for i in must if 0 <= i < n]] = True
    keys = [0]
    a = 0
    while a < n - 1:
        b = a + 1
        # extend the span a..b while the waypoints inside it stay within tol of the line between its ends
        while b < n - 1 and not forced[b] and _span_error(t, points_mm, a, b + 1) <= tol:
            b += 1
        keys.append(b)
        a = b
    return np.asarray(keys)


def _span_error(t: np.ndarray, P: np.ndarray, a: int, b: int) -> float:
    """Largest distance (mm) of the points of waypoints a+1..b-1 from their interpolation between a and b."""
    if b - a < 2:
        return 0.0
    span = t[b] - t[a]
    w = (t[a + 1 : b] - t[a]) / span if span > 0 else np.linspace(0, 1, b - a + 1)[1:-1]
    line = P[a] + w[:, None, None] * (P[b] - P[a])
    return float(np.max(np.abs(P[a + 1 : b] - line)))


def moving_points(run: Result, poses: RobotPoses, timeline: Timeline) -> np.ndarray:
    """Every drawn point that moves (N, P, 3) mm: joints, obstacle extremes, the closest-approach pair."""
    parts = [poses.joints / M_PER_MM]
    if run.centers.shape[1]:
        r = run.radii[..., None]
        parts += [run.centers + r, run.centers - r]
    if timeline.clearance.shape[1]:
        parts += [timeline.body_point[:, None], timeline.obstacle_point[:, None]]
    return np.concatenate(parts, axis=1)


class _Clips:
    """Collects one clip per node, every track keyed at the same times (s)."""

    def __init__(self, scene: SceneBuilder, times: np.ndarray) -> None:
        self.scene = scene
        self.times = np.asarray(times, dtype=float).tolist()
        self.anim = Animation()

    def add(self, name: str, **tracks: tuple[str, np.ndarray]) -> None:
        path = self.scene.node(name).path
        self.anim.clips[path] = AnimationClip(
            tracks={
                prop: AnimationTrack(prop, jstype, frames=list(self.times), values=np.asarray(v, float).tolist())
                for prop, (jstype, v) in tracks.items()
            },
            fps=1,  # key times are seconds
        )


def run_animation(run: Result, poses: RobotPoses, scene: SceneBuilder, timeline: Timeline) -> Animation:
    """meshcat animation of `run` keyed at `key_frames` on every moving node of `scene`.

    poses: the robot's poses at the run's waypoints (`SceneBuilder.poses(run.x)`); timeline: its closest approach.
    """
    keys = key_frames(timeline.t, moving_points(run, poses, timeline), must=[timeline.closest_index])
    clips = _Clips(scene, timeline.t[keys])
    ones = np.ones(len(keys))
    length = poses.chord_len[keys]
    for i in range(scene.n_chords):
        tracks = {
            "position": ("vector3", poses.chord_mid[keys, i]),
            "quaternion": ("quaternion", _xyzw(poses.chord_quat[keys, i])),
        }
        if np.ptp(length[:, i]) > _FIXED_LENGTH * np.max(length[:, i]):
            tracks["scale"] = ("vector3", np.stack([ones, length[:, i], ones], axis=-1))
        clips.add(f"{scene.prefix}/backbone/{i:03d}", **tracks)
    for j in range(scene.n_chords + 1):
        clips.add(
            f"{scene.prefix}/discs/{j:03d}",
            position=("vector3", poses.joints[keys, j]),
            quaternion=("quaternion", _xyzw(poses.disc_quat[keys, j])),
        )
    clips.add(f"{scene.prefix}/base", position=("vector3", scene.base_position(run.x[keys, -1])))
    clips.add(f"{scene.prefix}/tip", position=("vector3", run.tip[keys] * M_PER_MM))
    if scene.prefix == "robot":  # the scene's own obstacles and closest approach; a compared run shows only its robot
        _obstacle_clips(clips, run, timeline, keys)
        shapes = () if run.scene is None else run.scene.shapes
        for k, ms in enumerate(shapes):
            if not ms.static:
                clips.add(f"shapes/{k}", **shape_tracks(ms, timeline.t[keys] + run.scene.time_origin))
    return clips.anim


def _obstacle_clips(clips: _Clips, run: Result, timeline: Timeline, keys: np.ndarray) -> None:
    """The obstacles, their D_sf shells and the closest-approach line between the body and the nearest one."""
    for i in range(run.centers.shape[1]):
        c = run.centers[keys, i] * M_PER_MM
        r = run.radii[keys, i] * M_PER_MM
        shell = r + timeline.safety_distance * M_PER_MM
        clips.add(f"obstacles/{i}", position=("vector3", c), scale=("vector3", np.stack([r, r, r], axis=-1)))
        clips.add(f"shells/{i}", position=("vector3", c), scale=("vector3", np.stack([shell] * 3, axis=-1)))
    if timeline.clearance.shape[1] == 0:  # neither spheres nor shapes
        return
    a, b = timeline.body_point[keys] * M_PER_MM, timeline.obstacle_point[keys] * M_PER_MM
    d = b - a
    ones = np.ones(len(keys))
    clips.add(
        "closest/line",
        position=("vector3", 0.5 * (a + b)),
        quaternion=("quaternion", _xyzw(cylinder_quat(unit(d)))),
        scale=("vector3", np.stack([ones, np.linalg.norm(d, axis=1), ones], axis=-1)),
    )
    clips.add("closest/body", position=("vector3", a))
    clips.add("closest/obstacle", position=("vector3", b))
