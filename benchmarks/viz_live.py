"""The closed loop's iteration time with and without the live view (`crtraj replan --view`), and the view's frames.

Issue 30: the live view updates the page at up to 30 Hz from its own thread "so the loop's timing does not change".
This runs the paper's simulation 2 (problems/paper_dynamic.toml, one seed) alternately without the view and with
it (a served `crtraj.viz.live_view.LiveView`, its page open in headless Chromium when there is one, so the server
really pushes to a browser), and prints per run and pooled: the loop's iteration time (median, p99, max), its
deadline misses, and the view's published / drawn / dropped frames. Old path = without the view, new = with it.
Wall-clock numbers on a shared machine: the load is printed with them. The deterministic bound (the view adds a
constant few function calls per iteration) is tests/test_viz_live_page.py's.
Run: python benchmarks/viz_live.py [--problem P.toml] [--seed 2] [--repeat 3] [--no-browser]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from crtraj.control.loop import ClosedLoop
from crtraj.io.problem import Problem
from crtraj.viz.chromium import Chromium, find_chromium
from crtraj.viz.live_view import LiveView

ROOT = Path(__file__).resolve().parent.parent


def one_run(problem: Problem, seed: int, view: bool, browser: Chromium | None) -> dict:
    """One loop run; with view: fed to a served live page (open in `browser` if given)."""
    loop = ClosedLoop.from_problem(problem, seed=seed)
    live = LiveView.for_loop(loop) if view else None
    tab = browser.open(live.url, 1280, 800) if live is not None and browser is not None else None
    try:
        run = loop.run(observer=live.feed if live is not None else None)
        counts = {**live.stop_feed(), "cpu": live.feed.draw_cpu} if live is not None else {}
    finally:
        if tab is not None:
            tab.close()
        if live is not None:
            live.close()
    return {"iter": np.asarray(run.iter_time) * 1e3, "misses": run.deadline_misses, "status": str(run.status), **counts}


def line(name: str, it: np.ndarray, extra: str = "") -> str:
    return (
        f"{name:28s} steps {len(it):5d}  median {np.median(it):6.2f} ms  p99 {np.percentile(it, 99):7.2f} ms  "
        f"max {it.max():7.2f} ms{extra}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_dynamic.toml"))
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-browser", action="store_true", help="serve the live page without a browser on it")
    args = ap.parse_args()
    problem = Problem.load(Path(args.problem))
    print(f"date {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; machine {platform.node()} {platform.machine()}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}; load {os.getloadavg()}")  # fmt: skip
    exe = None if args.no_browser else find_chromium()
    browser = Chromium(exe, timeout=300.0) if exe else None
    print(f"problem {args.problem}, seed {args.seed}, {args.repeat} runs each, alternating; "
          f"live page {'open in headless Chromium' if browser else 'served, no browser'}")  # fmt: skip
    pooled: dict[bool, list[np.ndarray]] = {False: [], True: []}
    try:
        one_run(problem, args.seed, False, None)  # builds and caches the solvers: not measured
        for i in range(args.repeat):
            for view in (False, True):
                r = one_run(problem, args.seed, view, browser)
                pooled[view].append(r["iter"])
                extra = f"  deadline misses {r['misses']:3d}  {r['status']}"
                if view:
                    extra += (
                        f"  frames: {r['published']} published, {r['drawn']} drawn, {r['dropped']} dropped;"
                        f" view thread CPU {1e3 * r['cpu'] / max(1, r['drawn']):.1f} ms per draw"
                    )
                print(line(f"run {i + 1} {'with' if view else 'without'} --view", r["iter"], extra), flush=True)
    finally:
        if browser is not None:
            browser.close()
    print(line("pooled without --view (old)", np.concatenate(pooled[False])))
    print(line("pooled with --view (new)", np.concatenate(pooled[True])))
    print(f"load after {os.getloadavg()}")


if __name__ == "__main__":
    main()
