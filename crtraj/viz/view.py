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

meshcat 0.3.2 quirks handled here, once: cylinders lie along the y axis
(three.js convention), int64 arrays are refused (everything is sent as
float32), and ``meshcat.Visualizer.close()`` raises (the window here closes).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import subprocess
import warnings
import weakref
import webbrowser
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import msgpack
import numpy as np
import umsgpack
import zmq

from crtraj.core.errors import InputError
from crtraj.core.fields import Table, check_array
from crtraj.core.fileio import atomic_write_text
from crtraj.core.options import Options, option
from crtraj.io.results import Result, read_result
from crtraj.model.kinematics import Model
from crtraj.viz import server as meshcat_server

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    import meshcat
    import meshcat.geometry as mg
    from meshcat.animation import Animation, AnimationClip, AnimationTrack
    from meshcat.servers.tree import SceneTree, walk
    from meshcat.servers.zmqserver import ZMQWebSocketBridge


_M_PER_MM = 1e-3
_CAMERA_FOV_DEG = 75.0  # meshcat's default perspective camera
_RAIL_OFFSET_MM = 15.0  # the base rail is drawn beside the backbone (+y), not through it
_ROOT = "/meshcat"  # meshcat's conventional root of user content; deleting it keeps camera and lights
# Rotation about x by +90 deg, (w, x, y, z): takes a three.js cylinder's y axis onto z.
_Q_Y_TO_Z = np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
_COLOR_RE = re.compile(r"^#[0-9a-fA-F]{6}$")
# Most colours in view.segment_colors (cycled over the segments; a robot has a few).
MAX_SEGMENT_COLORS = 100


# ---------------------------------------------------------------------- options
@dataclasses.dataclass(frozen=True)
class ViewOptions(Options):
    """How a scene is drawn; the problem file's ``[view]`` section.

    backbone_radius: drawn radius of the backbone (mm; the real NiTi wire is
    0.3 mm, drawn thicker so it stays visible). disc_spacing: largest arc
    length between two discs (mm). disc_thickness (mm). disc_radius: None
    means the robot's body_radius (mm; the paper's discs are 6 mm wide).
    segment_colors: "#rrggbb" per segment, cycled. obstacle_color and
    obstacle_opacity (0..1). marker_radius: start/goal spheres (mm).
    show_tree: draw planner trees. play: start the animation when the page opens.
    """

    SECTION: ClassVar[str] = "view"

    backbone_radius: float = option(1.0, gt=0.0)
    disc_spacing: float = option(20.0, gt=0.0)
    disc_thickness: float = option(2.0, gt=0.0)
    disc_radius: float | None = option(None, gt=0.0)
    # a list in the file: read and checked by the hooks below (the base reads scalars only)
    segment_colors: tuple[str, ...] = option(("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#17becf"), read=False)
    obstacle_color: str = option("#d62728")
    obstacle_opacity: float = option(0.3, gt=0.0, le=1.0)
    start_color: str = option("#ffb000")
    goal_color: str = option("#e000e0")
    path_color: str = option("#202020")
    trail_color: str = option("#ff7f0e")
    tree_color: str = option("#8c8c8c")
    marker_radius: float = option(4.0, gt=0.0)
    show_tree: bool = option(True)
    play: bool = option(True)

    def _check(self) -> None:
        colors = self.segment_colors
        if isinstance(colors, (str, bytes)) or not isinstance(colors, Sequence):
            raise InputError(f'view.segment_colors: expected a list of "#rrggbb" strings, got {colors!r:.60}')
        if not colors:
            raise InputError("view.segment_colors: give at least one colour")
        if len(colors) > MAX_SEGMENT_COLORS:
            raise InputError(f"view.segment_colors: at most {MAX_SEGMENT_COLORS} colours, got {len(colors)}")
        for i, c in enumerate(colors):
            _color(c, f"view.segment_colors[{i}]")
        object.__setattr__(self, "segment_colors", tuple(colors))  # a list from Python is stored as the file's
        for name in ("obstacle_color", "start_color", "goal_color", "path_color", "trail_color", "tree_color"):
            _color(getattr(self, name), f"view.{name}")

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        default = cls.__dataclass_fields__["segment_colors"].default
        colors = t.raw("segment_colors", list(default))
        if not isinstance(colors, list) or not all(isinstance(c, str) for c in colors):
            raise t.error("segment_colors", f'expected a list of "#rrggbb" strings, got {colors!r:.60}')
        return {"segment_colors": tuple(colors)}


def _color(text: str, name: str) -> int:
    """'#rrggbb' -> 0xrrggbb; one-line error naming `name` otherwise."""
    if not isinstance(text, str) or not _COLOR_RE.match(text):
        raise InputError(f'{name}: expected a colour "#rrggbb", got {text!r}')
    return int(text[1:], 16)


# ------------------------------------------------------------ pose geometry
def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (..., 4) in (w, x, y, z) order."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def _cylinder_quat(v: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) that turn a three.js cylinder (axis y) onto unit vectors v (..., 3).

    First y -> z, then the shortest arc z -> v. That arc is undefined only for
    v = -z (a chord pointing straight down), where a half turn about x is used.
    """
    q = np.stack([1.0 + v[..., 2], -v[..., 1], v[..., 0], np.zeros(v.shape[:-1])], axis=-1)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    down = norm[..., 0] < 1e-9
    q = np.where(down[..., None], np.array([0.0, 1.0, 0.0, 0.0]), q / np.where(down[..., None], 1.0, norm))
    return _quat_mul(q, _Q_Y_TO_Z)


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) in (w, x, y, z) order."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def _transforms(pos_m: np.ndarray, quat: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """4x4 matrices (..., 4, 4): translate(pos) @ rotate(quat) @ diag(scale), as three.js composes them."""
    T = np.zeros((*pos_m.shape[:-1], 4, 4))
    T[..., :3, :3] = _quat_to_matrix(quat) * scale[..., None, :]
    T[..., :3, 3] = pos_m
    T[..., 3, 3] = 1.0
    return T


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


@dataclasses.dataclass(frozen=True)
class _RobotPoses:
    """Poses of every drawn robot part for N configurations (metres, quaternions w-x-y-z)."""

    joints: np.ndarray  # (N, J, 3) disc centres
    disc_quat: np.ndarray  # (N, J, 4)
    chord_mid: np.ndarray  # (N, C, 3)
    chord_quat: np.ndarray  # (N, C, 4)
    chord_len: np.ndarray  # (N, C)


def _f32(a: Any) -> np.ndarray:
    """meshcat refuses int64 and sends float64 as float32 anyway: be explicit."""
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32))


# ------------------------------------------------------------ meshcat window
class _Reply:
    """Stands in for the server's ZMQ reply socket: keeps the last reply."""

    __slots__ = ("data",)

    def __init__(self) -> None:
        self.data = b""

    def send(self, data: bytes) -> None:
        self.data = data


def _scene_recorder() -> Any:
    """meshcat's server scene logic (ZMQWebSocketBridge.handle_zmq) without any socket.

    Only its scene tree and reply are used, so the commands it keeps and the
    static HTML it builds are exactly what meshcat's own server would give.
    """
    bridge = object.__new__(ZMQWebSocketBridge)
    bridge.tree = SceneTree()
    bridge.websocket_pool = set()
    bridge.zmq_socket = _Reply()
    return bridge


def _ext(obj: Any) -> Any:
    if isinstance(obj, umsgpack.Ext):
        return msgpack.ExtType(obj.type, obj.data)
    raise TypeError(f"cannot pack {type(obj).__name__}")


def _packb(data: Any) -> bytes:
    """msgpack bytes of a lowered meshcat command: the C msgpack packs a long animation ~20x faster than
    meshcat's pure-Python umsgpack, with the same bytes."""
    return msgpack.packb(data, default=_ext, use_bin_type=True)


class _Window:
    """meshcat's ViewerWindow interface: every command goes to the in-process scene
    recorder and, when connected, to a meshcat server."""

    def __init__(self, zmq_url: str | None, start_server: bool, timeout: float) -> None:
        self._recorder = _scene_recorder()
        self._timeout_ms = int(timeout * 1000)
        self.server_proc: subprocess.Popen[bytes] | None = None
        self._log = None
        self._sock = None
        self.zmq_url: str | None = None
        self.web_url: str | None = None
        if start_server:
            self.server_proc, self._log, self.zmq_url, self.web_url = meshcat_server.start_server(timeout)
            self._connect()
        elif zmq_url is not None:
            self.zmq_url = zmq_url
            self._connect()
            self.web_url = self._request(b"url").decode("utf-8")
            # meshcat's client does the same: a url request before any browser
            # connects leaves the server's receive callback stuck until a reconnect.
            self._sock.close(linger=0)
            self._connect()
        self._finalizer = weakref.finalize(self, meshcat_server.stop_server, self.server_proc, self._sock, self._log)

    def _connect(self) -> None:
        sock = zmq.Context.instance().socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVTIMEO, self._timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, self._timeout_ms)
        sock.connect(self.zmq_url)
        self._sock = sock

    def _request(self, *frames: bytes) -> bytes:
        try:
            self._sock.send_multipart(list(frames))
            return self._sock.recv()
        except zmq.Again:
            self._sock.close(linger=0)
            self._sock = None
            raise RuntimeError(
                f"meshcat server at {self.zmq_url} did not answer within {self._timeout_ms / 1000:g} s"
            ) from None

    def send(self, command: Any) -> None:
        data = command.lower()
        frames = [data["type"].encode("utf-8"), data["path"].encode("utf-8"), _packb(data)]
        self._recorder.handle_zmq(frames)
        if self._sock is not None:
            self._request(*frames)

    def get_scene(self) -> str:
        self._recorder.handle_zmq([b"get_scene"])
        return self._recorder.zmq_socket.data.decode("utf-8")

    def tree(self) -> Any:
        return self._recorder.tree

    def open(self) -> _Window:
        if self.web_url:
            webbrowser.open(self.web_url, new=2)
        return self

    def close(self) -> None:
        self._finalizer()
        self._sock = None


# ----------------------------------------------------------------- Visualizer
class Visualizer:
    """Browser view (meshcat) of one robot model: configurations, obstacles and whole runs.

    ``Visualizer(model)`` starts a meshcat server on 127.0.0.1 (`url` is its
    address); ``server=False`` draws offline, for `save_html` /
    `static_html` only; ``zmq_url`` connects to a running meshcat server
    instead. ``open=True`` opens the page in the default browser. `options`:
    colours and sizes (`ViewOptions`, the problem file's ``[view]``). `timeout`
    (s) bounds the server's start-up and every reply. Lengths in mm, times in
    s. Use as a context manager or call `close` to stop the server.
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
    ) -> None:
        self.model = model
        self.robot = model.robot
        self.options = options if options is not None else ViewOptions()
        self._window = _Window(zmq_url, server and zmq_url is None, timeout)
        self._vis = meshcat.Visualizer(window=self._window)
        self._robot_drawn = False
        self._n_obstacles = -1
        self._framed = False
        self._run: Result | None = None
        self.animation: Animation | None = None
        self._layout()
        self._stage()
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

        Offline by default: ``Visualizer.for_result(result).save_html(path)``.
        """
        res = read_result(result)
        vis = cls(Model(res.robot), server=server, options=options)
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
        """The page's address (http://127.0.0.1:PORT/static/), None when offline."""
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

    def _node(self, name: str) -> meshcat.Visualizer:
        return self._vis[name]

    # ---------------------------------------------------------------- setup
    def _layout(self) -> None:
        """Split the backbone into C equal chords with a disc at each of the C+1 joints."""
        lengths = np.array([s.length for s in self.robot.segments])
        total = float(lengths.sum())
        self._n_chords = max(1, math.ceil(total / self.options.disc_spacing - 1e-9))
        arcs = self.model.arc_positions(self._n_chords + 1)
        bounds = np.cumsum(lengths)
        mid = 0.5 * (arcs[1:] + arcs[:-1])
        # a chord that straddles a segment boundary takes the colour of the segment holding its middle
        self._chord_segment = np.minimum(np.searchsorted(bounds, mid, side="right"), len(lengths) - 1)
        self._disc_segment = np.minimum(np.searchsorted(bounds, arcs, side="left"), len(lengths) - 1)

    def _segment_color(self, k: int) -> int:
        colors = self.options.segment_colors
        return _color(colors[k % len(colors)], f"view.segment_colors[{k % len(colors)}]")

    def _stage(self) -> None:
        """Light background, no 0.5 m axes or 10 m grid (both dwarf a 400 mm robot)."""
        self._vis["/Background"].set_property("top_color", [0.96, 0.96, 0.97])
        self._vis["/Background"].set_property("bottom_color", [0.80, 0.82, 0.85])
        self._vis["/Grid"].set_property("visible", False)
        self._vis["/Axes"].set_property("visible", False)

    def clear(self) -> None:
        """Remove everything drawn (camera, lights and background stay)."""
        self._vis[_ROOT].delete()
        self._robot_drawn = False
        self._n_obstacles = -1
        self._framed = False
        self._run = None
        self.animation = None

    def frame_camera(self, points: Any, direction: Sequence[float] = (1.0, -0.6, 0.5)) -> None:
        """Aim the camera at the bounding box of `points` (..., 3) (mm), looking along -direction.

        The whole drawing (meshcat path /meshcat) is shifted so that the box centre sits at
        meshcat's origin, which is what the mouse orbits around.
        """
        P = np.asarray(points, dtype=float).reshape(-1, 3)
        P = P[np.all(np.isfinite(P), axis=1)]
        if P.size == 0:
            raise InputError("frame_camera: no finite points to frame")
        lo, hi = P.min(axis=0), P.max(axis=0)
        center = 0.5 * (lo + hi)
        half = np.maximum(0.5 * (hi - lo), 25.0)
        view = _unit(np.asarray(direction, dtype=float))  # from the target towards the camera
        right = _unit(np.cross([0.0, 0.0, 1.0], view))
        if not np.any(right):
            right = np.array([1.0, 0.0, 0.0])
        up = np.cross(view, right)
        corners = center + half * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        rel = corners - center
        # nearest camera distance at which every box corner is inside the frustum (4:3 window assumed)
        tan_v = math.tan(math.radians(_CAMERA_FOV_DEG / 2))
        need = rel @ view + np.maximum(np.abs(rel @ up) / tan_v, np.abs(rel @ right) / (tan_v * 4 / 3))
        dist = 1.08 * float(need.max())
        off = view * dist * _M_PER_MM
        # meshcat 0.3.2's orbit controls look at and turn about the world origin whatever the
        # camera node's transform, so the scene root moves instead: the box centre goes to the origin
        self._vis[_ROOT].set_transform(_translation(-center * _M_PER_MM))
        # the camera sits in meshcat's "rotated" frame (y up): world (x, y, z) is (x, z, -y) there
        self._vis["/Cameras/default/rotated/<object>"].set_property("position", [off[0], off[2], -off[1]])
        self._framed = True

    # ---------------------------------------------------------------- robot
    def _poses(self, x: Any) -> _RobotPoses:
        """Disc and chord poses (metres) for configurations x (nx,) or (N, nx)."""
        X = np.atleast_2d(np.asarray(x, dtype=float))
        P = np.asarray(self.model.points(X, self._n_chords + 1)).reshape(X.shape[0], -1, 3) * _M_PER_MM
        d = P[:, 1:] - P[:, :-1]
        length = np.linalg.norm(d, axis=-1)
        u = _unit(d)
        # disc normal: mean direction of the chords on either side
        tangent = np.concatenate([u[:, :1], u[:, :-1] + u[:, 1:], u[:, -1:]], axis=1)
        return _RobotPoses(
            joints=P,
            disc_quat=_cylinder_quat(_unit(tangent)),
            chord_mid=0.5 * (P[:, 1:] + P[:, :-1]),
            chord_quat=_cylinder_quat(u),
            chord_len=length,
        )

    def _draw_robot(self) -> None:
        if self._robot_drawn:
            return
        o = self.options
        disc_r = self._disc_radius_m()
        mats = [mg.MeshPhongMaterial(color=self._segment_color(k)) for k in range(self.robot.n_segments)]
        for i, k in enumerate(self._chord_segment):
            # unit height, stretched per frame to the chord length by the y scale
            self._node(f"robot/backbone/{i:03d}").set_object(
                mg.Cylinder(1.0, o.backbone_radius * _M_PER_MM), mats[int(k)]
            )
        for j, k in enumerate(self._disc_segment):
            self._node(f"robot/discs/{j:03d}").set_object(
                mg.Cylinder(o.disc_thickness * _M_PER_MM, disc_r), mats[int(k)]
            )
        lo, hi = self.robot.z_range
        grey = mg.MeshPhongMaterial(color=0x606060)
        if hi > lo:
            rail = mg.Cylinder((hi - lo) * _M_PER_MM, 1.5 * _M_PER_MM)
            self._node("robot/rail").set_object(rail, grey)
            mid = np.array([0.0, _RAIL_OFFSET_MM, 0.5 * (lo + hi)]) * _M_PER_MM
            self._node("robot/rail").set_transform(_transforms(mid, _Q_Y_TO_Z, np.ones(3)))
        # the carriage: from the rail to just past the first disc
        width = _RAIL_OFFSET_MM + 2.0 + disc_r / _M_PER_MM + 1.0
        size = np.array([2 * disc_r / _M_PER_MM + 2.0, width, 4.0]) * _M_PER_MM
        self._node("robot/base").set_object(mg.Box(size.tolist()), grey)
        self._robot_drawn = True

    def _rail_ends(self) -> np.ndarray:
        """Ends of the base rail (mm): the stroke of the base translation z."""
        lo, hi = self.robot.z_range
        return np.array([[0.0, _RAIL_OFFSET_MM, lo], [0.0, _RAIL_OFFSET_MM, hi]])

    def _base_position(self, z_mm: np.ndarray) -> np.ndarray:
        """Centre of the carriage (metres) below the first disc, for base translations z (mm)."""
        disc_r = self._disc_radius_m() / _M_PER_MM
        y = 0.5 * ((_RAIL_OFFSET_MM + 2.0) - (disc_r + 1.0))
        z = np.asarray(z_mm, dtype=float) - 0.5 * self.options.disc_thickness - 2.0
        return np.stack([np.zeros_like(z), np.full_like(z, y), z], axis=-1) * _M_PER_MM

    def _disc_radius_m(self) -> float:
        o = self.options
        r = o.disc_radius if o.disc_radius is not None else self.robot.body_radius
        return max(r, 1.5 * o.backbone_radius) * _M_PER_MM

    def display(self, x: Any) -> None:
        """Draw the robot at configuration x (nx,): bending vectors (rad) then z (mm)."""
        xa = check_array(x, "x", (self.robot.nx,))
        self._draw_robot()
        pose = self._poses(xa)
        for i in range(self._n_chords):
            scale = np.array([1.0, pose.chord_len[0, i], 1.0])
            self._node(f"robot/backbone/{i:03d}").set_transform(
                _transforms(pose.chord_mid[0, i], pose.chord_quat[0, i], scale)
            )
        for j in range(self._n_chords + 1):
            self._node(f"robot/discs/{j:03d}").set_transform(
                _transforms(pose.joints[0, j], pose.disc_quat[0, j], np.ones(3))
            )
        self._node("robot/base").set_transform(_translation(self._base_position(xa[-1])))
        if not self._framed:
            self.frame_camera(pose.joints[0] / _M_PER_MM)

    # ------------------------------------------------------------ obstacles
    def set_obstacles(self, centers: Any, radii: Any) -> None:
        """Draw spheres with centres (m, 3) and radii (m,) in mm."""
        C = np.zeros((0, 3)) if len(centers) == 0 else check_array(centers, "centers", (None, 3))
        R = check_array(radii, "radii", (C.shape[0],))
        self._draw_obstacles(C.shape[0])
        for i in range(C.shape[0]):
            self._node(f"obstacles/{i}").set_transform(
                _transforms(C[i] * _M_PER_MM, np.array([1.0, 0, 0, 0]), np.full(3, R[i] * _M_PER_MM))
            )

    def _draw_obstacles(self, m: int) -> None:
        if m == self._n_obstacles:
            return
        self._vis[f"{_ROOT}/obstacles"].delete()
        o = self.options
        mat = mg.MeshPhongMaterial(
            color=_color(o.obstacle_color, "view.obstacle_color"),
            opacity=o.obstacle_opacity,
            transparent=o.obstacle_opacity < 1.0,
            depthWrite=o.obstacle_opacity >= 1.0,  # the robot inside a translucent sphere stays visible
        )
        for i in range(m):
            self._node(f"obstacles/{i}").set_object(mg.Sphere(1.0), mat)  # unit sphere, scaled to the radius
        self._n_obstacles = m

    # --------------------------------------------------------------- markers
    def _marker(self, name: str, p: np.ndarray, color: str) -> None:
        r = self.options.marker_radius * _M_PER_MM
        self._node(f"markers/{name}").set_object(mg.Sphere(r), mg.MeshPhongMaterial(color=_color(color, name)))
        self._node(f"markers/{name}").set_transform(_translation(p * _M_PER_MM))

    def _polyline(self, name: str, pts: np.ndarray, color: str, dots: bool) -> None:
        """A line through pts (M, 3) mm; with dots, also a dot at every point."""
        pos = _f32(pts.T * _M_PER_MM)
        c = _color(color, name)
        self._node(f"{name}/line").set_object(mg.Line(mg.PointsGeometry(pos), mg.LineBasicMaterial(color=c)))
        if dots:
            rgb = np.array([(c >> 16) & 255, (c >> 8) & 255, c & 255], dtype=float) / 255
            cols = _f32(np.repeat(rgb[:, None], pos.shape[1], axis=1))
            size = 0.6 * self.options.marker_radius * _M_PER_MM
            self._node(f"{name}/dots").set_object(mg.PointCloud(pos, cols, size=size))

    def _tree(self, edges: np.ndarray) -> None:
        pos = _f32(edges.reshape(-1, 3).T * _M_PER_MM)
        mat = mg.LineBasicMaterial(
            color=_color(self.options.tree_color, "view.tree_color"), opacity=0.6, transparent=True
        )
        self._node("tree").set_object(mg.LineSegments(mg.PointsGeometry(pos), mat))

    def _box(self, name: str, lo: np.ndarray, hi: np.ndarray) -> None:
        """Wireframe box between corners lo and hi (mm)."""
        c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        # corner index bits are (x, y, z): edges join corners that differ in one bit
        pairs = [(i, i ^ b) for i in range(8) for b in (1, 2, 4) if i < i ^ b]
        pos = _f32(c[np.array(pairs)].reshape(-1, 3).T * _M_PER_MM)
        self._node(name).set_object(mg.LineSegments(mg.PointsGeometry(pos), mg.LineBasicMaterial(color=0x9AA0A8)))

    def _floor(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """A 50 mm grid in the base plane z = 0 under the scene's x-y extent, for depth cues."""
        step = 50.0
        x0, x1 = step * math.floor(lo[0] / step), step * math.ceil(hi[0] / step)
        y0, y1 = step * math.floor(lo[1] / step), step * math.ceil(hi[1] / step)
        z = 0.0
        xs = np.arange(x0, x1 + step / 2, step)
        ys = np.arange(y0, y1 + step / 2, step)
        seg = [[[x, y0, z], [x, y1, z]] for x in xs] + [[[x0, y, z], [x1, y, z]] for y in ys]
        pos = _f32(np.asarray(seg).reshape(-1, 3).T * _M_PER_MM)
        self._node("floor").set_object(mg.LineSegments(mg.PointsGeometry(pos), mg.LineBasicMaterial(color=0xB0B4BA)))

    # ------------------------------------------------------------------ runs
    def show_result(
        self, result: Mapping[str, Any] | Result, *, animate: bool = True, play: bool | None = None
    ) -> Visualizer:
        """Draw a plan/replan result (`crtraj.io.results.read_result`: a document or a `Result`) and replay it.

        One key frame per waypoint at its time t (s); the robot, the obstacle
        centres and radii move with the slider. The static scene shows the
        first waypoint. play=None takes `options.play`.
        """
        run = read_result(result)
        run.check_robot(self.robot, "this Visualizer draws")
        missing = np.isnan(run.tip).any(axis=1)
        if missing.any():
            tip = run.tip.copy()
            tip[missing] = self.model.tip_position(run.x[missing]).reshape(-1, 3)
            run = dataclasses.replace(run, tip=tip)
        self.clear()
        self._run = run
        poses = self._poses(run.x)
        self._draw_robot()
        self._draw_obstacles(run.centers.shape[1])
        content = [poses.joints.reshape(-1, 3) / _M_PER_MM, run.tip, self._rail_ends()]
        if run.centers.shape[1]:
            r = run.radii[..., None]
            content += [(run.centers - r).reshape(-1, 3), (run.centers + r).reshape(-1, 3)]
        if run.start is not None:
            self._marker("start", run.start, self.options.start_color)
            content.append(run.start[None])
        if run.goal is not None:
            self._marker("goal", run.goal, self.options.goal_color)
            content.append(run.goal[None])
        planned = run.reference if run.reference is not None else (run.tip if run.kind == "plan" else None)
        if planned is not None and len(planned) > 1:
            self._polyline("path/planned", planned, self.options.path_color, dots=True)
            content.append(planned)
        if run.kind == "replan" and len(run.tip) > 1:
            self._polyline("path/executed", run.tip, self.options.trail_color, dots=False)
        if run.edges is not None and self.options.show_tree:
            self._tree(run.edges)
            content.append(run.edges.reshape(-1, 3))
        box = run.workspace
        if box is not None:
            self._box("workspace", *box)
            content.append(np.array(box))
        allp = np.concatenate(content)
        self._floor(allp.min(axis=0) - 10.0, allp.max(axis=0) + 10.0)
        self.frame_camera(allp)
        if animate and len(run.t) > 1:
            self.animation = self._animation(run, poses)
            self._vis.set_animation(self.animation, play=self.options.play if play is None else play, repetitions=1)
        self.show_waypoint(0)
        return self

    def show_waypoint(self, k: int) -> None:
        """Show the robot and obstacles at waypoint k of the run drawn last."""
        if self._run is None:
            raise InputError("show_waypoint: no result shown yet; call show_result first")
        n = len(self._run.t)
        if not -n <= k < n:
            raise InputError(f"show_waypoint: k must be in [0, {n - 1}], got {k}")
        self.display(self._run.x[k])
        self.set_obstacles(self._run.centers[k], self._run.radii[k])

    def _animation(self, run: Result, poses: _RobotPoses) -> Animation:
        """meshcat animation with one key per waypoint on every moving node."""
        times = (run.t - run.t[0]).tolist()
        anim = Animation()

        def clip(name: str, **tracks: tuple[str, np.ndarray]) -> None:
            path = self._node(name).path
            anim.clips[path] = AnimationClip(
                tracks={
                    prop: AnimationTrack(prop, jstype, frames=list(times), values=np.asarray(v, dtype=float).tolist())
                    for prop, (jstype, v) in tracks.items()
                },
                fps=1,  # key times are seconds
            )

        def xyzw(q: np.ndarray) -> np.ndarray:  # three.js quaternion order
            return q[..., [1, 2, 3, 0]]

        ones = np.ones(len(times))
        for i in range(self._n_chords):
            scale = np.stack([ones, poses.chord_len[:, i], ones], axis=-1)
            clip(
                f"robot/backbone/{i:03d}",
                position=("vector3", poses.chord_mid[:, i]),
                quaternion=("quaternion", xyzw(poses.chord_quat[:, i])),
                scale=("vector3", scale),
            )
        for j in range(self._n_chords + 1):
            clip(
                f"robot/discs/{j:03d}",
                position=("vector3", poses.joints[:, j]),
                quaternion=("quaternion", xyzw(poses.disc_quat[:, j])),
            )
        clip("robot/base", position=("vector3", self._base_position(run.x[:, -1])))
        for i in range(run.centers.shape[1]):
            r = run.radii[:, i] * _M_PER_MM
            clip(
                f"obstacles/{i}",
                position=("vector3", run.centers[:, i] * _M_PER_MM),
                scale=("vector3", np.stack([r, r, r], axis=-1)),
            )
        return anim

    # ---------------------------------------------------------------- export
    def static_html(self) -> str:
        """The scene as one self-contained HTML page (meshcat's static export; no server needed)."""
        return self._vis.static_html()

    def save_html(self, path: str | os.PathLike[str]) -> Path:
        """Write `static_html` to `path` atomically; returns the path."""
        return atomic_write_text(path, self.static_html())

    def scene_commands(self) -> list[dict[str, Any]]:
        """The decoded meshcat commands that make up the scene, in the order a page replays them."""
        out = []
        for node in walk(self._window.tree()):
            blobs = [node.object, *node.properties, node.transform, node.animation]
            out.extend(umsgpack.unpackb(b) for b in blobs if b is not None)
        return out

    def jupyter_cell(self, height: int = 500) -> Any:
        """IPython HTML for a notebook cell: the live page with a server, else the static page.

        Make it the last expression of the cell.
        """
        if self.url:
            return self._vis.jupyter_cell(height=height)
        return self._vis.render_static(height=height)


def _translation(p_m: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p_m
    return T
