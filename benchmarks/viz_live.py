"""The closed loop's iteration time with and without the live view (`crtraj replan --view`), and the view's frames.

Issue 30: the live view updates the page at up to 30 Hz from its own thread "so the loop's timing does not change".
This runs the paper's simulation 2 (problems/paper_dynamic.toml, one seed) alternately without the view and with
it (a served `crtraj.viz.live.LiveView`, its page open in headless Chromium when there is one, so the server
really pushes to a browser), and prints per run and pooled: the loop's iteration time (median, p99, max), its
deadline misses, and the view's frames (published, drawn, dropped, drawn per second of the run) with the CPU each
part of the view spent per drawn frame: the feed thread (in the loop's process, holding the interpreter lock), the
drawing process, the meshcat server and the browser (all of Chromium's processes). Old path = without the view,
new = with it. Wall-clock numbers on a shared machine: the load before and after is printed with them, and the
other processes' CPU use during the runs. The deterministic bound (the view adds a constant few function calls
per iteration) is tests/test_viz_live_page.py's.
A deadline miss changes a run's path (and the solves on it: the p99 of a run that missed once early is about twice
a clean run's, with or without the view), so runs are comparable only on the same path: --no-deadline drops the
step deadline, every run then takes the same path, and the iterations longer than the deadline are counted.
Run: python benchmarks/viz_live.py [--problem P.toml] [--seed 2] [--repeat 3] [--no-browser] [--no-deadline]
[--nice N [N ...]]
(--nice 0 19: the view at both niceness levels, alternating with the runs without it, as rows of one table).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from crtraj.control.horizon._options import ReplanOptions
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.io.problem import Problem
from crtraj.viz.chromium import Chromium, find_chromium
from crtraj.viz.live._view import VIEW_NICE, LiveView

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


def one_run(problem: Problem, seed: int, view: bool, browser: Chromium | None, nice: int | None, opts) -> dict:
    """One loop run (replan options `opts`); with view: fed to a served live page (open in `browser` if given)."""
    loop = ClosedLoop.from_problem(problem, seed=seed, options=opts)
    live = LiveView.for_loop(loop, nice=nice) if view else None
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
        counts = {**live.stop_feed(), "cpu": live.feed.draw_cpu, "rate": live.feed.draw_rate()} if live else {}
    finally:
        if tab is not None:
            tab.close()
        if live is not None:
            live.close()
    return {"iter": np.asarray(run.iter_time) * 1e3, "misses": run.deadline_misses, "status": str(run.status),
            "path": (len(run.t), tuple(run.step_status)),
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
        f"\n{'':28s} frames: {r['published']} published, {r['drawn']} drawn ({r['rate']:.1f} per s; the loop stepped "
        f"{r['stepping']:.2f} s), "
        f"{r['dropped']} dropped; CPU per drawn frame: feed thread {1e3 * r['cpu'] / n:.2f} ms, drawing process "
        f"{1e3 * u['child'] / n:.2f} ms, server {1e3 * u['server'] / n:.2f} ms, browser {1e3 * u['browser'] / n:.2f} ms"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_dynamic.toml"))
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-browser", action="store_true", help="serve the live page without a browser on it")
    ap.add_argument(
        "--no-deadline",
        action="store_true",
        help="drop replan.step_deadline: every run takes the same path (a miss makes a run take another "
        "path, with other solves), and the iterations over the problem's deadline are counted instead",
    )
    ap.add_argument(
        "--quiet",
        type=float,
        default=0.1,
        help="cores the other processes may use in a run counted as quiet (default 0.1)",
    )
    ap.add_argument("--nice", type=int, nargs="+", default=[VIEW_NICE],
                    help=f"niceness of the view's processes; several: each a row (default {VIEW_NICE})")  # fmt: skip
    args = ap.parse_args()
    problem = Problem.load(Path(args.problem))
    opts = problem.options(ReplanOptions, "replan")
    deadline = opts.step_deadline * 1e3  # ms
    if args.no_deadline:
        opts = dataclasses.replace(opts, step_deadline=0.0)
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    print(f"date {time.strftime('%Y-%m-%d %H:%M:%S %Z')}; machine {platform.node()} {platform.machine()}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}; commit {rev.stdout.strip() or '?'}; "
          f"load {os.getloadavg()}")  # fmt: skip
    exe = None if args.no_browser else find_chromium()
    browser = Chromium(exe, timeout=300.0) if exe else None
    configs = [("without --view (old)", None)] + [(f"with --view, nice {n} (new)", n) for n in args.nice]
    print(f"problem {args.problem}, seed {args.seed}, step deadline "
          f"{'none (dropped: every run takes the same path)' if args.no_deadline else f'{deadline:g} ms'}, "
          f"{args.repeat} runs each, alternating: "
          f"{', '.join(c for c, _ in configs)}; live page "
          f"{'open in headless Chromium' if browser else 'served, no browser'}")  # fmt: skip
    pooled: dict[str, list[dict]] = {c: [] for c, _ in configs}
    try:
        one_run(problem, args.seed, False, None, None, opts)  # builds and caches the solvers: not measured
        for i in range(args.repeat):
            for name, nice in configs:
                r = one_run(problem, args.seed, nice is not None, browser, nice, opts)
                pooled[name].append(r)
                r["over"] = int(np.sum(r["iter"] > deadline)) if deadline > 0 else 0
                extra = (f"  misses {r['misses']:3d}, over {deadline:g} ms {r['over']:3d}  {r['status']}; "
                         f"others' CPU {r['others'] / r['wall']:.2f} cores")  # fmt: skip
                if nice is not None:
                    extra += frames_text(r)
                print(line(f"run {i + 1} {name.removesuffix(' (old)').removesuffix(' (new)')}", r["iter"], extra),
                      flush=True)  # fmt: skip
    finally:
        if browser is not None:
            browser.close()
    base = configs[0][0]
    it = {c: np.concatenate([r["iter"] for r in rs]) for c, rs in pooled.items()}
    miss = {c: sum(r["misses"] for r in rs) for c, rs in pooled.items()}
    over = {c: sum(r["over"] for r in rs) for c, rs in pooled.items()}
    paths = [r["path"] for rs in pooled.values() for r in rs]
    same = sum(p == paths[0] for p in paths)
    print(f"runs on the first run's path (same steps, same statuses): {same} of {len(paths)}")
    p99 = {c: np.percentile(v, 99) for c, v in it.items()}
    med = {c: np.median([np.percentile(r["iter"], 99) for r in rs]) for c, rs in pooled.items()}
    for name, nice in configs:
        extra = f"  misses {miss[name]}, over {deadline:g} ms {over[name]}"
        if nice is not None:
            rs = pooled[name]
            drawn, published = sum(r["drawn"] for r in rs), sum(r["published"] for r in rs)
            extra += (f"\n{'':28s} p99 / without's: pooled {p99[name] / p99[base]:.3f}, median of the runs' p99 "
                      f"{med[name] / med[base]:.3f} (issue 30: <= 1.10); deadline misses {miss[name] - miss[base]:+d}, "
                      f"iterations over {deadline:g} ms {over[name] - over[base]:+d} (target 0); frames drawn {drawn} "
                      f"of {published} published, {np.nanmedian([r['rate'] for r in rs]):.1f} per s")  # fmt: skip
        print(line(f"pooled {name}", it[name], extra))
    quiet_rows(pooled, paths[0], args.quiet)
    print(f"load after {os.getloadavg()}")


def quiet_rows(pooled: dict[str, list[dict]], path, cores: float) -> None:
    """The same pooled rows over the runs on `path` during which the other processes used under `cores` cores (on
    a shared machine, the runs that measure the loop and the view alone)."""
    print(f"runs on the first run's path while the other processes used under {cores:g} cores:")
    for name, rs in pooled.items():
        rs = [r for r in rs if r["path"] == path and r["others"] / r["wall"] < cores]
        if not rs:
            print(f"  {name}: none")
            continue
        it = np.concatenate([r["iter"] for r in rs])
        p99s = ", ".join(f"{np.percentile(r['iter'], 99):.2f}" for r in rs)
        print(line(f"  {name}", it, f"  misses {sum(r['misses'] for r in rs)}; {len(rs)} runs, p99s {p99s} ms"))


if __name__ == "__main__":
    main()
