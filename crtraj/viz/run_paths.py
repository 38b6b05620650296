"""The still parts of a drawn run: start and goal markers, planned and executed tip paths, planner tree,
the replans' reference paths, the workspace box.

Planned paths are ghosts (thin, grey) under the executed trace; the planner tree and the replans' references are
layers, shown for plans and hidden for runs unless `ViewOptions.show_tree` says otherwise (the page's legend turns
them on). Lengths in mm.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from crtraj.io.results import Result
from crtraj.viz.scene import SceneBuilder

# at most this many of a run's replanned reference paths are drawn (the first ones; each is a layer line)
MAX_REFERENCES = 50


def _references(run: Result) -> list[np.ndarray]:
    """The tip paths (M, 3) mm of a run's replanned references, as its document records them."""
    out = []
    for ref in run.data.get("references") or []:
        tip = ref.get("tip") if isinstance(ref, Mapping) else None
        try:
            pts = np.asarray(tip, dtype=float)
        except (TypeError, ValueError):
            continue
        if pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 1 and np.isfinite(pts).all():
            out.append(pts)
    return out[:MAX_REFERENCES]


def draw_run_paths(scene: SceneBuilder, run: Result) -> list[np.ndarray]:
    """Draw the still parts of `run`; returns the points (K, 3) mm the camera should frame with the robot."""
    o = scene.options
    frame: list[np.ndarray] = []
    if run.start is not None:
        scene.marker("start", run.start, o.start_color)
        frame.append(run.start[None])
    if run.goal is not None:
        scene.marker("goal", run.goal, o.goal_color)
        frame.append(run.goal[None])
    planned = run.reference if run.reference is not None else (run.tip if run.kind == "plan" else None)
    if planned is not None and len(planned) > 1:
        scene.polyline("path/planned", planned, o.path_color, dots=True)
        frame.append(planned)
    if run.kind == "replan" and len(run.tip) > 1:
        scene.polyline("path/executed", run.tip, o.trail_color, dots=False)
    layers_on = o.show_tree if o.show_tree is not None else run.kind == "plan"
    if run.edges is not None:
        scene.tree(run.edges)
        scene.set_visible("tree", layers_on)
    refs = _references(run)
    for k, pts in enumerate(refs):
        scene.polyline(f"references/{k:03d}", pts, o.tree_color, dots=False)
    if refs:
        scene.set_visible("references", layers_on)
    if run.workspace is not None:
        scene.box("workspace", *run.workspace)
    return frame
