"""Calibration fit time: 2,000 samples, every parameter group, Gauss-Newton vs exact Hessian in one run.

Target (issue 17): fit time <= 2 s for 2,000 samples with all parameters.
Synthetic setup: cdsr2 perturbed (`synthetic_truth`: lengths +-5 %, coupling -0.8, servo zero offsets +-0.05
rad, capture frame rotated 10 degrees and shifted 50 mm), 2,000 random samples within 60 % of the bend limits
(`synthetic_values`), base + proximal tip + distal tip markers with 0.3 mm noise per axis and 2 % outliers of
~20 mm; 20 % held out. "fit" is the whole `crtraj.model.calibration._fit` call (initial capture frame,
identifiability, NLP build and solve, covariance, statistics; wall and CPU time of this process: on a loaded
machine the CPU time is the steadier figure); "solve" is the NLP build and IPOPT solve (wall); "gate" is the
sanity gate on the last fit (time offset, noise estimate, checks; `crtraj.app.lab._calibrate.gate`), wall time.
Run: python benchmarks/calibrate.py [--n 2000] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj.app.lab._calibrate import gate
from crtraj.hardware.actuators import Actuators
from crtraj.io.calibration_data import Dataset
from crtraj.io.problem import load_robot
from crtraj.model.calibration import (
    GROUPS,
    CalibrateOptions,
    Hardware,
    Observations,
    fit,
    paper_markers,
    simulate_markers,
    split,
    synthetic_truth,
    synthetic_values,
)

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    act = Actuators.from_robot(robot)
    hw = Hardware(act.spool_radius, act.sign)
    sites = paper_markers(robot.n_segments)
    truth = synthetic_truth(robot, act.zero_offset, seed=0)
    values = synthetic_values(robot, hw, args.n, seed=1)
    m, _ = simulate_markers(
        truth.robot, hw, truth.zero_offsets, truth.capture, values, sites, noise=0.3, outliers=0.02, seed=2
    )
    obs = Observations(values, m, sites, split(args.n, 0.2, 0))
    print(f"{datetime.now(timezone.utc).isoformat(timespec='seconds')}  {platform.node()}  {platform.processor()}")
    print(f"python {platform.python_version()}, {os.cpu_count()} CPUs, load average {os.getloadavg()}")
    print(f"{args.n} samples x {len(sites)} markers, groups: {', '.join(GROUPS)}; median of {args.repeat} (min..max)")
    for hessian in ("exact", "gauss-newton"):
        opts = CalibrateOptions(hessian=hessian)
        fit(robot, hw, act.zero_offset, obs, GROUPS, opts)  # warm-up
        total, solve, cpu = [], [], []
        for _ in range(args.repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            res = fit(robot, hw, act.zero_offset, obs, GROUPS, opts)
            total.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            solve.append(res.solve_time)
        tip_b, tip_a = res.before["heldout"]["tip"], res.after["heldout"]["tip"]
        print(
            f"hessian {hessian:12s}: fit {statistics.median(total):.2f} s ({min(total):.2f}..{max(total):.2f}), "
            f"CPU {statistics.median(cpu):.2f} s, "
            f"solve {statistics.median(solve):.2f} s ({min(solve):.2f}..{max(solve):.2f}), "
            f"{res.iterations} iterations, {res.status}; {int(res.free.sum())} parameters fitted, "
            f"{len(res.held)} held ({', '.join(h.name for h in res.held)})"
        )
        print(
            f"  held-out tip residual: uncalibrated RMS {tip_b.rms:.2f} mm -> calibrated RMS {tip_a.rms:.2f} mm "
            f"(p95 {tip_a.p95:.2f} mm; without the {tip_a.outliers} outliers {tip_a.rms_inliers:.3f} mm; "
            f"noise {0.3 * np.sqrt(3):.3f} mm)"
        )
        t0 = time.perf_counter()
        verdict = gate(Dataset(act.names, sites, np.arange(args.n, dtype=float), values, m), robot, res)
        print(
            f"  gate: {time.perf_counter() - t0:.2f} s, {'passed' if verdict.ok else 'FAILED: ' + verdict.line()}; "
            f"noise estimated {verdict.noise:.3f} mm per axis (true 0.3)"
        )
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
