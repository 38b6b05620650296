"""FK throughput of the symbolic model: single calls, batched in-process, and the compiled export.

Target (issue 2): batched backbone evaluation >= 200,000 configurations/s on a 2-core machine.
Run: python benchmarks/model.py [--n 20000] [--repeat 7]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np

from crtraj.io.problem import load_robot
from crtraj.model.export import export_model
from crtraj.model.kinematics import Model

ROOT = Path(__file__).resolve().parent.parent


def timed(fn, repeat: int) -> list[float]:
    fn()  # warm-up (builds maps, loads libraries)
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def report(label: str, times: list[float], count: int) -> float:
    rates = sorted(count / t for t in times)
    med = statistics.median(rates)
    print(f"{label:<44s} {med:>12,.0f} configs/s   (min {rates[0]:,.0f}, max {rates[-1]:,.0f})")
    return med


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=20000, help="configurations per batch")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    model = Model(robot)
    rng = np.random.default_rng(0)
    lo, hi = robot.config_box()
    X = rng.uniform(lo, hi, size=(args.n, robot.nx)) * np.r_[np.full(4, 0.4), 1.0]
    print(
        f"machine: {platform.processor() or platform.machine()}, {platform.python_version()}, casadi {ca.__version__}"
    )
    print(f"robot {robot.name}: {robot.n_segments} segments, {model.n_points} backbone points, batch {args.n}\n")

    n_single = 2000
    report("single backbone call (numpy wrapper)", timed(lambda: [model.points(x) for x in X[:n_single]], 3), n_single)
    f = model.backbone
    report("single backbone call (raw CasADi Function)", timed(lambda: [f(x) for x in X[:n_single]], 3), n_single)
    med_batch = report(
        "batched backbone, in-process (Function.map)", timed(lambda: model.points(X), args.repeat), args.n
    )
    report("batched tip position, in-process", timed(lambda: model.tip_position(X), args.repeat), args.n)

    with tempfile.TemporaryDirectory() as tmp:
        batch = 4096
        rep = export_model(model, tmp, batch=batch)
        if rep.library is None:
            print(f"compiled export: skipped ({rep.compiler_message})")
            med_c = float("nan")
        else:
            ext = ca.external("backbone_map", str(rep.library))
            n_calls = args.n // batch
            Xb = [np.ascontiguousarray(X[i * batch : (i + 1) * batch].T) for i in range(n_calls)]
            med_c = report(
                f"batched backbone, compiled export ({batch}/call)",
                timed(lambda: [ext(xb) for xb in Xb], args.repeat),
                n_calls * batch,
            )
            ext1 = ca.external("backbone", str(rep.library))
            report("single backbone call, compiled export", timed(lambda: [ext1(x) for x in X[:n_single]], 3), n_single)
    print(
        f"\ntarget >= 200,000 configs/s batched: in-process {med_batch / 2e5:.2f}x target, compiled {med_c / 2e5:.2f}x"
    )


if __name__ == "__main__":
    main()
