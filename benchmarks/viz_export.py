"""Cost of drawing a run and exporting it as standalone HTML (crtraj.viz.view), by run length.

No target in the issue; this documents what `crtraj view --html` and the replan
script's run.html cost: drawing + building the animation (one key per waypoint),
the HTML export, and the file size. Also the packing speed-up of the C msgpack
over meshcat's pure-Python umsgpack (the bytes are identical).
Run: python benchmarks/viz_export.py [--sizes 160,1000,2000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import umsgpack

from crtraj.core.fileio import to_jsonable
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.viz.view import Visualizer, _packb

ROOT = Path(__file__).resolve().parent.parent


def synthetic_run(model: Model, n: int) -> dict:
    """A replan-shaped result: n waypoints between two bent configurations, two breathing spheres."""
    x0 = np.array([0.4, 0.3, -0.2, 0.6, -20.0])
    x1 = np.array([-0.5, -0.6, 0.9, -0.4, -120.0])
    s = np.linspace(0.0, 1.0, n)
    X = x0 + s[:, None] * (x1 - x0)
    t = 0.1 * np.arange(n)
    tips = model.tip_position(X)
    centers = np.array([[0.0, 90.0, 330.0], [-10.0, -70.0, 250.0]])
    radii = np.stack([60 + 10 * np.sin(t), 45 + 15 * np.cos(t)], axis=-1)
    wps = [
        {"t": t[i], "tip": tips[i], "x": X[i], "obstacles": {"centers": centers, "radii": radii[i]}} for i in range(n)
    ]
    res = {"kind": "replan", "robot": model.robot.to_dict(), "waypoints": wps, "reference": {"tip": tips}}
    return to_jsonable(res)


def stats(xs: list[float]) -> str:
    xs = sorted(xs)
    p90 = xs[min(len(xs) - 1, round(0.9 * (len(xs) - 1)))]
    return f"median {statistics.median(xs):.3f} s, p90 {p90:.3f} s"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="160,1000,2000", help="waypoint counts, comma-separated")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    model = Model(load_robot(ROOT / "problems" / "robots" / "cdsr2.toml"))
    print(f"{platform.processor() or platform.machine()}, Python {platform.python_version()}")
    for n in (int(v) for v in args.sizes.split(",")):
        run = synthetic_run(model, n)
        draw, html = [], []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            vis = Visualizer.for_result(run)
            t1 = time.perf_counter()
            page = vis.static_html()
            html.append(time.perf_counter() - t1)
            draw.append(t1 - t0)
        anim = next(c for c in vis.scene_commands() if c["type"] == "set_animation")
        t0 = time.perf_counter()
        fast = _packb(anim)
        t_fast = time.perf_counter() - t0
        t0 = time.perf_counter()
        slow = umsgpack.packb(anim)
        t_slow = time.perf_counter() - t0
        assert fast == slow
        print(
            f"{n:5d} waypoints: draw+animate {stats(draw)}; html {stats(html)}; {len(page) / 1e6:.1f} MB; "
            f"animation packing {t_slow / t_fast:.0f}x faster than umsgpack ({t_fast:.3f} s vs {t_slow:.3f} s)"
        )


if __name__ == "__main__":
    main()
