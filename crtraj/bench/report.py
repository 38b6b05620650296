"""The benchmark's report: statistics per planner and obstacle count, table1.md, runs.csv, scenarios.json."""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from crtraj import __version__
from crtraj.bench.outputs import OutputSet
from crtraj.bench.records import LABELS, PAPER_COUNTS, PAPER_TABLE1, BenchOptions, RunRecord, _fmt, _pct
from crtraj.bench.runlog import csv_text
from crtraj.bench.scenarios import Scenario, ScenarioOptions
from crtraj.core.fileio import json_document, to_jsonable
from crtraj.planning.options import PlannerOptions


@dataclass
class BenchReport:
    """All records of a run, the statistics the table shows, and the files."""

    options: BenchOptions
    scenario_options: ScenarioOptions
    planner_options: PlannerOptions
    records: list[RunRecord]
    scenarios: list[Scenario]
    wall_time: float
    executor: str
    workers: int
    interrupted: bool = False
    note: str = ""
    created: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))

    # ------------------------------------------------------------- figures
    def stats(self, planner: str, n_obstacles: int) -> dict[str, float]:
        """mean/median/p90 time (s) over all runs, success rate, mean/median length (mm) of successes."""
        rows = [r for r in self.records if r.planner == planner and r.n_obstacles == n_obstacles]
        nan = float("nan")
        if not rows:
            return {
                "runs": 0,
                "success": nan,
                "time_mean": nan,
                "time_median": nan,
                "time_p90": nan,
                "length_mean": nan,
                "length_median": nan,
                "rejected": 0,
            }
        times = np.array([r.time_s for r in rows], dtype=float)
        times = times[np.isfinite(times)]
        lengths = np.array([r.length_mm for r in rows if r.success], dtype=float)
        return {
            "runs": len(rows),
            "success": float(np.mean([r.success for r in rows])),
            "time_mean": float(times.mean()) if len(times) else nan,
            "time_median": float(np.median(times)) if len(times) else nan,
            "time_p90": float(np.percentile(times, 90)) if len(times) else nan,
            "length_mean": float(lengths.mean()) if len(lengths) else nan,
            "length_median": float(np.median(lengths)) if len(lengths) else nan,
            "rejected": sum(1 for r in rows if r.claimed and not r.verified),
        }

    def paired_lengths(self, a: str, b: str, n_obstacles: int) -> tuple[int, float]:
        """Scenarios both planners solved: (count, mean of length_a / length_b)."""
        la = {
            r.index: r.length_mm for r in self.records if r.planner == a and r.n_obstacles == n_obstacles and r.success
        }
        lb = {
            r.index: r.length_mm for r in self.records if r.planner == b and r.n_obstacles == n_obstacles and r.success
        }
        both = sorted(set(la) & set(lb))
        if not both:
            return 0, float("nan")
        return len(both), float(np.mean([la[i] / lb[i] for i in both]))

    # --------------------------------------------------------------- files
    def markdown(self) -> str:
        """table1.md: the run's setup, then the paper's layout (time / success, path length), the time spread
        and the default planner's paired length ratios."""
        paper_cols = {c: PAPER_COUNTS.index(c) for c in self.options.counts if c in PAPER_COUNTS}
        return (
            self._intro()
            + self._time_success_table(paper_cols)
            + self._length_table(paper_cols)
            + self._spread_table()
            + self._paired_table()
            + "\nTimes were measured with the workers sharing the machine; the paper's figures come from an "
            "Intel i7-12700H laptop.\n"
        )

    def _intro(self) -> str:
        """Title, machine, run settings and the dense check's terms."""
        o = self.options
        margin = "D_sf" if o.verify_margin is None else f"{o.verify_margin:g} mm"
        text = (
            "# Table I — planners on the paper's random dynamic scenes\n\n"
            f"crtraj {__version__}, {self.created}, {platform.node()} ({platform.machine()}, "
            f"{os.cpu_count()} logical CPUs, {platform.python_implementation()} {platform.python_version()}); "
            f"{self.executor} with {self.workers} worker(s); whole run {self.wall_time:.0f} s.\n\n"
            f"{o.scenarios} scenarios per obstacle count (seed {o.seed}), time limit {o.time_limit:g} s per run, "
            f"goal tolerance {o.goal_tolerance:g} mm. Every claimed success was re-checked densely "
            f"({o.verify_points} backbone points, <= {o.verify_dt:g} s and <= {o.verify_step:g} mm between "
            f"samples, clearance > {margin}); a success it rejects counts as a failure.\n\n"
        )
        if self.interrupted:
            text += (
                f"**Incomplete — {self.note}: the table covers only the {len(self.records)} runs that finished.**\n\n"
            )
        return text

    def _time_success_table(self, paper_cols: dict[int, int]) -> str:
        """The paper's layout: mean time (s) and success rate per obstacle count, the paper's row above ours."""
        counts = self.options.counts
        out = [
            "## Time (s) / success\n\n",
            'Mean wall time per run over all runs (the paper\'s "average running time"), and the success rate.\n\n',
            "| Method | " + " | ".join(f"{c} obs: time (s) | {c} obs: succ" for c in counts) + " |\n",
            "|---|" + "---:|---:|" * len(counts) + "\n",
        ]
        for p in self.options.planners:
            if p in PAPER_TABLE1 and paper_cols:
                cells = [
                    f"{_fmt(_paper(paper_cols, p, 'time_s', c))} | {_pct(_paper(paper_cols, p, 'success', c))}"
                    for c in counts
                ]
                out.append(f"| {LABELS.get(p, p)} — paper | " + " | ".join(cells) + " |\n")
            cells = []
            for c in counts:
                s = self.stats(p, c)
                cells.append(f"{_fmt(s['time_mean'], 3)} | {_pct(s['success'])}")
            out.append(f"| {LABELS.get(p, p)} — crtraj | " + " | ".join(cells) + " |\n")
        return "".join(out)

    def _length_table(self, paper_cols: dict[int, int]) -> str:
        """Mean path length (mm) of the successful runs, the paper's row above ours."""
        counts = self.options.counts
        out = [
            "\n## Average path length (mm) of successful runs\n\n",
            "| Method | " + " | ".join(f"{c} obs" for c in counts) + " |\n",
            "|---|" + "---:|" * len(counts) + "\n",
        ]
        for p in self.options.planners:
            if p in PAPER_TABLE1 and paper_cols:
                figures = " | ".join(_fmt(_paper(paper_cols, p, "path_mm", c)) for c in counts)
                out.append(f"| {LABELS.get(p, p)} — paper | " + figures + " |\n")
            lengths = " | ".join(_fmt(self.stats(p, c)["length_mean"]) for c in counts)
            out.append(f"| {LABELS.get(p, p)} — crtraj | " + lengths + " |\n")
        return "".join(out)

    def _spread_table(self) -> str:
        """Median / p90 time (s) and the claimed successes the dense check rejected."""
        counts = self.options.counts
        out = [
            "\n## Time spread (s): median / p90, and claimed successes the dense check rejected\n\n",
            "| Method | " + " | ".join(f"{c} obs" for c in counts) + " |\n",
            "|---|" + "---:|" * len(counts) + "\n",
        ]
        for p in self.options.planners:
            cells = []
            for c in counts:
                s = self.stats(p, c)
                cells.append(f"{_fmt(s['time_median'], 3)} / {_fmt(s['time_p90'], 3)} ({s['rejected']} rej.)")
            out.append(f"| {LABELS.get(p, p)} | " + " | ".join(cells) + " |\n")
        return "".join(out)

    def _paired_table(self) -> str:
        """Path length of C-space relative to each other planner on the scenarios both solved ("" without
        C-space or another planner)."""
        counts, planners = self.options.counts, list(self.options.planners)
        others = [p for p in planners if p != "cspace"]
        if "cspace" not in planners or not others:
            return ""
        out = [
            "\n## Path length of the default planner relative to each other planner (scenarios both solved)\n\n",
            "Mean over the scenarios both solved of length(C-space) / length(other); below 1: C-space is shorter.\n",
            "\n",
            "| Other planner | " + " | ".join(f"{c} obs" for c in counts) + " |\n",
            "|---|" + "---:|" * len(counts) + "\n",
        ]
        for p in others:
            cells = []
            for c in counts:
                n, ratio = self.paired_lengths("cspace", p, c)
                cells.append(f"{_fmt(ratio, 3)} (n={n})")
            out.append(f"| {LABELS.get(p, p)} | " + " | ".join(cells) + " |\n")
        return "".join(out)

    def csv_text(self) -> str:
        return csv_text(self.records)

    def outputs(self, out_dir: str | os.PathLike[str]) -> OutputSet:
        """table1.md, runs.csv and scenarios.json in out_dir, not yet written (`OutputSet.commit`)."""
        d = Path(out_dir)
        out = OutputSet()
        out.file(d / "table1.md", self.markdown())
        out.file(d / "runs.csv", self.csv_text())
        scenarios = {
            "crtraj_version": __version__,
            "created": self.created,
            "bench": self.options.to_dict(),
            "generator": self.scenario_options.to_dict(),
            "planner": self.planner_options.to_dict(),
            "scenarios": [s.to_dict() for s in self.scenarios],
        }
        out.file(d / "scenarios.json", json_document(to_jsonable(scenarios)))
        return out

    def write(self, out_dir: str | os.PathLike[str]) -> list[Path]:
        """Write table1.md, runs.csv and scenarios.json into out_dir, all together or none (`OutputSet`)."""
        return self.outputs(out_dir).commit()


def _paper(paper_cols: dict[int, int], planner: str, key: str, count: int) -> float:
    """The paper's Table I figure `key` of `planner` at `count` obstacles (nan when it has none)."""
    if planner not in PAPER_TABLE1 or count not in paper_cols:
        return float("nan")
    return PAPER_TABLE1[planner][key][paper_cols[count]]
