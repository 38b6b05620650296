"""Look at a plan or replan result in the browser, or draw single configurations.

    python examples/view_result.py RESULT.json             # serve on 127.0.0.1 and open a tab, Ctrl-C stops
    python examples/view_result.py RESULT.json view.html   # one standalone HTML file, no server needed
    python examples/view_result.py --pose pose.html        # the default robot at one configuration

In a Jupyter notebook, end a cell with ``vis.jupyter_cell()`` (the live page
when the Visualizer has a server, the standalone page inline otherwise).
Lengths are in mm, angles in rad, times in s.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

import crtraj

ROBOT = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"


def serve(result_path: str) -> None:
    """Replay a result with meshcat's time slider until Ctrl-C."""
    result = crtraj.read_result(result_path)  # validated: one line naming the field if the file is off the schema
    with crtraj.Visualizer.for_result(result, server=True, open=True) as vis:
        print(f"{result_path}: {vis.url}  (Ctrl-C to stop)")
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass


def export(result_path: str, html_path: str) -> None:
    """The same page as one self-contained file (what `crtraj view --html` writes)."""
    path = crtraj.Visualizer.for_result(crtraj.read_result(result_path)).save_html(html_path)
    print(f"wrote {path}")


def pose(html_path: str) -> None:
    """The default robot at one configuration x = (u_1x, u_1y, u_2x, u_2y, z) among the paper's spheres."""
    model = crtraj.Model(crtraj.load_robot(ROBOT))
    vis = crtraj.Visualizer(model, server=False)  # offline: only for the HTML file
    x = np.array([-0.33, 0.73, -0.09, 0.78, -33.0])  # rad, rad, rad, rad, mm: threads between the spheres
    centers = np.array([[0.0, 90.0, 330.0], [-10.0, -70.0, 250.0]])  # mm, paper simulation 1
    radii = np.array([65.0, 55.0])  # mm
    vis.display(x)
    vis.set_obstacles(centers, radii)
    vis.frame_camera(np.vstack([model.points(x, 50), centers - radii[:, None], centers + radii[:, None]]))
    gap = np.linalg.norm(model.points(x, 50)[:, None] - centers, axis=2) - radii - model.robot.body_radius
    print(f"tip at {np.round(model.tip_position(x), 1)} mm, {gap.min():.1f} mm from the nearest sphere")
    print(f"wrote {vis.save_html(html_path)}")


if __name__ == "__main__":
    args = sys.argv[1:]
    if len(args) == 2 and args[0] == "--pose":
        pose(args[1])
    elif len(args) == 2:
        export(args[0], args[1])
    elif len(args) == 1:
        serve(args[0])
    else:
        sys.exit(__doc__)
