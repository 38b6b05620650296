"""The closed loop's iteration time with and without the live view (`crtraj replan --view`), and the view's frames.

Issue 30: the live view updates the page at up to 30 Hz from its own thread "so the loop's timing does not change".
This runs the paper's simulation 2 (problems/paper_dynamic.toml, one seed) alternately without the view and with
it (a served `crtraj.viz.live_view.LiveView`, its page open in headless Chromium when there is one, so the server
really pushes to a browser), and prints per run and pooled: the loop's iteration time (median, p99, max), its
deadline misses, and the view's frames (published, drawn, dropped, drawn per second of the run) with the CPU each
part of the view spent per drawn frame: the feed thread (in the loop's process, holding the interpreter lock), the
drawing process, the meshcat server and the browser (all of Chromium's processes). Old path = without the view,
new = with it. Wall-clock numbers on a shared machine: the load before and after is printed with them, and the
other processes' CPU use during the runs. The deterministic bound (the view adds a constant few function calls
per iteration) is tests/test_viz_live_page.py's.
Run: python benchmarks/viz_live.py [--problem P.toml] [--seed 2] [--repeat 3] [--no-browser] [--nice N]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from crtraj.control.loop import ClosedLoop
from crtraj.io.problem import Problem
from crtraj.viz.chromium import Chromium, find_chromium
from crtraj.viz.live_view import LiveView

ROOT = Path(__file__).resolve().parent.parent
_TICK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int | None, tree: bool = False) -> float:
    """CPU time (user + system, s) of process `pid` so far (with its live descendants when `tree`); 0 if gone."""
    if pid is None:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    total = (int(fields[11]) + int(fields[12])) / _TICK
    if tree:
        for task in Path(f"/proc/{pid}/task").glob("*"):
            try:
                kids = (task / "children").read_text().split()
            except OSError:
                continue
            total += sum(cpu_s(int(k), tree=True) for k in kids)
    return total


def machine_cpu_s() -> float:
    """CPU time (s) every process on the machine spent so far (user, nice, system; from /proc/stat)."""
    f = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    return sum(int(v) for v in f[1:4]) / _TICK


class Stamped:
    """The live view's observer with the wall times of the first and the last step it was told of (to count the
    frames drawn per second of the loop's stepping; two clock reads per step, on the loop's thread)."""

    def __init__(self, feed) -> None:
        self.feed, self.first, self.last = feed, None, None

    def observe(self, state, step) -> None:
        self.feed.observe(state, step)
        if step is not None:
            self.last = time.monotonic()
            self.first = self.first or self.last


def one_run(problem: Problem, seed: int, view: bool, browser: Chromium | None, nice: int | None) -> dict:
    """One loop run; with view: fed to a served live page (open in `browser` if given)."""
    loop = ClosedLoop.from_problem(problem, seed=seed)
    kw = {} if nice is None else {"nice": nice}
    live = LiveView.for_loop(loop, **kw) if view else None
    tab = browser.open(live.url, 1280, 800) if live is not None and browser is not None else None
    bpid = browser.proc.pid if browser is not None and tab is not None else None
    pids = {"child": live.drawer.proc.pid, "server": live.vis.server_pid} if live is not None else {}
    before = {k: cpu_s(p) for k, p in pids.items()} | {"browser": cpu_s(bpid, tree=True)}
    mine0, all0, wall0 = time.process_time(), machine_cpu_s(), time.monotonic()
    try:
        observer = Stamped(live.feed) if live is not None else None
        run = loop.run(observer=observer)
        wall = time.monotonic() - wall0
        stepping = observer.last - observer.first if observer is not None and observer.first else wall
        others = machine_cpu_s() - all0 - (time.process_time() - mine0)
        used = {k: cpu_s(p) - before[k] for k, p in pids.items()}
        used["browser"] = cpu_s(bpid, tree=True) - before["browser"]
        counts = {**live.stop_feed(), "cpu": live.feed.draw_cpu} if live is not None else {}
    finally:
        if tab is not None:
            tab.close()
        if live is not None:
            live.close()
    return {"iter": np.asarray(run.iter_time) * 1e3, "misses": run.deadline_misses, "status": str(run.status),
            "wall": wall, "stepping": stepping, "used": used, "others": others - sum(used.values()),
            **counts}  # fmt: skip


def line(name: str, it: np.ndarray, extra: str = "") -> str:
    return (
        f"{name:28s} steps {len(it):5d}  median {np.median(it):6.2f} ms  p99 {np.percentile(it, 99):7.2f} ms  "
        f"max {it.max():7.2f} ms{extra}"
    )


def frames_text(r: dict) -> str:
    n = max(1, r["drawn"])
    u = r["used"]
    return (
        f"\n{'':28s} frames: {r['published']} published, {r['drawn']} drawn ({r['drawn'] / r['stepping']:.1f} per s of "
        f"stepping, {r['stepping']:.2f} s), "
        f"{r['dropped']} dropped; CPU per drawn frame: feed thread {1e3 * r['cpu'] / n:.2f} ms, drawing process "
        f"{1e3 * u['child'] / n:.2f} ms, server {1e3 * u['server'] / n:.2f} ms, browser {1e3 * u['browser'] / n:.2f} ms"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_dynamic.toml"))
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-browser", action="store_true", help="serve the live page without a browser on it")
    ap.add_argument("--nice", type=int, default=None, help="niceness of the view's processes (default: LiveView's)")
    args = ap.parse_args()
    problem = Problem.load(Path(args.problem))
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    print(f"date {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; machine {platform.node()} {platform.machine()}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}; commit {rev.stdout.strip() or '?'}; "
          f"load {os.getloadavg()}")  # fmt: skip
    exe = None if args.no_browser else find_chromium()
    browser = Chromium(exe, timeout=300.0) if exe else None
    print(f"problem {args.problem}, seed {args.seed}, {args.repeat} runs each, alternating; "
          f"live page {'open in headless Chromium' if browser else 'served, no browser'}; "
          f"view niceness {'default' if args.nice is None else args.nice}")  # fmt: skip
    pooled: dict[bool, list[dict]] = {False: [], True: []}
    try:
        one_run(problem, args.seed, False, None, None)  # builds and caches the solvers: not measured
        for i in range(args.repeat):
            for view in (False, True):
                r = one_run(problem, args.seed, view, browser, args.nice)
                pooled[view].append(r)
                extra = f"  misses {r['misses']:3d}  {r['status']}; others' CPU {r['others'] / r['wall']:.2f} cores"
                if view:
                    extra += frames_text(r)
                print(line(f"run {i + 1} {'with' if view else 'without'} --view", r["iter"], extra), flush=True)
    finally:
        if browser is not None:
            browser.close()
    it = {v: np.concatenate([r["iter"] for r in pooled[v]]) for v in (False, True)}
    miss = {v: sum(r["misses"] for r in pooled[v]) for v in (False, True)}
    print(line("pooled without --view (old)", it[False], f"  misses {miss[False]}"))
    print(line("pooled with --view (new)", it[True], f"  misses {miss[True]}"))
    p99 = {v: np.percentile(it[v], 99) for v in (False, True)}
    med = {v: np.median([np.percentile(r["iter"], 99) for r in pooled[v]]) for v in (False, True)}
    print(f"p99 with / without: pooled {p99[True] / p99[False]:.3f}, median of the runs' p99 "
          f"{med[True] / med[False]:.3f} (issue 30: <= 1.10); deadline misses with - without: "
          f"{miss[True] - miss[False]:+d} (target 0)")  # fmt: skip
    print(f"load after {os.getloadavg()}")


if __name__ == "__main__":
    main()
