"""Meshcat browser view of a robot, its obstacles, planner tree and runs; standalone HTML.

`Visualizer` draws the backbone as a chain of cylinders with the robot's
discs (one colour per segment), obstacles as translucent spheres whose centre
and radius follow time, start and goal markers, the planned tip path, the
planner tree and the executed tip trail. A plan or replan result replays as a
meshcat animation (time slider in the page's "Animations" panel) with one key
frame per recorded waypoint.

Units: crtraj works in mm and s; meshcat (three.js) works in metres, so every
length is scaled by 1e-3 on the way out and times are passed in seconds.

Every command is also applied to an in-process copy of meshcat's own scene
tree (the server's code, run without sockets), so `static_html` and
`save_html` work with or without a server and give exactly the page meshcat's
server would give. A server, when asked for, is meshcat's, started as a child
process (`crtraj.viz.server`) with its web and ZMQ sockets bound to 127.0.0.1
only (meshcat 0.3.2 would listen on every interface), and it exits when this
process does. Results are read and validated by `crtraj.io.results`.

Jupyter: make ``vis.jupyter_cell()`` the last expression of a cell. With a
server it embeds the live page (an iframe on 127.0.0.1, so the browser must run
on the same machine as the kernel); offline (``server=False``, or
``Visualizer.for_result(result)``) it embeds the standalone page, which also
works for a remote kernel and in a saved notebook.

The parts: `crtraj.viz.options` (`ViewOptions`), `crtraj.viz.geometry` (poses and transforms),
`crtraj.viz.scene` (building the scene), `crtraj.viz.animation` (the replay's key frames),
`crtraj.viz.export` (the in-process scene tree and the standalone page) and `crtraj.viz.live._link` (the link to a
live server, `crtraj.viz.server`); `Visualizer` is the facade over them.

meshcat 0.3.2 quirks handled once: cylinders lie along the y axis
(three.js convention), int64 arrays are refused (everything is sent as
float32), and ``meshcat.Visualizer.close()`` raises (the window here closes).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import check_array
from crtraj.core.fileio import atomic_write_text
from crtraj.io.problem import Problem
from crtraj.io.results import Result, read_result
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.planning.body import planning_model
from crtraj.viz.animation import run_animation
from crtraj.viz.geometry import M_PER_MM, cylinder_quat, fit_view, transforms, translation, unit
from crtraj.viz.live import MeshcatWindow
from crtraj.viz.options import ViewOptions
from crtraj.viz.page import page_data, page_json, wrap_page
from crtraj.viz.run_paths import draw_run_paths
from crtraj.viz.scene import ROOT, SceneBuilder
from crtraj.viz.shapes import draw_shapes, shape_extent
from crtraj.viz.timeline import Timeline, build_timeline

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    import meshcat
    from IPython.display import HTML  # meshcat's own dependency, for its notebook cell
    from meshcat.animation import Animation

__all__ = ["Visualizer"]

_CAMERA_FOV_DEG = 75.0  # meshcat's default perspective camera
# width / height of the page's scene pane (1280 x 800 window less the side panel and the plots): what is framed
_PANE_ASPECT = 1.6


log = logging.getLogger(__name__)


def result_model(res: Result) -> Model:
    """The `Model` whose body a result was planned for: the rod model (`crtraj.planning.body.planning_model`,
    from the build cache) when its options record ``body.kind = "rod"``, else PCC. A rod model other than the
    result's (the robot file's mechanics or the model's options changed since) is drawn with a warning; a robot
    without ``[robot.mechanics]`` falls back to PCC with a warning."""
    body = res.data.get("options", {}).get("body") if isinstance(res.data, Mapping) else None
    if not isinstance(body, Mapping) or body.get("kind") != "rod":
        return Model(res.robot)
    try:
        model = planning_model(_mechanics_robot(res), "rod")
    except InputError as exc:
        log.warning("view: drawing PCC's body for a rod result (%s)", exc)
        return Model(res.robot)
    ident = model.identity() or {}
    if ident.get("rod_model") != body.get("rod_model"):
        log.warning("view: the result was planned with rod model %s; drawing rod model %s (the robot file or the "
                    "model's options changed since)", body.get("rod_model"), ident.get("rod_model"))  # fmt: skip
    return model


def _mechanics_robot(res: Result) -> Robot:
    """The result's robot with its ``[robot.mechanics]``: a result records the robot's model but not its
    mechanics, which come from the robot file of the problem the result names (checked against the result's)."""
    if res.robot.mechanics is not None:
        return res.robot
    path = (res.data.get("problem") or {}).get("path")
    if not path or not Path(path).is_file():
        raise InputError("the result names no readable problem file, whose robot file holds [robot.mechanics]")
    robot = Problem.load(path).robot
    res.check_robot(robot, f"the robot of {path}", "view the result beside the problem file it was planned from")
    return robot


class Visualizer:
    """Browser view (meshcat) of one robot model: configurations, obstacles and whole runs.

    ``Visualizer(model)`` starts a meshcat server on 127.0.0.1 (`url` is its
    address); ``server=False`` draws offline, for `save_html` /
    `static_html` only; ``zmq_url`` connects to a running meshcat server
    instead. ``open=True`` opens the page in the default browser. `options`:
    colours and sizes (`ViewOptions`, the problem file's ``[view]``). `timeout`
    (s) bounds the server's start-up and every reply; `nice` (0-19) is the
    niceness of the server it starts. Lengths in mm, times in s. Use as a
    context manager or call `close` to stop the server.
    """

    def __init__(
        self,
        model: Model,
        zmq_url: str | None = None,
        open: bool = False,
        *,
        server: bool = True,
        options: ViewOptions | None = None,
        timeout: float = 60.0,
        nice: int = 0,
    ) -> None:
        self.model = model
        self.robot = model.robot
        self.options = options if options is not None else ViewOptions()
        self._window = MeshcatWindow(zmq_url, server and zmq_url is None, timeout, nice)
        self._vis = meshcat.Visualizer(window=self._window)
        self._scene = SceneBuilder(self._vis, model, self.options)
        self._framed = False
        self._run: Result | None = None
        self._safety = 0.0  # D_sf (mm) of the run shown: the radius added to each obstacle's shell
        self._play = self.options.play
        self.animation: Animation | None = None
        self.timeline: Timeline | None = None  # the shown run's per-waypoint numbers
        self.compared: tuple[Result, Timeline] | None = None  # a second run drawn as a ghost
        self._scene.stage()
        if open:
            self.open()

    # ------------------------------------------------------------ plumbing
    @classmethod
    def for_result(
        cls,
        result: Mapping[str, Any],
        *,
        server: bool = False,
        open: bool = False,
        options: ViewOptions | None = None,
        play: bool | None = None,
    ) -> Visualizer:
        """A Visualizer for the robot of `result` (a plan/replan result dict) with the run drawn.

        Offline by default: ``Visualizer.for_result(result).save_html(path)``. The body drawn is the one the
        result was planned for (`result_model`): the rod's for a ``--model rod`` result.
        """
        res = read_result(result)
        vis = cls(result_model(res), server=server, options=options)
        try:
            vis.show_result(res, play=play)
            if open:
                vis.open()
        except BaseException:
            vis.close()
            raise
        return vis

    @property
    def url(self) -> str | None:
        """The full page's address (http://127.0.0.1:PORT/crtraj/: the scene with the heads-up panel, plots,
        events and legend, as in `static_html`), None when offline."""
        return self._window.page_url

    @property
    def scene_url(self) -> str | None:
        """meshcat's own page of the scene alone (http://127.0.0.1:PORT/static/), None when offline."""
        return self._window.web_url

    @property
    def zmq_url(self) -> str | None:
        """The meshcat server's ZMQ address, for other meshcat clients; None when offline."""
        return self._window.zmq_url

    @property
    def server_pid(self) -> int | None:
        """Process id of the server this Visualizer started, if any."""
        proc = self._window.server_proc
        return proc.pid if proc is not None else None

    def open(self) -> Visualizer:
        """Open the page in the default browser (needs a server)."""
        if self.url is None:
            raise InputError("open: this Visualizer has no server (server=False); use save_html(path)")
        self._window.open()
        return self

    def close(self) -> None:
        """Stop the server this Visualizer started (meshcat's own close() raises in 0.3.2)."""
        self._window.close()

    def __enter__(self) -> Visualizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def clear(self) -> None:
        """Remove everything drawn (camera, lights and background stay)."""
        self._scene.clear()
        self._framed = False
        self._run = None
        self.animation = None
        self.timeline = None
        self.compared = None

    def frame_camera(self, points: Any, direction: Sequence[float] = (1.0, -0.6, 0.5)) -> None:
        """Aim the camera at `points` (..., 3) (mm), looking along -direction, so that they fill the page's
        scene pane (`crtraj.viz.geometry.fit_view`).

        The whole drawing (meshcat path /meshcat) is shifted so that the aim point sits at
        meshcat's origin, which is what the mouse orbits around.
        """
        P = np.asarray(points, dtype=float).reshape(-1, 3)
        P = P[np.all(np.isfinite(P), axis=1)]
        if P.size == 0:
            raise InputError("frame_camera: no finite points to frame")
        view = unit(np.asarray(direction, dtype=float))  # from the target towards the camera
        center, dist = fit_view(P[:: max(1, len(P) // 4000)], view, _CAMERA_FOV_DEG, _PANE_ASPECT)
        off = view * dist * M_PER_MM
        # meshcat 0.3.2's orbit controls look at and turn about the world origin whatever the
        # camera node's transform, so the scene root moves instead: the box centre goes to the origin
        self._vis[ROOT].set_transform(translation(-center * M_PER_MM))
        # the camera sits in meshcat's "rotated" frame (y up): world (x, y, z) is (x, z, -y) there
        self._vis["/Cameras/default/rotated/<object>"].set_property("position", [off[0], off[2], -off[1]])
        self._framed = True

    # ---------------------------------------------------------------- robot
    def display(self, x: Any) -> None:
        """Draw the robot at configuration x (nx,): bending vectors (rad) then z (mm)."""
        xa = check_array(x, "x", (self.robot.nx,))
        self._scene.draw_robot()
        pose = self._scene.poses(xa)
        self._scene.pose_robot(pose, xa[-1])
        if not self._framed:
            self.frame_camera(pose.joints[0] / M_PER_MM)

    # ------------------------------------------------------------ obstacles
    def set_obstacles(self, centers: Any, radii: Any) -> None:
        """Draw spheres with centres (m, 3) and radii (m,) in mm."""
        for path, T in zip(*self._obstacle_frame(centers, radii), strict=True):
            self._vis[path].set_transform(T)

    def _obstacle_frame(self, centers: Any, radii: Any) -> tuple[list[str], np.ndarray]:
        """The obstacles' and their shells' paths and 4x4 transforms (2 m, 4, 4) for centres (m, 3), radii (m,) mm."""
        C = np.zeros((0, 3)) if len(centers) == 0 else check_array(centers, "centers", (None, 3))
        R = check_array(radii, "radii", (C.shape[0],))
        m = C.shape[0]
        self._scene.draw_obstacles(m)
        one = np.tile([1.0, 0, 0, 0], (m, 1))
        scales = np.repeat(np.stack([R, R + self._safety])[..., None], 3, axis=-1) * M_PER_MM  # (2, m, 3)
        mats = transforms(np.stack([C, C]) * M_PER_MM, np.stack([one, one]), scales).reshape(-1, 4, 4)
        return [f"{ROOT}/{kind}/{i}" for kind in ("obstacles", "shells") for i in range(m)], mats

    # ------------------------------------------------------------------ runs
    def show_result(
        self, result: Mapping[str, Any] | Result, *, animate: bool = True, play: bool | None = None
    ) -> Visualizer:
        """Draw a plan/replan result (`crtraj.io.results.read_result`: a document or a `Result`) and replay it.

        Key frames at the waypoints' times t (s) (`crtraj.viz.animation.key_frames`); the robot, the obstacle
        centres and radii, their D_sf shells and the closest-approach line move with the page's clock. The
        static scene shows the first waypoint. play=None takes `options.play`.
        """
        run = self._read_run(result, "the robot this Visualizer draws", "draw it with Visualizer.for_result")
        self.clear()
        self._run = run
        self._safety = run.scene.safety_distance if run.scene is not None else 0.0
        self.timeline = build_timeline(run, self.model)
        scene = self._scene
        poses = scene.poses(run.x)
        scene.draw_robot()
        scene.draw_obstacles(run.centers.shape[1])
        if self.timeline.clearance.shape[1]:  # spheres or other shapes
            scene.draw_closest()
        if run.scene is not None and run.scene.shapes:
            draw_shapes(self._vis, run.scene.shapes, self._safety, self.options, run.t[0] + run.scene.time_origin)
        content = draw_run_paths(scene, run)
        self._play = self.options.play if play is None else play
        self.animation = run_animation(run, poses, scene, self.timeline) if animate and len(run.t) > 1 else None
        self._send_animation()
        frame = [poses.joints.reshape(-1, 3) / M_PER_MM, run.tip, *content]
        if run.centers.shape[1]:
            r = run.radii[..., None] + self._safety
            frame += [(run.centers - r).reshape(-1, 3), (run.centers + r).reshape(-1, 3)]
        if run.scene is not None:
            frame.append(shape_extent(run.scene.shapes, run.t[0] + run.scene.time_origin))
        allp = np.concatenate(frame)
        scene.floor(allp.min(axis=0) - 10.0, allp.max(axis=0) + 10.0)
        self.frame_camera(allp)
        self.show_waypoint(0)
        self.push_page()
        return self

    def compare(self, result: Mapping[str, Any] | Result) -> Visualizer:
        """Add a second result of the same robot, its robot ghosted (`options.ghost_opacity`), on the same clock.

        Call after `show_result`; the page shows both sets of plots.
        """
        if self._run is None:
            raise InputError("compare: no result shown yet; call show_result first")
        shown = f"the result shown ({self._run.source})" if self._run.source else "the result shown"
        run = self._read_run(result, shown, "compare two results of the same robot file")
        ghost = SceneBuilder(self._vis, self.model, self.options, prefix="ghost")
        ghost.draw_robot()
        poses = ghost.poses(run.x)
        ghost.pose_robot(poses, run.x[0, -1])
        self.compared = (run, build_timeline(run, self.model))
        if self.animation is not None and len(run.t) > 1:
            self.animation.clips.update(run_animation(run, poses, ghost, self.compared[1]).clips)
            self._send_animation()
        self.push_page()
        return self

    def _read_run(self, result: Mapping[str, Any] | Result, who: str, fix: str) -> Result:
        """`result` read, refused (`Result.check_robot`: `who`, `fix`) when it is not this Visualizer's robot."""
        run = read_result(result)
        run.check_robot(self.robot, who, fix)
        missing = np.isnan(run.tip).any(axis=1)
        if missing.any():
            tip = run.tip.copy()
            tip[missing] = self.model.tip_position(run.x[missing]).reshape(-1, 3)
            run = dataclasses.replace(run, tip=tip)
        return run

    def _send_animation(self) -> None:
        if self.animation is not None:
            self._vis.set_animation(self.animation, play=self._play, repetitions=1)

    def show_waypoint(self, k: int) -> None:
        """Show the robot, the obstacles and the closest approach at waypoint k of the run drawn last."""
        if self._run is None:
            raise InputError("show_waypoint: no result shown yet; call show_result first")
        n = len(self._run.t)
        if not -n <= k < n:
            raise InputError(f"show_waypoint: k must be in [0, {n - 1}], got {k}")
        self.display(self._run.x[k])
        self.set_obstacles(self._run.centers[k], self._run.radii[k])
        tl = self.timeline
        if tl is not None and tl.clearance.shape[1]:
            self.set_closest(tl.body_point[k], tl.obstacle_point[k])

    def set_closest(self, body_point: Any, obstacle_point: Any) -> None:
        """Put the closest-approach line between body_point and obstacle_point (3,) mm."""
        for path, T in zip(*self._closest_frame(body_point, obstacle_point), strict=True):
            self._vis[path].set_transform(T)

    def _closest_frame(self, body_point: Any, obstacle_point: Any) -> tuple[list[str], np.ndarray]:
        """The closest-approach line's and its end points' paths and 4x4 transforms (none for a non-finite point)."""
        a, b = np.asarray(body_point, float) * M_PER_MM, np.asarray(obstacle_point, float) * M_PER_MM
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            return [], np.zeros((0, 4, 4))
        d = b - a
        line = transforms(0.5 * (a + b), cylinder_quat(unit(d)), np.array([1.0, np.linalg.norm(d), 1.0]))
        paths = [f"{ROOT}/closest/{name}" for name in ("line", "body", "obstacle")]
        return paths, np.stack([line, translation(a), translation(b)])

    def robot_poses(self, x: Any) -> Any:
        """The poses (metres) of the drawn robot's parts at configurations x (nx,) or (N, nx)
        (`crtraj.viz.geometry.RobotPoses`)."""
        return self._scene.poses(x)

    def draw_frame(self, x: Any, centers: Any, radii: Any, closest: Any = None, rows: Any = None) -> None:
        """One frame of a live run: the robot at x (nx,), obstacles (m, 3) / (m,) mm and, if given, the closest
        approach between closest's two points (mm). With a server, the frame is one message (`MeshcatWindow.
        send_frame`: every transform at once, with `rows`, the page's new numbers, `crtraj.viz.page.append_rows`),
        not one request per object; such frames are not recorded (a live run's page is built from its result).
        Offline, each transform is set (and recorded) as by `display`."""
        xa = check_array(x, "x", (self.robot.nx,))
        self._scene.draw_robot()
        pose = self._scene.poses(xa)
        if not self._framed:
            self.frame_camera(pose.joints[0] / M_PER_MM)
        parts = [(self._scene.robot_paths(), self._scene.robot_matrices(pose, xa[-1]))]
        parts.append(self._obstacle_frame(centers, radii))
        if closest is not None:
            parts.append(self._closest_frame(*closest))
        paths = [path for names, _ in parts for path in names]
        mats = np.concatenate([T for _, T in parts])
        if self._window.connected:
            self._window.send_frame(paths, mats, rows)
            return
        for path, T in zip(paths, mats, strict=True):
            self._vis[path].set_transform(T)

    # ---------------------------------------------------------------- export
    def static_html(self) -> str:
        """The scene as one self-contained HTML page: meshcat's static export inside the page around it
        (heads-up panel, plots, controls, legend; `crtraj.viz.page`); no server needed."""
        return wrap_page(self.scene_html(), self.page_data())

    def scene_html(self) -> str:
        """meshcat's own standalone page of the scene alone (what its server serves), without the page around it."""
        return self._vis.static_html()

    def page_data(self) -> dict[str, Any]:
        """What the page around the scene shows (`crtraj.viz.page.page_data`), as JSON-ready values."""
        runs = []
        if self._run is not None and self.timeline is not None:
            runs.append((self._run, self.timeline))
        if self.compared is not None:
            runs.append(self.compared)
        return page_data(runs, self.options)

    def push_page(self, data: dict[str, Any] | None = None) -> None:
        """Send the full page's data (default: `page_data`) to the server, whose page shows it (no-op offline)."""
        if self._window.web_url:
            self._window.send_page(page_json(self.page_data() if data is None else data))

    def start_live(self, safety_distance: float, goal: Any, n_obstacles: int) -> None:
        """Prepare a live view of a running loop: the robot, `n_obstacles` obstacles with shells of
        D_sf = safety_distance (mm), the closest-approach line and the goal (3,) mm marked."""
        self.clear()
        self._safety = float(safety_distance)
        self._scene.draw_robot()
        self._scene.draw_obstacles(n_obstacles)
        if n_obstacles:
            self._scene.draw_closest()
        self._scene.marker("goal", check_array(goal, "goal", (3,)), self.options.goal_color)

    def save_html(self, path: str | os.PathLike[str]) -> Path:
        """Write `static_html` to `path` atomically; returns the path."""
        return atomic_write_text(path, self.static_html())

    def scene_commands(self) -> list[dict[str, Any]]:
        """The decoded meshcat commands that make up the scene, in the order a page replays them."""
        return self._window.recorder.commands()

    def jupyter_cell(self, height: int = 500) -> Any:
        """IPython HTML for a notebook cell: the live page with a server, else the static page.

        Make it the last expression of the cell.
        """
        if self.url:  # meshcat's own cell, with the full page in its frame
            frame = f'<iframe src="{self.url}" style="width: 100%; height: 100%; border: none"></iframe>'
            box = f"height: {int(height)}px; width: 100%; overflow-x: auto; overflow-y: hidden; resize: both"
            return HTML(f'<div style="{box}">{frame}</div>')
        return self._vis.render_static(height=height)
