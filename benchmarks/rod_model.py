"""Planning for the rod's body (issue 40): the rod model's error, its build time, and planning time PCC vs rod.

What is measured (problems/robots/cdsr2.toml unless --robot, its [robot.mechanics], gravity on):

- build: `load_rod_model` with the default options. With --cold into a fresh temporary cache (the surrogate's
  grid of rod solves, its held-out check, the fit and the model's held-out check), wall and CPU time; without,
  from the shared build cache (``$CRTRAJ_CACHE_DIR``), which is a load;
- error: the model's body against fresh rod solves (the robot file's actuation mode, gravity) at every rod
  integration node, the nodes `crtraj verify --model cosserat` checks, on --holdout seeded random
  configurations within the limits that neither the fit nor the model's own held-out check used: largest
  and 95th-percentile distance over the body and at the tip (mm); PCC's body against the same solves beside it;
- plan: `crtraj.app.plan.plan_problem` on each --problems file for seeds 1..--seeds, PCC and rod interleaved in
  one process (models and compiled kernels loaded before the clock starts): the planner's ``total`` (safe goal
  IK, search, shortcuts, smoothing), median and sum per model and their ratio; with --verify every plan is
  checked by fresh rod solves (`crtraj.app.lab.verify_cosserat`) and the passes are counted.

- replan (--replan PROBLEM): the closed loop of `crtraj replan PROBLEM --model M --plant cosserat` (the problem's
  seed, the rod plant with gravity, no tip feedback, the problem's step deadline) in one process: PCC and the rod
  with the horizon's first-order correction (the path `--model rod` takes) alternately for --rounds rounds (their
  iteration times also pooled), then once the rod with the full correction built into the horizon NLP (the
  earlier path, interpreted: `Replanner(rod_linear=False)`). Per run: the loop iteration (median / p90 / p99,
  ms), the NLP's share, deadline misses, the step outcomes, the plant rod's final tip error and collisions; for
  the new path also the first-order model's error over the moves the loop made (about each step's start
  configuration, at the next one) and its stated bound over one step's reach.

The date, the machine and its load average are printed with the numbers: other jobs' load moves wall
times on a shared 2-core machine.

Run: python benchmarks/rod_model.py [--holdout 1000] [--seeds 10] [--verify] [--cold] [--replan PROBLEM] [--rounds 3]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import functools
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.app.lab import verify_cosserat
from crtraj.app.plan import plan_problem
from crtraj.app.plant_sim import attach_plant, make_plant
from crtraj.control.horizon._replanner import Replanner, linearisation_bound
from crtraj.control.horizon._rod_body import LinearCorrection
from crtraj.control.loop import ClosedLoop
from crtraj.io.problem import Problem, load_robot
from crtraj.io.results import read_result
from crtraj.model.cosserat import RodModel, load_rod_model, sample_within_limits
from crtraj.model.cosserat._surrogate import RodSampler
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

ROOT = Path(__file__).resolve().parent.parent


def build(robot: Robot, cold: bool) -> RodModel:
    """The rod model of `robot`, built into a fresh cache (cold) or loaded from the shared one; timed."""
    w0, c0 = time.perf_counter(), time.process_time()
    if cold:
        with tempfile.TemporaryDirectory() as tmp:
            model = load_rod_model(robot, cache_dir=tmp)
    else:
        model = load_rod_model(robot)
    kind = "cold build (fresh cache)" if cold else "load from the shared cache"
    print(f"rod model, {kind}: {time.perf_counter() - w0:.1f} s wall, {time.process_time() - c0:.1f} s CPU")
    print(f"  stated: {model.error.text()}; margin {model.planning_margin:.3f} mm")
    c = model.correction
    print(
        f"  degree {int(c.exps.sum(axis=1).max())}, {len(c.exps)} monomials, "
        f"{c.basis.shape[0]} modes of {c.basis.shape[1]} numbers"
    )
    return model


def error(model: RodModel, n: int) -> None:
    """The model's and PCC's body against n fresh rod solves at every rod node (new seeded configurations)."""
    robot = model.robot
    sampler = RodSampler(robot, Mechanics.from_robot(robot), 1.0)
    f = model.points_at_arcs(sampler.node_arcs)
    xs = sample_within_limits(robot, n, np.random.default_rng([9, 9, 9]))
    body, tip, pbody = [], [], []
    w0 = time.perf_counter()
    for x in xs:
        shape = sampler.drive.shape_config(x)
        if not shape.is_success():
            raise RuntimeError(f"rod solve failed at {x.tolist()}")
        d = np.linalg.norm(np.asarray(f(x)).T - shape.points, axis=1)
        body.append(d.max())
        tip.append(d[-1])
        arcs = sampler.arcs  # PCC at the collision points, against the rod there (spline along its nodes)
        rod_pts = np.array([np.interp(arcs, sampler.node_arcs, shape.points[:, i]) for i in range(3)]).T
        pbody.append(np.linalg.norm(sampler.pcc_points(x) - rod_pts, axis=1).max())
    b, t, p = np.array(body), np.array(tip), np.array(pbody)
    print(f"error over {n} held-out configurations ({time.perf_counter() - w0:.1f} s of rod solves):")
    print(f"  rod model: body max {b.max():.3f} mm (p95 {np.percentile(b, 95):.3f}), tip max {t.max():.3f} mm "
          f"(p95 {np.percentile(t, 95):.3f}); stated bound {model.planning_margin:.3f} mm")  # fmt: skip
    print(f"  PCC:       body max {p.max():.2f} mm (p95 {np.percentile(p, 95):.2f}) at the collision points")


def plans(path: Path, rod: RodModel, seeds: int, verify: bool) -> None:
    """PCC and rod plans of `path` for seeds 1..seeds, interleaved; planning time and (verify) rod passes."""
    problem = Problem.load(path)
    models = {"pcc": Model(problem.robot), "rod": rod}
    for m in models.values():
        plan_problem(problem, model=m, seed=1)  # loads or builds the compiled kernels
    times: dict[str, list[float]] = {k: [] for k in models}
    ok = {k: 0 for k in models}
    passed = {k: 0 for k in models}
    for seed in range(1, seeds + 1):
        for name, m in models.items():
            run = plan_problem(problem, model=m, seed=seed)
            times[name].append(run.result.timings.get("total", float("nan")) * 1e3)
            ok[name] += run.result.is_success()
            if verify and run.result.is_success():
                v = verify_cosserat(read_result(run.document()), problem.robot)
                passed[name] += v.failed == 0 and v.rod.clearance >= 0.0
    print(f"{path.name}, seeds 1-{seeds}:")
    for name in models:
        ts = times[name]
        line = f"  {name}: median {statistics.median(ts):.1f} ms, sum {sum(ts):.0f} ms, {ok[name]}/{seeds} found"
        print(line + (f", {passed[name]}/{ok[name]} pass verify --model cosserat" if verify else ""))
    ratio = statistics.median(times["rod"]) / statistics.median(times["pcc"])
    print(f"  rod / PCC: {ratio:.2f} x (medians), {sum(times['rod']) / sum(times['pcc']):.2f} x (sums)")


@contextlib.contextmanager
def _full_rod_horizon() -> Any:
    """The loop's replanner built with the full correction in the NLP (the earlier path), for one run."""
    from crtraj.control.loop import _setup

    saved = _setup.Replanner
    _setup.Replanner = functools.partial(Replanner, rod_linear=False)
    try:
        yield
    finally:
        _setup.Replanner = saved


def replan(path: Path, rounds: int) -> None:
    """The closed loop of `path` on the rod plant: PCC and rod (first order) alternately for `rounds` rounds, then
    rod (full correction, the old path) once; each run's figures, then the rounds' pooled step times."""
    problem = Problem.load(path)
    print(f"{path.name}, closed loop on the rod plant (gravity, no tip feedback), seed {problem.seed}:")
    runs = [("pcc", "pcc", False), ("rod, first order", "rod", False)] * rounds + [("rod, full (old)", "rod", True)]
    pooled: dict[str, list[np.ndarray]] = {}
    for name, body, old in runs:
        it = _replan_run(problem, name, body, old)
        pooled.setdefault(name, []).append(it)
    print(f"  pooled over {rounds} round(s), interleaved:")
    for name, its in pooled.items():
        it = np.concatenate(its)
        p50, p90, p99 = np.percentile(it, [50, 90, 99])
        print(f"    {name}: loop iteration median {p50:.2f} / p90 {p90:.2f} / p99 {p99:.2f} ms over {len(it)} steps")


def _replan_run(problem: Problem, name: str, body: str, old: bool) -> np.ndarray:
    """One closed loop on the rod plant; prints its figures; returns its loop iteration times (ms)."""
    w0 = time.perf_counter()
    plant = make_plant("cosserat", problem)
    with _full_rod_horizon() if old else contextlib.nullcontext():
        loop = ClosedLoop.from_problem(problem, body=body, tip_sensor=plant)
    attach_plant(plant, loop)
    built = time.perf_counter() - w0
    load = os.getloadavg()[0]
    run = loop.run(device=plant)
    s, pl = run.summary(), plant.describe()
    it, nlp = run.iter_time * 1e3, run.nlp_time * 1e3
    p50, p90, p99 = np.percentile(it, [50, 90, 99])
    print(f"  {name}: {loop.describe_nlp()['solver']}, built in {built:.1f} s, load average {load:.1f}")
    print(f"    loop iteration median {p50:.2f} / p90 {p90:.2f} / p99 {p99:.2f} ms (NLP median "
          f"{np.median(nlp):.2f} ms); {s['deadline_misses']} of {s['steps']} steps past the "
          f"{s['step_deadline_s'] * 1e3:g} ms deadline; steps {s['status_counts']}")  # fmt: skip
    print(f"    reached {s['reached_goal']}; rod tip {pl['final_tip_error_mm']:.2f} mm off the goal; "
          f"rod collisions {pl['collisions']}, D_sf breaches {pl['safety_violations']}")  # fmt: skip
    if loop.replanner.linear is not None:
        _linear_error(loop.replanner.linear, run.x, linearisation_bound(loop.replanner))
    return it


def _linear_error(lin: LinearCorrection, xs: np.ndarray, bound: float | None) -> None:
    """The first-order model about each step's configuration, at the next step's, against the full correction."""
    exact, _ = lin.values(xs[1:])
    at, J = lin.values(xs[:-1])
    approx = at + np.einsum("nkb,nb->nk", J, (xs[1:] - xs[:-1])[:, : lin.nb])
    err = np.linalg.norm((exact - approx).reshape(len(approx), -1, 3), axis=2).max(axis=1)
    print(f"    first-order error over the loop's {len(err)} moves: max {err.max():.3f} mm, p99 "
          f"{np.percentile(err, 99):.3f} mm; stated bound over one step's full reach {bound:.3f} mm")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default=str(ROOT / "problems" / "robots" / "cdsr2.toml"))
    ap.add_argument("--holdout", type=int, default=1000)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--problems", nargs="*", default=[str(ROOT / "problems" / "paper_static.toml")])
    ap.add_argument("--verify", action="store_true", help="check every plan with fresh rod solves")
    ap.add_argument("--cold", action="store_true", help="build the rod model into a fresh cache")
    ap.add_argument("--replan", nargs="*", default=[], help="problems whose closed loop is run (e.g. paper_dynamic)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved PCC / rod loops per --replan problem")
    args = ap.parse_args()
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"{stamp}, {platform.node()}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    robot = load_robot(args.robot)
    rod = build(robot, args.cold)
    if args.holdout > 0:
        error(rod, args.holdout)
    for p in args.problems:
        other = Problem.load(p).robot
        plans(Path(p), rod if other.name == robot.name else load_rod_model(other), args.seeds, args.verify)
    for p in args.replan:
        replan(Path(p), args.rounds)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
