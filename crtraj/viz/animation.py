"""The replay of a run as a meshcat animation: one key frame per recorded waypoint on every moving node.

Key times are the waypoints' times t (s) from the first; the robot's chords and discs, its base and the
obstacles' centres and radii move with the page's time slider. Positions in metres (three.js), quaternions in
three.js order (x, y, z, w).
"""

from __future__ import annotations

import warnings

import numpy as np

from crtraj.io.results import Result
from crtraj.viz.geometry import M_PER_MM, RobotPoses
from crtraj.viz.scene import SceneBuilder

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    from meshcat.animation import Animation, AnimationClip, AnimationTrack


def _xyzw(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) from (w, x, y, z) to three.js order (x, y, z, w)."""
    return q[..., [1, 2, 3, 0]]


def run_animation(run: Result, poses: RobotPoses, scene: SceneBuilder) -> Animation:
    """meshcat animation of `run` with one key per waypoint on every moving node of `scene`.

    poses: the robot's poses at the run's waypoints (`SceneBuilder.poses(run.x)`).
    """
    times = (run.t - run.t[0]).tolist()
    anim = Animation()

    def clip(name: str, **tracks: tuple[str, np.ndarray]) -> None:
        path = scene.node(name).path
        anim.clips[path] = AnimationClip(
            tracks={
                prop: AnimationTrack(prop, jstype, frames=list(times), values=np.asarray(v, dtype=float).tolist())
                for prop, (jstype, v) in tracks.items()
            },
            fps=1,  # key times are seconds
        )

    ones = np.ones(len(times))
    for i in range(scene.n_chords):
        scale = np.stack([ones, poses.chord_len[:, i], ones], axis=-1)
        clip(
            f"robot/backbone/{i:03d}",
            position=("vector3", poses.chord_mid[:, i]),
            quaternion=("quaternion", _xyzw(poses.chord_quat[:, i])),
            scale=("vector3", scale),
        )
    for j in range(scene.n_chords + 1):
        clip(
            f"robot/discs/{j:03d}",
            position=("vector3", poses.joints[:, j]),
            quaternion=("quaternion", _xyzw(poses.disc_quat[:, j])),
        )
    clip("robot/base", position=("vector3", scene.base_position(run.x[:, -1])))
    for i in range(run.centers.shape[1]):
        r = run.radii[:, i] * M_PER_MM
        clip(
            f"obstacles/{i}",
            position=("vector3", run.centers[:, i] * M_PER_MM),
            scale=("vector3", np.stack([r, r, r], axis=-1)),
        )
    return anim
