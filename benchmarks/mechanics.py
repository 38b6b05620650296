"""Cosserat-rod statics: the time of one warm-started solve of the two-segment robot, and of the compare tool.

What is measured (problems/robots/cdsr2.toml, its [robot.mechanics], gravity on):

- build: constructing `CosseratRod`, once: the old path (``compiled=False``: the SX shooting function
  and CasADi's Newton rootfinder, interpreted) and the new one (generated C from the build cache,
  `crtraj.model.cosserat._compiled`; the first build of a robot compiles, later ones load);
- warm solve: `CosseratRod.solve` for a tension vector a small random step (up to 0.05 N per tendon)
  from the previous solve, as a closed loop or the compare tool calls it; `--solves` of them, each timed
  alone, old path and new path in the same run. Reported: median, 10th and 90th percentile of wall
  time and of the process's CPU time (``time.process_time``, which moves far less with other jobs'
  load on a shared machine), and the median Newton iterations;
- cold solve: the same tensions with ``warm=False`` (from the straight rod), old and new;
- cable-length mode, warm: `CableDrivenRod.solve` (tensions unknown, slack by the active set) for the
  commanded lengths `RodDrive.lengths` gives along a seeded random walk of the actuation (each cable moving by
  up to 0.05 mm per solve, as the closed-loop plant moves between control periods), old path
  (``compiled=False``) and new (generated C, `crtraj.model.cosserat._cable_compiled`), each timed alone;
- compare: `compare_models` over `--samples` configurations (two solves each, one without and one
  with gravity), wall and CPU time, per configuration.

Target (issue 31): warm solve <= 2 ms. The date, the machine and its load average are printed with
the numbers, since the load of other jobs moves wall times on a shared 2-core machine.

Run: python benchmarks/mechanics.py [--solves 200] [--samples 50] [--cable-solves 100]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from crtraj.app.lab._model_compare import compare_models, sample_configs
from crtraj.io.problem import load_robot
from crtraj.model.cosserat._cables import CableDrivenRod
from crtraj.model.cosserat._drive import RodDrive
from crtraj.model.cosserat._statics import CosseratRod, RodLoad
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

ROBOT = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"


def _spread(values: list[float]) -> str:
    """median [p10, p90] in ms."""
    q = np.percentile(np.array(values) * 1e3, [10, 50, 90])
    return f"{q[1]:.2f} ms [p10 {q[0]:.2f}, p90 {q[2]:.2f}]"


def warm_solves(rod: CosseratRod, n: int, warm: bool = True) -> tuple[list[float], list[float], list[int]]:
    """Wall and CPU seconds and Newton iterations of n solves along a seeded random walk of the tensions
    (each tendon moves by up to 0.05 N per solve, independently), warm-started or not. A random walk, not a
    ramp: along a ramp the warm start's secant predictor would be nearly exact and flatter the figure."""
    rng = np.random.default_rng(0)
    tau = np.array([6.0, 0.0, 1.0, 0.0, 4.0, 0.0])
    rod.solve(tau, RodLoad())
    walls, cpus, iters = [], [], []
    for i in range(n):
        tau = np.maximum(tau + rng.uniform(-0.05, 0.05, tau.size), 0.0)
        w0, c0 = time.perf_counter(), time.process_time()
        sol = rod.solve(tau, RodLoad(), warm=warm)
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
        iters.append(sol.iterations)
        if not sol.is_success():
            raise RuntimeError(f"solve {i} failed: {sol.status}")
    return walls, cpus, iters


def cable_solves(drive: RodDrive, rod: CableDrivenRod, n: int) -> tuple[list[float], list[float], list[int]]:
    """Wall and CPU seconds and Newton iterations of n warm cable-length solves (gravity on) along a seeded
    random walk of the actuation: each cable moves by up to 0.05 mm per solve, the base stage stays; the
    commanded lengths are `drive`'s (its own rod is not used)."""
    rng = np.random.default_rng(0)
    robot = drive.robot
    q = robot.cables(robot.straight(0.0)) + np.concatenate([[1.0, -0.5, 0.5, -1.0], np.zeros(robot.nq - 4)])
    rod.solve(drive.lengths(q), RodLoad())
    walls, cpus, iters = [], [], []
    for i in range(n):
        q = q + np.concatenate([rng.uniform(-0.05, 0.05, robot.nq - 1), [0.0]])
        ell = drive.lengths(q)
        w0, c0 = time.perf_counter(), time.process_time()
        sol = rod.solve(ell, RodLoad())
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
        iters.append(sol.rod.iterations)
        if not sol.is_success():
            raise RuntimeError(f"cable solve {i} failed: {sol.rod.status}")
    return walls, cpus, iters


def cable_mode(robot: Robot, mech: Mechanics, n: int) -> None:
    """Print the cable-length mode's build and warm solves, old and new path."""
    drive = RodDrive(robot, mech, pretension=1.0)  # the length map (builds or loads the compiled rod once)
    for name, compiled in (("old (interpreted)", False), ("new (compiled)", True)):
        t = time.perf_counter()
        rod = CableDrivenRod(robot, mech, compiled=compiled)
        rod.solve(drive.lengths(robot.cables(robot.straight(0.0))), RodLoad())
        print(f"cable-length mode, {name}: build and first solve {time.perf_counter() - t:.2f} s")
        walls, cpus, iters = cable_solves(drive, rod, n)
        print(f"warm cable-length solve, {name}, {n} solves: wall {_spread(walls)}; CPU {_spread(cpus)}")
        print(f"  Newton iterations: median {statistics.median(iters):g}, max {max(iters)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solves", type=int, default=200)
    ap.add_argument("--samples", type=int, default=50)
    ap.add_argument("--cable-solves", type=int, default=100)
    args = ap.parse_args()
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"{stamp}, {platform.node()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    robot = load_robot(ROBOT)
    mech = Mechanics.from_robot(robot)
    rods = {}
    for name, compiled in (("old (interpreted)", False), ("new (compiled)", True)):
        t = time.perf_counter()
        rods[name] = CosseratRod(robot, mech, compiled=compiled)
        rods[name].solve(np.zeros(6), RodLoad(), warm=False)  # the interpreted path builds its graphs here
        print(f"{name}: build and first solve {time.perf_counter() - t:.2f} s ({mech.steps} RK4 steps per segment)")
    for kind, warm in (("warm", True), ("cold", False)):
        for name, rod in rods.items():
            walls, cpus, iters = warm_solves(rod, args.solves, warm)
            print(f"{kind} solve, {name}, {args.solves} solves: wall {_spread(walls)}; CPU {_spread(cpus)}")
            print(f"  Newton iterations: median {statistics.median(iters):g}, max {max(iters)}")
    cable_mode(robot, mech, args.cable_solves)
    configs = sample_configs(robot, args.samples, np.random.default_rng(0))
    w0, c0 = time.perf_counter(), time.process_time()
    cmp = compare_models(robot, mech, configs)
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    print(
        f"compare, {args.samples} configurations: wall {wall:.2f} s, CPU {cpu:.2f} s "
        f"({1e3 * cpu / args.samples:.1f} ms CPU each, build included), {cmp.failures} failed"
    )
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
