"""The held-out suite's results (`crtraj bench suite`): per-method summaries, suite.md and suite.json's data.

Input: the `SuiteRecord`s of `crtraj.bench.suite.SuiteRunner` (units s, mm).
"""

from __future__ import annotations

import math
import platform
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import numpy as np

from crtraj.bench.records import LABELS, _fmt
from crtraj.bench.suite import FAMILIES, REPLANNER, SuiteOptions, SuiteRecord
from crtraj.model.kinematics import Model


def summarize(records: Sequence[SuiteRecord], method: str, family: str | None = None) -> dict[str, float]:
    """Runs, successes, success rate, median time (s, over successes), smallest and median D_sf clearance
    (mm, over checked runs) of one method, in one family or overall."""
    rows = [r for r in records if r.method == method and (family is None or r.family == family)]
    ok = [r for r in rows if r.success]
    clr = np.array([r.clearance_mm for r in rows if math.isfinite(r.clearance_mm)])
    times = np.array([r.time_s for r in ok if math.isfinite(r.time_s)])
    nan = math.nan
    return {
        "runs": float(len(rows)),
        "successes": float(len(ok)),
        "success": len(ok) / len(rows) if rows else nan,
        "time_median": float(np.median(times)) if len(times) else nan,
        "time_p90": float(np.percentile(times, 90)) if len(times) else nan,
        "clearance_min": float(clr.min()) if len(clr) else nan,
        "clearance_median": float(np.median(clr)) if len(clr) else nan,
        "rejected": float(sum(1 for r in rows if r.claimed and not r.success)),
        "rejected_holding": float(sum(1 for r in rows if r.claimed and r.check.startswith("holding the goal"))),
    }


def _label(method: str) -> str:
    return "closed-loop replanner" if method == REPLANNER else LABELS.get(method, method)


def markdown(
    records: Sequence[SuiteRecord], options: SuiteOptions, methods: Sequence[str], header: dict[str, Any]
) -> str:
    """The results table: success k/n, median time and smallest D_sf clearance per method and family."""
    lines = [
        "# crtraj bench suite — held-out dynamic scenes",
        "",
        f"crtraj {header['crtraj_version']}, {header['created']}, {header['machine']}; robot {header['robot']}; "
        f"whole run {header['wall_time_s']:.0f} s (sequential, in one process).",
        "",
        f"{options.scenarios} scenarios (seed {options.seed}) over {len(FAMILIES)} families; planner budget "
        f"{options.time_limit:g} s per run; replanner: arrival within {options.replan_duration:g} s of simulated "
        f"time, reference plans {options.planner_time:g} s each. Success = the dense check ({options.verify_points} "
        f"backbone points, <= {options.verify_dt:g} s and <= {options.verify_step:g} mm between samples) finds the "
        f"body more than D_sf from every sphere along the path and while it holds its end for {options.hold_time:g} s "
        "(goal_sweep: until the sweeper rests), tip within the goal tolerance.",
        "",
        "Cells: successes/runs, median time of the successes (s; the replanner: simulated arrival time), "
        "smallest D_sf clearance of the checked runs (mm; negative = closer than D_sf).",
        "",
        "| Family | " + " | ".join(_label(m) for m in methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for fam in (*FAMILIES, None):
        cells = []
        for m in methods:
            s = summarize(records, m, fam)
            cells.append(
                f"{int(s['successes'])}/{int(s['runs'])}, {_fmt(s['time_median'])} s, {_fmt(s['clearance_min'])} mm"
            )
        name = "**all**" if fam is None else fam
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    rejected = ", ".join(
        f"{_label(m)} {int(summarize(records, m)['rejected'])} ({int(summarize(records, m)['rejected_holding'])} "
        "while holding the goal)"
        for m in methods
    )
    lines += ["", f"Claimed successes the dense check rejected: {rejected}."]
    return "\n".join(lines) + "\n"


def header(model: Model, wall_time: float, version: str, created: str) -> dict[str, Any]:
    return {
        "crtraj_version": version,
        "created": created,
        "machine": f"{platform.node()} ({platform.machine()}, {platform.python_implementation()} "
        f"{platform.python_version()})",
        "robot": model.robot.name,
        "wall_time_s": wall_time,
    }


def results_document(
    records: Sequence[SuiteRecord], options: SuiteOptions, methods: Sequence[str], head: dict[str, Any]
) -> dict[str, Any]:
    """The results as JSON data: header, options, per-method summaries (overall and per family), every run."""
    return {
        **head,
        "suite": options.to_dict(),
        "summary": {
            m: {"all": summarize(records, m), **{f: summarize(records, m, f) for f in FAMILIES}} for m in methods
        },
        "runs": [asdict(r) for r in records],
    }
