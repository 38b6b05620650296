"""Plans for the rod's body (issue 40) on every query set, 20 seeds each: planning time and `verify --model cosserat`.

Query sets (cdsr2 unless the problem says otherwise, its [robot.mechanics], gravity on):

- sim 1: problems/paper_static.toml, seeds 1..--seeds;
- sim 2: problems/paper_dynamic.toml (moving obstacles), seeds 1..--seeds;
- Table I, 3 and 7 obstacles: scenarios 0..--seeds - 1 of `crtraj.bench.scenarios.ScenarioGenerator` (seed 0,
  cdsr2; their start configurations, goals and moving, breathing spheres), planned with paper_static.toml's
  [planner] and [steer] sections and the bench's goal tolerance (1 mm), seed = scenario index + 1;
- side_shelf: problems/side_shelf.toml (cdsr1_side, mounted sideways), seeds 1..--seeds.

Per query, in one process and interleaved (every model and compiled kernel loaded before the clock starts):
PCC, the rod model through the kernel's hand-written correction (`crtraj.planning.validity._rod_body`, the new
path) and, for the time only, the rod model through CasADi's generated correction (main's path before it: the
same expression generated as one function; `--no-old` skips it). The planner's own ``total`` (safe start and goal
IK, search, shortcuts, smoothing: what `crtraj plan` reports as planning time) is the time; the found plans of
PCC and of the rod (new path) are each checked by fresh rod solves (`crtraj.app.lab.verify_cosserat`, what
`crtraj verify --model cosserat` runs: every frame, the robot file's actuation mode, gravity), and the passes
(D_sf holds on the rod at every frame, no failed solve) are counted.

--stages N: instead, where the time goes on sim 1 (seeds 1..N): per planner stage, CPU time and the part in
compiled calls (`benchmarks/plan_stages.py`'s clock), PCC, the rod's new path and the old one.

The date, the machine and its load average are printed with the numbers: other jobs' load moves every wall time
on a shared 2-core machine; the ratios compare models measured side by side.

Run: python benchmarks/rod_plans.py [--seeds 20] [--sets sim1,sim2,table3,table7,shelf] [--no-verify] [--no-old]
     python benchmarks/rod_plans.py --stages 5
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

from crtraj.app.lab import verify_cosserat
from crtraj.app.plan import plan_problem
from crtraj.bench.scenarios import ScenarioGenerator, ScenarioOptions
from crtraj.io.problem import Problem, Task
from crtraj.io.results import read_result
from crtraj.model.cosserat import load_rod_model
from crtraj.model.kinematics import Model
from crtraj.planning.validity import _rod_body

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
SETS = {
    "sim1": "sim 1 (paper_static)",
    "sim2": "sim 2 (paper_dynamic)",
    "table3": "Table I, 3 obstacles",
    "table7": "Table I, 7 obstacles",
    "shelf": "side_shelf (cdsr1_side)",
}
MODELS = ("pcc", "rod", "rod-old")


@contextmanager
def old_path(on: bool) -> Iterator[None]:
    """While on: rod kernels generated as main generated them (the correction inside CasADi's C, their own
    library key), by hiding the rod from `_rod_body.is_rod`."""
    saved = _rod_body.is_rod
    if on:
        _rod_body.is_rod = lambda model: False
    try:
        yield
    finally:
        _rod_body.is_rod = saved


def queries(name: str, seeds: int) -> list[tuple[Problem, int, Any]]:
    """(problem, seed, scene or None) of query set `name`."""
    if name in ("sim1", "sim2", "shelf"):
        file = {"sim1": "paper_static", "sim2": "paper_dynamic", "shelf": "side_shelf"}[name]
        p = Problem.load(ROOT / "problems" / f"{file}.toml")
        return [(p, s, None) for s in range(1, seeds + 1)]
    base = Problem.load(ROOT / "problems" / "paper_static.toml")
    gen = ScenarioGenerator(Model(base.robot), ScenarioOptions(seed=0))
    out = []
    for i in range(seeds):
        sc = gen.generate(int(name[-1]), i)
        task = Task(sc.start_tip, sc.goal, sc.start, 1.0)
        out.append((replace(base, task=task, name=f"table1_{sc.n_obstacles}obs_{i}"), i + 1, sc.scene))
    return out


def run_set(name: str, seeds: int, verify: bool, old: bool) -> dict[str, Any]:
    """Plan every query of set `name` with each model (interleaved); times, found and verified counts."""
    qs = queries(name, seeds)
    robot = qs[0][0].robot
    models = {"pcc": Model(robot), "rod": load_rod_model(robot)}
    names = [m for m in MODELS if m != "rod-old" or old]
    for m in names:  # loads or builds the compiled kernels before the clock
        with old_path(m == "rod-old"):
            plan_problem(qs[0][0], model=models[m.split("-")[0]], seed=qs[0][1], scene=qs[0][2])
    times: dict[str, list[float]] = {m: [] for m in names}
    found = dict.fromkeys(names, 0)
    passed = dict.fromkeys(names, 0)
    for problem, seed, scene in qs:
        for m in names:
            with old_path(m == "rod-old"):
                run = plan_problem(problem, model=models[m.split("-")[0]], seed=seed, scene=scene)
            times[m].append(run.result.timings.get("total", float("nan")) * 1e3)
            ok = run.result.is_success()
            found[m] += ok
            if verify and ok and m != "rod-old":
                v = verify_cosserat(read_result(run.document()), robot)
                passed[m] += v.holds
    return {"times": times, "found": found, "passed": passed, "n": len(qs)}


def print_table(rows: dict[str, dict[str, Any]], verify: bool) -> None:
    """The table: per set, median planning time per model, ratios, found and verified counts."""
    old = any("rod-old" in r["times"] for r in rows.values())
    head = "| queries | PCC median ms | rod median ms | rod / PCC |"
    head += " rod old path ms | old / PCC |" if old else ""
    head += " found PCC / rod |" + (" verify passes PCC | verify passes rod |" if verify else "")
    print(head)
    print("|" + " --- |" * (head.count("|") - 1))
    for name, r in rows.items():
        med = {m: statistics.median(t) for m, t in r["times"].items()}
        n, f, p = r["n"], r["found"], r["passed"]
        line = f"| {SETS[name]}, {n} seeds | {med['pcc']:.1f} | {med['rod']:.1f} | {med['rod'] / med['pcc']:.2f} x |"
        if old:
            line += f" {med['rod-old']:.1f} | {med['rod-old'] / med['pcc']:.2f} x |"
        line += f" {f['pcc']}/{n} / {f['rod']}/{n} |"
        if verify:
            line += f" {p['pcc']}/{f['pcc']} | {p['rod']}/{f['rod']} |"
        print(line)


def stages(n: int) -> None:
    """Where sim 1's planning time goes, per stage, for PCC and the rod's new and old paths (module docstring)."""
    from plan_stages import StageClock

    problem = Problem.load(ROOT / "problems" / "paper_static.toml")
    models = {"pcc": Model(problem.robot), "rod": load_rod_model(problem.robot)}
    for m in MODELS:
        with old_path(m == "rod-old"):
            plan_problem(problem, model=models[m.split("-")[0]], seed=1)
    for m in MODELS:
        clock = StageClock()
        total = []
        with old_path(m == "rod-old"), clock.installed():
            for seed in range(1, n + 1):
                run = plan_problem(problem, model=models[m.split("-")[0]], seed=seed)
                total.append(run.result.timings.get("total", float("nan")) * 1e3)
        print(f"-- {m}: planner total median {statistics.median(total):.1f} ms (wall), seeds 1-{n}")
        for line in clock.rows():
            print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--sets", default=",".join(SETS))
    ap.add_argument("--no-verify", action="store_true")
    ap.add_argument("--no-old", action="store_true")
    ap.add_argument("--stages", type=int, default=0, help="per-stage profile of sim 1 over this many seeds")
    args = ap.parse_args()
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"{stamp}, {platform.node()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}", flush=True)
    if args.stages:
        stages(args.stages)
    else:
        rows = {}
        for name in args.sets.split(","):
            if name not in SETS:
                raise SystemExit(f"--sets: unknown set {name!r} (choose from {', '.join(SETS)})")
            rows[name] = run_set(name, args.seeds, not args.no_verify, not args.no_old)
            print(f"{SETS[name]} done, load average {os.getloadavg()[0]:.2f}", flush=True)
        print_table(rows, not args.no_verify)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
