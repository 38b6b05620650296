"""Size and opening time of the view's standalone page (crtraj.viz), for real results and by run length.

Targets (issue 30): at most 3 MB for the paper's simulation-2 run and for a simulation-1 plan (100 Hz, ~1,400
waypoints), and the page ready in at most 2 s in headless Chromium (from navigation until the page's script has
found meshcat's scene and clock). Also the cost of drawing and exporting, and the key frames kept.
Run: python benchmarks/viz_export.py [--run RUN.json] [--plan PLAN.json] [--sizes 160,1000,2000] [--repeat 3]
(without --run/--plan, both are made with `crtraj replan problems/paper_dynamic.toml` and
`crtraj plan problems/paper_static.toml` in a temporary directory).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from crtraj.core.fileio import to_jsonable
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.viz.chromium import Chromium, find_chromium
from crtraj.viz.view import Visualizer

ROOT = Path(__file__).resolve().parent.parent
SIZE_TARGET_MB = 3.0
OPEN_TARGET_S = 2.0


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


def make_results(tmp: Path) -> tuple[Path, Path]:
    """The simulation-2 run and a simulation-1 plan, made by the CLI of this tree."""
    cli = [sys.executable, "-m", "crtraj.cli"]
    run = tmp / "run"
    subprocess.run([*cli, "replan", "problems/paper_dynamic.toml", "--out", str(run), "--quiet", "--no-html"],
                   cwd=ROOT, check=False)  # fmt: skip
    plan = tmp / "plan.json"
    subprocess.run([*cli, "plan", "problems/paper_static.toml", "--out", str(plan)], cwd=ROOT, check=True,
                   capture_output=True)  # fmt: skip
    return run / "run.json", plan


def open_time(browser: Chromium, page: Path) -> float:
    """s from navigation until the page is ready (its script found meshcat's scene and animation clock)."""
    t0 = time.perf_counter()
    tab = browser.open(page.as_uri(), 1280, 800, offline=True)
    elapsed = time.perf_counter() - t0
    tab.close()
    return elapsed


def measure(label: str, doc: dict, tmp: Path, browser: Chromium | None, repeat: int) -> None:
    draw, html = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        vis = Visualizer.for_result(doc, play=False)
        t1 = time.perf_counter()
        page = vis.static_html()
        html.append(time.perf_counter() - t1)
        draw.append(t1 - t0)
    keys = len(next(iter(next(iter(vis.animation.clips.values())).tracks.values())).frames) if vis.animation else 0
    path = tmp / f"{label.split()[0]}.html"
    path.write_text(page, encoding="utf-8")
    mb = path.stat().st_size / 1e6
    line = (
        f"{label}: {len(doc['waypoints'])} waypoints, {keys} key frames; draw {stats(draw)}; html {stats(html)}; "
        f"{mb:.2f} MB ({'ok' if mb <= SIZE_TARGET_MB else 'OVER'} <= {SIZE_TARGET_MB:g} MB)"
    )
    if browser is not None:
        opens = [open_time(browser, path) for _ in range(repeat)]
        ok = statistics.median(opens) <= OPEN_TARGET_S
        line += f"; opens in {stats(opens)} ({'ok' if ok else 'OVER'} <= {OPEN_TARGET_S:g} s)"
    print(line, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="a replan result (default: make the simulation-2 run)")
    ap.add_argument("--plan", type=Path, help="a plan result (default: make the simulation-1 plan)")
    ap.add_argument("--sizes", default="160,1000,2000", help="synthetic run lengths (waypoints), comma-separated")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    model = Model(load_robot(ROOT / "problems" / "robots" / "cdsr2.toml"))
    print(f"{platform.processor() or platform.machine()}, Python {platform.python_version()}")
    with tempfile.TemporaryDirectory(prefix="crtraj-bench-") as name:
        tmp = Path(name)
        run, plan = (args.run, args.plan) if args.run and args.plan else make_results(tmp)
        browser = Chromium() if find_chromium() else None
        if browser is None:
            print("no Chromium on PATH: opening time not measured")
        try:
            measure("sim-2 run", json.loads(run.read_text()), tmp, browser, args.repeat)
            measure("sim-1 plan", json.loads(plan.read_text()), tmp, browser, args.repeat)
            for n in (int(v) for v in args.sizes.split(",")):
                measure(f"synthetic {n}", synthetic_run(model, n), tmp, browser, args.repeat)
        finally:
            if browser is not None:
                browser.close()


if __name__ == "__main__":
    main()
