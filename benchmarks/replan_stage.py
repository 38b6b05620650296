"""The stage-form horizon QP (HPIPM) against the dense one (daqp) as the obstacle count grows (issue 29).

The scenes and the 3 s closed-loop run of benchmarks/scaling_solvers.py (cdsr2, m spheres of 15 mm), every
obstacle in the QP (``qp_obstacles = 0``, where the dense QP's cost grows with the obstacles), sqpmethod
interpreted, and with ``--compiled`` also the generated C of both (the problem's iteration cap). Prints median
iteration and NLP time per obstacle count and their 31-to-1 ratios, with the date, machine and load.

Run: python benchmarks/replan_stage.py [--obstacles 1,31] [--compiled]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from scaling_solvers import replan_ms, scene_for  # noqa: E402 - the scaling benchmark's scenes and run

from crtraj.io.problem import Problem  # noqa: E402
from crtraj.model.kinematics import Model  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--obstacles", default="1,31", help="comma list of obstacle counts")
    ap.add_argument("--compiled", action="store_true", help="also the generated C of both QPs")
    args = ap.parse_args()
    counts = [int(c) for c in args.obstacles.split(",")]
    model = Model(Problem.load(ROOT / "problems" / "paper_static.toml").robot)
    print(
        f"crtraj stage-form vs dense horizon QP: {platform.processor() or 'cpu'}, {os.cpu_count()} cores, load "
        f"average {os.getloadavg()[0]:.1f}, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"
    )
    variants = [("dense daqp", False, "daqp"), ("stage hpipm", False, "hpipm")]
    if args.compiled:
        variants += [("dense daqp C", True, "daqp"), ("stage hpipm C", True, "hpipm")]
    print(f"{'variant':<14} {'obstacles':>9} {'iter med':>9} {'iter p99':>9} {'NLP med':>9}")
    med: dict[tuple[str, int], float] = {}
    for m in counts:
        scene = scene_for(model, m, seed=20 + m)  # as scaling_solvers.py, 2 segments
        for name, compiled, qp in variants:
            it, nlp, p99, _ = replan_ms(model, scene, compiled=compiled, qpsol=qp)
            med[(name, m)] = nlp
            print(f"{name:<14} {m:>9} {it:>7.2f}ms {p99:>7.2f}ms {nlp:>7.2f}ms", flush=True)
    if len(counts) > 1:
        lo, hi = counts[0], counts[-1]
        for name, _, _ in variants:
            print(f"{name}: NLP median at {hi} obstacles / at {lo}: x{med[(name, hi)] / med[(name, lo)]:.2f}")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
