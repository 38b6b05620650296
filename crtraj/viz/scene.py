"""Building the meshcat scene of one robot: backbone, discs, base, obstacles, markers, paths, tree, box, floor.

`SceneBuilder` owns the drawn objects under meshcat's ``/meshcat`` root: it lays the backbone out as equal chords
with a disc at every joint (one colour per segment), poses them for configurations, and draws the static parts of
a run. Lengths in mm on the way in, metres (`M_PER_MM`) on the way out.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.viz.geometry import M_PER_MM, Q_Y_TO_Z, RobotPoses, cylinder_quat, f32, transforms, translation, unit
from crtraj.viz.options import ViewOptions, color_value

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    import meshcat
    import meshcat.geometry as mg

ROOT = "/meshcat"  # meshcat's conventional root of user content; deleting it keeps camera and lights
_RAIL_OFFSET_MM = 15.0  # the base rail is drawn beside the backbone (+y), not through it


class SceneBuilder:
    """Draws one robot model's scene into a meshcat visualizer.

    vis: the meshcat visualizer (its window records or sends every command); model: the robot's model;
    options: colours and sizes; prefix: the node the robot is drawn under ("robot", or "ghost" for the
    second robot of a comparison, drawn at `options.ghost_opacity`).
    """

    def __init__(self, vis: meshcat.Visualizer, model: Model, options: ViewOptions, prefix: str = "robot") -> None:
        self.vis = vis
        self.model = model
        self.robot = model.robot
        self.options = options
        self.prefix = prefix
        self.opacity = 1.0 if prefix == "robot" else options.ghost_opacity
        self._robot_drawn = False
        self._n_obstacles = -1
        self._paths: list[str] | None = None
        self._layout()

    def node(self, name: str) -> meshcat.Visualizer:
        """The meshcat node `name` under the scene root."""
        return self.vis[name]

    def _layout(self) -> None:
        """Split the backbone into C equal chords with a disc at each of the C+1 joints."""
        lengths = np.array([s.length for s in self.robot.segments])
        total = float(lengths.sum())
        self.n_chords = max(1, math.ceil(total / self.options.disc_spacing - 1e-9))
        arcs = self.model.arc_positions(self.n_chords + 1)
        bounds = np.cumsum(lengths)
        mid = 0.5 * (arcs[1:] + arcs[:-1])
        # a chord that straddles a segment boundary takes the colour of the segment holding its middle
        self._chord_segment = np.minimum(np.searchsorted(bounds, mid, side="right"), len(lengths) - 1)
        self._disc_segment = np.minimum(np.searchsorted(bounds, arcs, side="left"), len(lengths) - 1)

    def _segment_color(self, k: int) -> int:
        colors = self.options.segment_colors
        return color_value(colors[k % len(colors)], f"view.segment_colors[{k % len(colors)}]")

    def stage(self) -> None:
        """Light background, no 0.5 m axes or 10 m grid (both dwarf a 400 mm robot)."""
        self.vis["/Background"].set_property("top_color", [0.96, 0.96, 0.97])
        self.vis["/Background"].set_property("bottom_color", [0.80, 0.82, 0.85])
        self.vis["/Grid"].set_property("visible", False)
        self.vis["/Axes"].set_property("visible", False)

    def clear(self) -> None:
        """Remove everything drawn (camera, lights and background stay)."""
        self.vis[ROOT].delete()
        self._robot_drawn = False
        self._n_obstacles = -1

    # ---------------------------------------------------------------- robot
    def poses(self, x: Any) -> RobotPoses:
        """Disc and chord poses (metres) for configurations x (nx,) or (N, nx)."""
        X = np.atleast_2d(np.asarray(x, dtype=float))
        P = np.asarray(self.model.points(X, self.n_chords + 1)).reshape(X.shape[0], -1, 3) * M_PER_MM
        d = P[:, 1:] - P[:, :-1]
        length = np.linalg.norm(d, axis=-1)
        u = unit(d)
        # disc normal: mean direction of the chords on either side
        tangent = np.concatenate([u[:, :1], u[:, :-1] + u[:, 1:], u[:, -1:]], axis=1)
        return RobotPoses(
            joints=P,
            disc_quat=cylinder_quat(unit(tangent)),
            chord_mid=0.5 * (P[:, 1:] + P[:, :-1]),
            chord_quat=cylinder_quat(u),
            chord_len=length,
        )

    def draw_robot(self) -> None:
        """Create the robot's objects (once; `pose_robot` moves them)."""
        if self._robot_drawn:
            return
        o = self.options
        disc_r = self._disc_radius_m()
        mats = [self._material(self._segment_color(k)) for k in range(self.robot.n_segments)]
        # one geometry per part, shared by every chord (unit height, stretched by the y scale) and every disc
        tube = mg.Cylinder(1.0, self.tube_radius_mm() * M_PER_MM)
        disc = mg.Cylinder(o.disc_thickness * M_PER_MM, disc_r)
        for i, k in enumerate(self._chord_segment):
            self.node(f"{self.prefix}/backbone/{i:03d}").set_object(tube, mats[int(k)])
        for j, k in enumerate(self._disc_segment):
            self.node(f"{self.prefix}/discs/{j:03d}").set_object(disc, mats[int(k)])
        tip = mg.Sphere(1.6 * disc_r)
        self.node(f"{self.prefix}/tip").set_object(tip, self._material(self._segment_color(self.robot.n_segments - 1)))
        lo, hi = self.robot.z_range
        grey = self._material(0x606060)
        if hi > lo:
            rail = mg.Cylinder((hi - lo) * M_PER_MM, 1.5 * M_PER_MM)
            self.node(f"{self.prefix}/rail").set_object(rail, grey)
            mid = np.array([0.0, _RAIL_OFFSET_MM, 0.5 * (lo + hi)]) * M_PER_MM
            self.node(f"{self.prefix}/rail").set_transform(transforms(mid, Q_Y_TO_Z, np.ones(3)))
        # the carriage: from the rail to just past the first disc
        width = _RAIL_OFFSET_MM + 2.0 + disc_r / M_PER_MM + 1.0
        size = np.array([2 * disc_r / M_PER_MM + 2.0, width, 4.0]) * M_PER_MM
        self.node(f"{self.prefix}/base").set_object(mg.Box(size.tolist()), grey)
        self._robot_drawn = True

    def _material(self, color: int) -> mg.MeshPhongMaterial:
        """A shaded material of `color`, see-through for a ghost robot."""
        if self.opacity >= 1.0:
            return mg.MeshPhongMaterial(color=color)
        return mg.MeshPhongMaterial(color=color, opacity=self.opacity, transparent=True, depthWrite=False)

    def robot_paths(self) -> list[str]:
        """The meshcat paths of the robot's parts `robot_matrices` poses, in its order: chords, discs, base, tip."""
        if self._paths is None:
            p = self.prefix
            names = [f"{p}/backbone/{i:03d}" for i in range(self.n_chords)]
            names += [f"{p}/discs/{j:03d}" for j in range(self.n_chords + 1)] + [f"{p}/base", f"{p}/tip"]
            self._paths = [self.node(n).path.lower() for n in names]
        return self._paths

    def robot_matrices(self, pose: RobotPoses, z_mm: float) -> np.ndarray:
        """The 4x4 transforms (len(robot_paths()), 4, 4) (metres) of the robot's parts at the first configuration
        of `pose`, the base at translation z_mm (mm)."""
        n = self.n_chords
        ones = np.ones(n)
        chords = transforms(pose.chord_mid[0], pose.chord_quat[0], np.stack([ones, pose.chord_len[0], ones], axis=-1))
        discs = transforms(pose.joints[0], pose.disc_quat[0], np.ones((n + 1, 3)))
        ends = [translation(self.base_position(z_mm)), translation(pose.joints[0, -1])]
        return np.concatenate([chords, discs, np.stack(ends)])

    def pose_robot(self, pose: RobotPoses, z_mm: float) -> None:
        """Move the robot's objects to the first configuration of `pose`, the base to translation z_mm (mm)."""
        for path, T in zip(self.robot_paths(), self.robot_matrices(pose, z_mm), strict=True):
            self.vis[path].set_transform(T)

    def rail_ends(self) -> np.ndarray:
        """Ends of the base rail (mm): the stroke of the base translation z."""
        lo, hi = self.robot.z_range
        return np.array([[0.0, _RAIL_OFFSET_MM, lo], [0.0, _RAIL_OFFSET_MM, hi]])

    def base_position(self, z_mm: Any) -> np.ndarray:
        """Centre of the carriage (metres) below the first disc, for base translations z (mm)."""
        disc_r = self._disc_radius_m() / M_PER_MM
        y = 0.5 * ((_RAIL_OFFSET_MM + 2.0) - (disc_r + 1.0))
        z = np.asarray(z_mm, dtype=float) - 0.5 * self.options.disc_thickness - 2.0
        return np.stack([np.zeros_like(z), np.full_like(z, y), z], axis=-1) * M_PER_MM

    def tube_radius_mm(self) -> float:
        """Radius of the drawn backbone tube (mm): the option, else the body radius clearance is measured with."""
        r = self.options.backbone_radius
        return float(r) if r is not None else float(self.robot.body_radius)

    def _disc_radius_m(self) -> float:
        o = self.options
        tube = self.tube_radius_mm()
        r = o.disc_radius if o.disc_radius is not None else 1.5 * tube
        return max(r, 1.2 * tube) * M_PER_MM

    # ------------------------------------------------------------ obstacles
    def draw_obstacles(self, m: int) -> None:
        """Make sure there are `m` obstacle spheres (unit spheres, scaled to their radii by their transforms)."""
        if m == self._n_obstacles:
            return
        self.vis[f"{ROOT}/obstacles"].delete()
        o = self.options
        mat = mg.MeshPhongMaterial(
            color=color_value(o.obstacle_color, "view.obstacle_color"),
            opacity=o.obstacle_opacity,
            transparent=o.obstacle_opacity < 1.0,
            depthWrite=o.obstacle_opacity >= 1.0,  # the robot inside a translucent sphere stays visible
        )
        self.vis[f"{ROOT}/shells"].delete()
        shell = mg.MeshLambertMaterial(
            color=color_value(o.obstacle_color, "view.obstacle_color"),
            opacity=o.shell_opacity,
            transparent=True,
            depthWrite=False,
        )
        sphere = mg.Sphere(1.0)  # one unit sphere for all, scaled to each radius by its transform
        for i in range(m):
            self.node(f"obstacles/{i}").set_object(sphere, mat)
            self.node(f"shells/{i}").set_object(sphere, shell)
        self._n_obstacles = m

    def draw_closest(self) -> None:
        """The closest-approach line (a unit-height cylinder stretched per frame) and its two end points."""
        o = self.options
        mat = mg.MeshBasicMaterial(color=color_value(o.closest_color, "view.closest_color"))
        r = 0.6 * self.tube_radius_mm() * M_PER_MM
        self.node("closest/line").set_object(mg.Cylinder(1.0, 0.8 * r), mat)
        self.node("closest/body").set_object(mg.Sphere(r), mat)
        self.node("closest/obstacle").set_object(mg.Sphere(r), mat)

    def set_visible(self, name: str, visible: bool) -> None:
        """Show or hide the layer `name` (the page's legend can turn it back on)."""
        self.node(name).set_property("visible", visible)

    # --------------------------------------------------------------- markers
    def marker(self, name: str, p: np.ndarray, color: str) -> None:
        """A sphere of `options.marker_radius` at p (3,) mm."""
        r = self.options.marker_radius * M_PER_MM
        self.node(f"markers/{name}").set_object(mg.Sphere(r), mg.MeshPhongMaterial(color=color_value(color, name)))
        self.node(f"markers/{name}").set_transform(translation(p * M_PER_MM))

    def polyline(self, name: str, pts: np.ndarray, color: str, dots: bool) -> None:
        """A line through pts (M, 3) mm; with dots, also a dot at every point."""
        pos = f32(pts.T * M_PER_MM)
        c = color_value(color, name)
        self.node(f"{name}/line").set_object(mg.Line(mg.PointsGeometry(pos), mg.LineBasicMaterial(color=c)))
        if dots:
            rgb = np.array([(c >> 16) & 255, (c >> 8) & 255, c & 255], dtype=float) / 255
            cols = f32(np.repeat(rgb[:, None], pos.shape[1], axis=1))
            size = 0.6 * self.options.marker_radius * M_PER_MM
            self.node(f"{name}/dots").set_object(mg.PointCloud(pos, cols, size=size))

    def tree(self, edges: np.ndarray) -> None:
        """A planner tree: line segments edges (E, 2, 3) mm."""
        pos = f32(edges.reshape(-1, 3).T * M_PER_MM)
        mat = mg.LineBasicMaterial(
            color=color_value(self.options.tree_color, "view.tree_color"), opacity=0.6, transparent=True
        )
        self.node("tree").set_object(mg.LineSegments(mg.PointsGeometry(pos), mat))

    def box(self, name: str, lo: np.ndarray, hi: np.ndarray) -> None:
        """Wireframe box between corners lo and hi (mm)."""
        c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        # corner index bits are (x, y, z): edges join corners that differ in one bit
        pairs = [(i, i ^ b) for i in range(8) for b in (1, 2, 4) if i < i ^ b]
        pos = f32(c[np.array(pairs)].reshape(-1, 3).T * M_PER_MM)
        self.node(name).set_object(mg.LineSegments(mg.PointsGeometry(pos), mg.LineBasicMaterial(color=0x9AA0A8)))

    def floor(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """A 50 mm grid in the base plane z = 0 under the scene's x-y extent, for depth cues."""
        step = 50.0
        x0, x1 = step * math.floor(lo[0] / step), step * math.ceil(hi[0] / step)
        y0, y1 = step * math.floor(lo[1] / step), step * math.ceil(hi[1] / step)
        z = 0.0
        xs = np.arange(x0, x1 + step / 2, step)
        ys = np.arange(y0, y1 + step / 2, step)
        seg = [[[x, y0, z], [x, y1, z]] for x in xs] + [[[x0, y, z], [x1, y, z]] for y in ys]
        pos = f32(np.asarray(seg).reshape(-1, 3).T * M_PER_MM)
        self.node("floor").set_object(mg.LineSegments(mg.PointsGeometry(pos), mg.LineBasicMaterial(color=0xB0B4BA)))
