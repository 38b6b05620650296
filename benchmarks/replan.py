"""Receding-horizon replanning on the paper's simulation 2 (problems/paper_dynamic.toml), against the paper.

Targets (issue 6): reaches the goal, zero collisions (clearance > 0 at every
verification sample, i.e. densely in time, not only at steps), median time
per replanning iteration <= 20 ms (paper: 4.64 s), final tip error <= 0.5 mm
(paper: 0.47 mm); and with the collision-free terms off the clearance goes
negative (paper Fig. 4b).

An iteration is everything the controller does in one 0.1 s step: reference
check (and replanning when needed), horizon NLP, tracking simulation and the
dense verification of the move. Each configuration runs the closed loop for
several planner seeds; the figures pool all iterations.

Variants: "compiled" is the problem as shipped (qp_obstacles = 3: a scene of more obstacles gets a QP of 3
slots filled by the horizon's broad phase; "compiled-all" is the previous path, every obstacle in the QP,
qp_obstacles = 0; on simulation 2's two spheres the two are the same computation): the horizon's sqpmethod + daqp
generated as C (compiled once into the build cache, called through ctypes), a
4 ms step deadline, 1 SQP iteration per call (max_calls 60), and reference
paths planned by a worker process beside the loop ([loop] reference_delay =
0.2 s). "compiled-inline": the same with each reference path planned inside
the step that asks for it (reference_delay = 0, the previous round's loop).
"compiled-unfused": "compiled" with the solver, its KKT check and the row check as two C calls and numpy
(fused = false; "compiled" makes them one generated C call on preallocated parameter buffers, issue 29).
"compiled-3it": "compiled" with the previous stop's three SQP iterations per solver call (max_iter 3, max_calls 20;
the problem now runs one per call, issue 29). "compiled-prev": the previous stop's path as a whole (three
iterations a call, fused = false, the heap left to the garbage collector during the steps, the obstacle spheres
computed in every step). "compiled-untabled": "compiled" with the obstacle spheres computed in every step instead
of looked up in the table of the run's step times (`crtraj.control.horizon._obstacles`).
"sqp-hpipm", "compiled-hpipm": the horizon QP in stage form (state (x_k, x_k-1), input x_k+1) solved by
HPIPM (issue 29), interpreted as "sqp" runs and as generated C as "compiled" runs.
"compiled-old": the compiled solver with the QP of the previous round (every
backbone point of every step, closest_points = 0; dual tolerance 1e-6), 60
iterations, no deadline, inline references. "sqp", "sqp-qrqp", "ipopt": the
interpreted solvers as the previous submission ran the problem (no deadline, 60
iterations, inline references). All variants run in one process, so their
ratios are fair on a loaded machine.

Issue 14's target: iteration median <= 2 ms and p99 <= 4 ms, with a hard
deadline. 'p99 w/o plan' leaves out the iterations that planned a reference
path or took one over; 'misses' counts the steps whose NLP result came after
the deadline (they fall back to the last verified plan or a verified hold).

Run: python benchmarks/replan.py [--seeds 3] [--deadline 0.002]
         [--solvers compiled,compiled-prev,compiled-untabled,compiled-unfused,compiled-3it,compiled-all,compiled-old,
                    sqp,ipopt,sqp-qrqp,sqp-hpipm,compiled-hpipm]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import os
import platform
import time
from pathlib import Path
from unittest import mock

import numpy as np

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import _closed_loop as loop_module
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.control.loop._options import LoopOptions
from crtraj.core.fileio import read_toml
from crtraj.io.problem import Problem

ROOT = Path(__file__).resolve().parent.parent
PAPER = read_toml(ROOT / "benchmarks" / "paper_results.toml")  # the paper's figures (a copy of its reference file)

# [replan] overrides per variant, on top of the problem's (problems/paper_dynamic.toml: compiled, a 4 ms step
# deadline, max_iter 1 per call, max_calls 60)
VARIANTS = {
    # the interpreted paths, as the previous submission ran them: no deadline, 60 iterations, inline references
    "sqp": {"solver": "sqp", "qpsol": "daqp", "compiled": False, "step_deadline": 0.0, "max_iter": 60, "max_calls": 1},
    "sqp-qrqp": {"solver": "sqp", "qpsol": "qrqp", "compiled": False, "step_deadline": 0.0, "max_iter": 60},
    "ipopt": {"solver": "ipopt", "compiled": False, "step_deadline": 0.0, "max_iter": 60, "max_calls": 1},
    "compiled": {"solver": "sqp", "qpsol": "daqp", "compiled": True},
    # issue 29's old path: the solver call, then the KKT call, then the row check in numpy (fused = false)
    "compiled-unfused": {"solver": "sqp", "qpsol": "daqp", "compiled": True, "fused": False},
    # the previous path: every obstacle of the scene in the QP, no broad phase (the switch: qp_obstacles = 0)
    "compiled-all": {"solver": "sqp", "qpsol": "daqp", "compiled": True, "qp_obstacles": 0},
    # issue 29: the problem's one SQP iteration per solver call (a real-time iteration from the shifted warm
    # start) against the previous stop's three (max_iter 3, max_calls 20: at most the same 60 iterations)
    "compiled-3it": {"solver": "sqp", "qpsol": "daqp", "compiled": True, "max_iter": 3, "max_calls": 20},
    # the previous stop's path as a whole: three iterations a call, solver and KKT check as two calls, the numpy
    # row check and the parameters by concatenation (fused = false)
    "compiled-prev": {"solver": "sqp", "qpsol": "daqp", "compiled": True, "max_iter": 3, "max_calls": 20,
                      "fused": False},
    "compiled-inline": {"solver": "sqp", "qpsol": "daqp", "compiled": True},
    # "compiled" with the obstacle spheres computed in every step (the table of the run's step times off)
    "compiled-untabled": {"solver": "sqp", "qpsol": "daqp", "compiled": True},
    # issue 29: the stage-form QP for HPIPM (`crtraj.control.horizon._stage`), interpreted as "sqp" runs, and
    # as generated C as "compiled" runs (the problem's deadline)
    "sqp-hpipm": {"solver": "sqp", "qpsol": "hpipm", "compiled": False, "step_deadline": 0.0, "max_iter": 60,
                  "max_calls": 1},
    "compiled-hpipm": {"solver": "sqp", "qpsol": "hpipm", "compiled": True},
    "compiled-old": {
        "solver": "sqp", "qpsol": "daqp", "compiled": True, "closest_points": 0, "tol": 1e-6,
        "step_deadline": 0.0, "max_iter": 60, "max_calls": 1,
    },
}  # fmt: skip
# [loop] overrides per variant (the others take the problem's [loop], whose reference_delay is 0.2 s)
LOOP_VARIANTS = {
    "sqp": {"reference_delay": 0.0},
    "sqp-qrqp": {"reference_delay": 0.0},
    "ipopt": {"reference_delay": 0.0},
    "compiled-inline": {"reference_delay": 0.0},
    "compiled-old": {"reference_delay": 0.0},
    "sqp-hpipm": {"reference_delay": 0.0},
}


# variants whose loop leaves the heap to the garbage collector during the steps, as before issue 29 (the loop now
# freezes the setup's objects for the run: `crtraj.control.loop._closed_loop._freeze_heap`)
UNFROZEN = {"compiled-prev"}
# variants whose steps compute the horizon's obstacle spheres themselves, as before the table of the run's step times
# (`crtraj.control.horizon._obstacles.ObstacleTable`, issue 29)
UNTABLED = {"compiled-prev", "compiled-untabled"}

# --deadline: the step deadline (s) of the variants that keep the problem's (None: the problem's)
DEADLINE: list[float | None] = [None]


def _one(problem: Problem, name: str, seed: int, safety: bool) -> tuple[object, float]:
    """One closed-loop run of variant `name` for planner seed `seed`: the run and its CPU s per step."""
    base = problem.options(ReplanOptions, "replan")
    if DEADLINE[0] is not None:
        base = dataclasses.replace(base, step_deadline=DEADLINE[0])  # a variant's own deadline still wins
    opts = dataclasses.replace(base, **VARIANTS[name], safety=safety)
    lopts = dataclasses.replace(problem.options(LoopOptions, "loop"), **LOOP_VARIANTS.get(name, {}))
    loop = ClosedLoop.from_problem(problem, seed=seed, options=opts, loop_options=lopts)
    c0 = time.process_time()
    with contextlib.ExitStack() as stack:
        if name in UNFROZEN:
            # the previous stop's loop: the garbage collector's full collections traverse the whole heap in the steps
            stack.enter_context(mock.patch.object(loop_module, "_freeze_heap", lambda: False))
        if name in UNTABLED:
            table = loop.replanner.obstacle_table
            stack.enter_context(mock.patch.object(table, "tabulate", lambda scene, times: None))
        run = loop.run()
    return run, (time.process_time() - c0) / max(1, run.steps)


def run_variants(problem: Problem, names: list[str], seeds: list[int], safety: bool = True) -> list[dict]:
    """Every variant for every seed, interleaved (all variants of one seed before the next seed, so a shared
    machine's load falls on all of them alike); one summary per variant."""
    raw: dict[str, list] = {n: [] for n in names}
    for seed in seeds:
        for n in names:
            raw[n].append(_one(problem, n, seed, safety))
    return [_summary(n, raw[n]) for n in names]


def run_variant(problem: Problem, name: str, seeds: list[int], safety: bool = True) -> dict:
    """One variant over `seeds` (`run_variants` of one)."""
    return run_variants(problem, [name], seeds, safety)[0]


def _summary(name: str, runs: list) -> dict:
    """The figures of one variant from its (run, CPU s per step) pairs."""
    its, nlp, rows, quiet = [], [], [], []
    for run, _ in runs:
        s = run.summary()
        its.append(run.iter_time)
        quiet.append(run.iter_time[run.plan_time == 0.0])
        nlp.append(run.nlp_time)
        rows.append(s)
    it = np.concatenate(its)
    nl = np.concatenate(nlp)
    return {
        "variant": name,
        "runs": len(runs),
        "cpu_step": float(np.mean([c for _, c in runs])),
        "reached": sum(r["reached_goal"] for r in rows),
        "collisions": sum(r["collisions"] for r in rows),
        "breaches": sum(r["safety_violations"] for r in rows),
        "min_clearance": min(r["min_clearance_mm"] for r in rows),
        "min_bound": min(r["min_clearance_bound_mm"] for r in rows),
        "it_med": float(np.median(it)),
        "it_p90": float(np.percentile(it, 90)),
        "it_p99": float(np.percentile(it, 99)),
        "it_p99_np": float(np.percentile(np.concatenate(quiet), 99)),
        "nlp_p99": float(np.percentile(nl, 99)),
        "it_max": float(np.max(it)),
        "nlp_med": float(np.median(nl)),
        "nlp_p90": float(np.percentile(nl, 90)),
        "tip_err": max(r["final_tip_error_mm"] for r in rows),
        "track_err": max(r["max_tracking_error_mm"] for r in rows),
        "duration": float(np.median([r["duration_s"] for r in rows])),
        "plans": sum(r["reference_plans"] for r in rows),
        "misses": sum(r["deadline_misses"] for r in rows),
        "statuses": rows[0]["status_counts"] if len(rows) == 1 else _merge([r["status_counts"] for r in rows]),
    }


def _ratios(new: dict, old: dict) -> str:
    """old / new of the time figures of two variants' summaries."""
    keys = {
        "nlp_med": "NLP median",
        "nlp_p99": "NLP p99",
        "it_med": "iteration median",
        "it_p99": "p99",
        "it_max": "max",
        "cpu_step": "CPU per step",
    }
    return ", ".join(f"{text} x{old[k] / new[k]:.2f}" for k, text in keys.items())


def _comparisons(qp_obstacles: int) -> list[tuple[str, str, str]]:
    """(new variant, old variant, what the ratio compares) for every pair the run may hold."""
    return [
        ("compiled", "sqp", "compiled vs interpreted sqp + daqp"),
        ("compiled", "compiled-unfused", "compiled, one fused C call on preallocated buffers vs solver + KKT calls "
         "and the numpy row check"),
        ("compiled", "compiled-prev", "this stop's step vs the previous stop's (issue 29)"),
        ("compiled", "compiled-3it", "one SQP iteration per call vs three (the previous stop's)"),
        ("compiled", "compiled-untabled", "obstacle spheres looked up in the run's table vs computed every step"),
        ("compiled-3it", "compiled-prev", "three iterations a call: fused call on preallocated buffers vs not"),
        ("compiled", "compiled-inline", "compiled, references beside the loop vs inside the step"),
        ("compiled", "compiled-all", f"compiled, broad phase (qp_obstacles {qp_obstacles}) vs every obstacle in the "
         "QP (qp_obstacles 0)"),
        ("sqp", "sqp-hpipm", "dense QP, daqp vs the stage-form QP, HPIPM (interpreted)"),
        ("compiled", "compiled-hpipm", "dense QP, daqp vs the stage-form QP, HPIPM (compiled)"),
        ("compiled", "compiled-old", "compiled, this round's QP vs the previous round's"),
    ]  # fmt: skip


def _merge(dicts: list[dict]) -> dict:
    out: dict = {}
    for d in dicts:
        for k, v in d.items():
            out[k] = out.get(k, 0) + v
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problem", default=str(ROOT / "problems" / "paper_dynamic.toml"))
    ap.add_argument("--seeds", type=int, default=3, help="planner seeds per configuration (0..N-1)")
    ap.add_argument(
        "--solvers",
        default="compiled,compiled-unfused,compiled-all,compiled-inline,compiled-old,sqp",
        help=f"comma list of {', '.join(VARIANTS)}",
    )
    ap.add_argument("--deadline", type=float, default=None, help="step deadline s (default: the problem's)")
    args = ap.parse_args()
    DEADLINE[0] = args.deadline
    problem = Problem.load(args.problem)
    seeds = list(range(args.seeds))
    names = [s.strip() for s in args.solvers.split(",") if s.strip()]
    for n in names:
        if n not in VARIANTS:
            raise SystemExit(f"--solvers: unknown variant {n!r} (known: {', '.join(VARIANTS)})")
    paper = PAPER["dynamic"]
    print(
        f"crtraj replan benchmark: {problem.name}, seeds {seeds[0]}..{seeds[-1]}, {platform.processor() or 'cpu'}, "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}, python {platform.python_version()}, "
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"
    )
    o = problem.options(ReplanOptions, "replan")
    deadline = o.step_deadline if args.deadline is None else args.deadline
    print(
        f"horizon {o.horizon} x {o.dt:g} s, {o.points} points/config, step deadline {deadline * 1e3:g} ms; "
        "times per control iteration\n"
    )
    head = (
        f"{'variant':<12} {'reached':>8} {'coll.':>6} {'min clr':>8} {'it med':>8} {'it p99':>8} {'w/o plan':>8} "
        f"{'it max':>8} "
        f"{'NLP med':>8} {'NLP p99':>8} {'tip err':>8} {'sim s':>6} {'plans':>6} {'misses':>6} {'cpu/st':>8}"
    )
    print(head)
    print("-" * len(head))
    t0 = time.perf_counter()
    results = run_variants(problem, names, seeds)
    for r in results:
        n = r["variant"]
        print(
            f"{n:<12} {r['reached']:>4}/{r['runs']:<3} {r['collisions']:>6} {r['min_clearance']:>7.2f}m "
            f"{r['it_med'] * 1e3:>6.2f}ms {r['it_p99'] * 1e3:>6.2f}ms {r['it_p99_np'] * 1e3:>6.2f}ms "
            f"{r['it_max'] * 1e3:>6.0f}ms "
            f"{r['nlp_med'] * 1e3:>6.2f}ms {r['nlp_p99'] * 1e3:>6.2f}ms {r['tip_err']:>7.3f}m {r['duration']:>6.1f} "
            f"{r['plans']:>6} {r['misses']:>6} {r['cpu_step'] * 1e3:>6.2f}ms"
        )
    print(
        f"{'paper':<12} {'':>8} {'':>6} {'':>8} {paper['iteration_s'] * 1e3:>6.0f}ms {'':>8} {'':>8} {'':>8} {'':>8} "
        f"{'':>8} {paper['tip_error_mm']:>7.2f}m"
    )
    print(
        "\n(m = mm; 'min clr' = smallest body clearance minus D_sf over every verification sample, 41 backbone "
        "points; 'plans' = reference paths planned, summed over runs; 'w/o plan' = p99 over the iterations "
        "that neither planned nor took over a reference path; 'misses' = NLP results after the step deadline; "
        "'cpu/st' = process CPU time per step of the whole loop, recording included; the variants run "
        "interleaved, seed by seed)"
    )
    by = {r["variant"]: r for r in results}
    print()
    for new_, old_, text in _comparisons(problem.options(ReplanOptions, "replan").qp_obstacles):
        if new_ in by and old_ in by:
            a, b = by[new_], by[old_]
            print(f"{text}: {_ratios(a, b)}; deadline misses {a['misses']} vs {b['misses']}")
    ns = run_variant(problem, names[0], seeds[:1], safety=False)
    print(
        f"\nwithout collision-free terms ({names[0]}, seed 0): min clearance {ns['min_clearance']:.2f} mm, "
        f"{ns['collisions']} steps with the body inside an obstacle, reached {ns['reached']}/1"
    )
    best = results[0]
    print("\ntargets (first variant):")
    checks = [
        ("reaches the goal in every run", best["reached"] == best["runs"]),
        ("zero collisions, clearance > 0 at every sample", best["collisions"] == 0 and best["min_clearance"] > 0),
        (
            f"median iteration <= 20 ms ({best['it_med'] * 1e3:.2f} ms, "
            f"{paper['iteration_s'] / best['it_med']:.0f}x faster than the paper's {paper['iteration_s']} s)",
            best["it_med"] <= 0.020,
        ),
        (
            f"final tip error <= 0.5 mm ({best['tip_err']:.3f} mm; paper {paper['tip_error_mm']} mm)",
            best["tip_err"] <= 0.5,
        ),
        ("no-safety run shows negative clearance", ns["min_clearance"] < 0),
        (f"issue 14: iteration median <= 2 ms ({best['it_med'] * 1e3:.2f} ms)", best["it_med"] <= 0.002),
        (f"issue 14: iteration p99 <= 4 ms ({best['it_p99'] * 1e3:.2f} ms)", best["it_p99"] <= 0.004),
        (f"issue 29: iteration median <= 0.5 ms ({best['it_med'] * 1e3:.2f} ms)", best["it_med"] <= 0.0005),
        (f"issue 29: iteration p99 <= 1 ms ({best['it_p99'] * 1e3:.2f} ms)", best["it_p99"] <= 0.001),
        (f"issue 29: 0 misses at a 2 ms deadline ({best['misses']} at {deadline * 1e3:g} ms)", best["misses"] == 0),
    ]
    for text, ok in checks:
        print(f"  [{'ok' if ok else 'MISSED'}] {text}")
    print(f"\nbenchmark wall time {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
