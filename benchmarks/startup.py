"""Start-up: wall time of a whole `crtraj plan problems/paper_static.toml` process, old against new.

Each variant runs the command as a fresh process `--runs` times (hyperfine style: one untimed warm-up
run, then median, min and max of the wall times, and the median CPU time of the process, user +
system, which moves far less with other jobs' load) and reports how much of it was imports (``python -X
importtime``: the cumulative time of ``crtraj.app.plan``) and the planner's own total:

- new, cache warm: this checkout, compiled kernels already in the build cache (the usual case);
- new, interpreted: this checkout with ``CRTRAJ_CC=none`` (no compiler: the interpreted path);
- new, cold cache: this checkout with an empty build cache (the first run after install builds; one run);
- old: a checkout of the code before the compiled core (``--baseline DIR``, e.g. made with
  ``git worktree add /tmp/crtraj-old <commit>``), when given.

Target (issue 14): new, cache warm <= 0.8 s on a 2-core machine (old: 1.8 s).

Bytecode: the processes run as in a user's shell, where Python writes its bytecode cache (``__pycache__``)
at the first import and reuses it: PYTHONDONTWRITEBYTECODE is removed from their environment (a build VM
may set it; with an editable install and no cache ever written, every start then compiles crtraj's modules
from source, about 0.2 s more). Every variant has one untimed warm-up run, which writes the cache.

Run: python benchmarks/startup.py [--runs 10] [--baseline DIR]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROBLEM = ROOT / "problems" / "paper_static.toml"


def run_once(src: Path, env: dict[str, str], out: Path) -> tuple[float, float, float]:
    """One `crtraj plan` process: (wall s, CPU s of the process (user + system), planner total s)."""
    cmd = [sys.executable, "-m", "crtraj.cli", "plan", str(PROBLEM), "--out", str(out)]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run(cmd, cwd=src, env={**env, "PYTHONPATH": str(src)}, capture_output=True, text=True)
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"crtraj plan failed ({proc.returncode}): {proc.stderr.strip()[-300:]}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return wall, cpu, float(json.loads(out.read_text())["timing"].get("total_s", float("nan")))


def import_time(src: Path, env: dict[str, str]) -> float:
    """Seconds to import the plan use case (``python -X importtime``: cumulative time of crtraj.app.plan)."""
    cmd = [sys.executable, "-X", "importtime", "-c", "import crtraj.app.plan"]
    proc = subprocess.run(cmd, cwd=src, env={**env, "PYTHONPATH": str(src)}, capture_output=True, text=True)
    for line in proc.stderr.splitlines():
        parts = line.split("|")
        if len(parts) == 3 and parts[2].strip() == "crtraj.app.plan":
            return int(parts[1]) / 1e6
    return float("nan")


def variant(label: str, src: Path, env: dict[str, str], runs: int, warm: bool = True) -> None:
    """Time one variant and print its row."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "plan.json"
        if warm:
            run_once(src, env, out)
        walls, cpus, totals = [], [], []
        for _ in range(runs):
            w, c, tot = run_once(src, env, out)
            walls.append(w)
            cpus.append(c)
            totals.append(tot)
        imp = import_time(src, env)
    print(
        f"{label:<26s} {statistics.median(walls):7.2f} s  ({min(walls):5.2f}..{max(walls):5.2f})  "
        f"CPU {statistics.median(cpus):5.2f} s  imports {imp:5.2f} s  planner {statistics.median(totals) * 1e3:6.0f} ms"
        f"   n={runs}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--baseline", default=None, help="a checkout of the old code to time beside this one")
    args = ap.parse_args()
    print(
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; machine: {platform.node()} "
        f"{platform.machine()}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; Python "
        f"{platform.python_version()}; command: crtraj plan problems/paper_static.toml --out X"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    print("bytecode cache: on (Python's default; PYTHONDONTWRITEBYTECODE removed)")
    print(f"{'variant':<26s} {'median wall':>9s}  {'(min..max)':>12s}")
    with tempfile.TemporaryDirectory() as cache:
        env["CRTRAJ_CACHE_DIR"] = cache
        variant("new, cold cache (builds)", ROOT, env, 1, warm=False)
        variant("new, cache warm", ROOT, env, args.runs)
        variant("new, interpreted (no cc)", ROOT, {**env, "CRTRAJ_CC": "none"}, args.runs)
        if args.baseline:
            variant("old (baseline checkout)", Path(args.baseline), env, args.runs)
    print(f"load average at the end: {os.getloadavg()[0]:.1f} (a shared machine: compare rows of one run)")


if __name__ == "__main__":
    main()
