"""Use case: the held-out dynamic suite from the command line (`crtraj bench suite`).

Generates the scenarios (`crtraj.bench.suite`), runs the planners and the closed-loop replanner on each in
this process, and writes DIR/scenarios.json (every scene in full, so any one can be re-run), DIR/suite.md
(the table) and DIR/suite.json (summaries and every run) together at the end (`crtraj.bench.outputs`): a
refused or interrupted run leaves the files of an earlier run as they were. The scenarios come from the
seed alone, so an interrupted run loses none of them.
"""

from __future__ import annotations

import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from crtraj import __version__
from crtraj.bench.outputs import OutputSet
from crtraj.bench.suite import METHODS, SuiteGenerator, SuiteOptions, SuiteRecord, SuiteRunner
from crtraj.bench.suite_report import header, markdown, results_document
from crtraj.core.errors import InputError
from crtraj.core.fileio import check_output_file, check_outputs_not_inputs, json_document, to_jsonable
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.planners import BUILTIN

# What the suite writes into --out.
SUITE_FILES = ("scenarios.json", "suite.md", "suite.json")


def _planners(text: str | None) -> tuple[str, ...]:
    if not text:
        return METHODS
    names = tuple(s.strip() for s in text.split(",") if s.strip())
    if not names:
        raise InputError("--planners: empty list")
    return names


def run_suite(args: Any) -> int:
    """`crtraj bench suite ...` (arguments from `crtraj.cli`); returns the exit code."""
    for flag, value in (("--workers", args.workers), ("--dask", args.dask), ("--planner-config", args.planner_config)):
        if value is not None:
            raise InputError(f"{flag}: table1 only (the suite runs its scenarios one by one in this process)")
    options = SuiteOptions(
        scenarios=20 if args.scenarios is None else args.scenarios,
        seed=args.seed,
        time_limit=5.0 if args.time_limit is None else args.time_limit,
        planners=_planners(args.planners),
        replan_duration=args.replan_duration,
    )
    for name in options.planners:
        BUILTIN.check_available(name)
    out = Path(args.out or "out/suite")
    check_outputs_not_inputs({f"--out ({n})": out / n for n in SUITE_FILES}, {"--robot": args.robot})
    for n in SUITE_FILES:
        check_output_file(out / n, f"--out ({n})")
    model = Model(load_robot(args.robot))
    created = datetime.now(timezone.utc).isoformat(timespec="seconds")
    t0 = time.perf_counter()
    scenarios = SuiteGenerator(model, options.seed).generate_all(options.scenarios)
    runner = SuiteRunner(model, options)
    methods = runner.methods()
    print(
        f"crtraj bench suite: {len(scenarios)} scenarios x {len(methods)} methods ({', '.join(methods)}), "
        f"planner budget {options.time_limit:g} s, replanner limit {options.replan_duration:g} s simulated"
    )

    def show(r: SuiteRecord) -> None:
        if not args.no_progress:
            verdict = "ok" if r.success else f"FAIL ({r.check or r.status})"
            print(f"  {r.family:<10} #{r.index:<3} {r.method:<16} {verdict[:90]}  ({r.wall_s:.1f} s)", flush=True)

    records = runner.run(scenarios, show)
    head = header(model, time.perf_counter() - t0, __version__, created)
    table = markdown(records, options, methods, head)
    outputs = OutputSet()
    scenes = {
        "crtraj_version": __version__,
        "created": created,
        "robot": model.robot.to_dict(),
        "suite": options.to_dict(),
        "scenarios": [s.to_dict() for s in scenarios],
    }
    outputs.file(out / "scenarios.json", json_document(to_jsonable(scenes)))
    outputs.file(out / "suite.md", table)
    outputs.file(out / "suite.json", json_document(to_jsonable(results_document(records, options, methods, head))))
    files = outputs.commit()
    print(table.split("\n\n")[-2])
    print(f"wrote {', '.join(str(f) for f in files)} ({head['wall_time_s']:.0f} s)")
    return 0
