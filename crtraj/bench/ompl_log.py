"""Benchmark runs as OMPL benchmark logs: the text that ``ompl_benchmark_statistics.py`` and Planner Arena read.

One log is one OMPL "experiment": here one obstacle count in one checking
mode, its planners and their runs (one run per scenario). The grammar is the
one OMPL's ``ompl::tools::Benchmark::saveResultsToStream`` writes and
``ompl_benchmark_statistics.py`` (``readBenchmarkLog``) parses:

    crtraj version <v>
    Experiment <name>
    <k> experiment properties
    <name> <TYPE> = <value>                   (k lines)
    Running on <host>
    Starting at <date>
    <<<|
    <setup, any lines>
    |>>>
    <<<|
    <cpu info, any lines>
    |>>>
    <seed> is the random seed
    <t> seconds per run
    <m> MB per run
    <n> runs per planner
    <total> seconds spent to collect the data
    <e> enum types
    <P> planners
      (per planner)
    <planner name>
    <c> common properties
    <name> <TYPE> = <value>                   (c lines)
    <q> properties for each run
    <name words> <TYPE>                       (q lines: REAL, INTEGER, BOOLEAN, VARCHAR(128))
    <r> runs
    <v_1>; <v_2>; ... <v_q>;                  (r lines; empty = missing)
    <g> progress properties for each run
    <name words> <TYPE>                       (g lines)
    <r> runs
    <a_1>,<b_1>,;<a_2>,<b_2>,;...             (r lines: the samples of each run)
    .

Per-run properties: ``time`` (wall s), ``cpu time``, ``solved`` (a path was
returned, exact or approximate), ``approximate solution``, ``correct
solution`` (success by the mode's check), ``solution length`` (tip path, mm),
``solution clearance`` (the dense check's clearance beyond D_sf, mm),
``surface clearance`` (body to sphere surface, mm), ``paper clearance``
(the paper check's, mm), ``graph states``, ``time first solution`` (s) and
``best cost`` (at the end of the budget). Progress properties: ``time`` and
``best cost`` each time the best cost improved (OMPL planners).
"""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from crtraj import __version__
from crtraj.bench.outputs import OutputSet
from crtraj.bench.records import RunRecord

# (property name, OMPL type, value of a record)
_PROPERTIES = (
    ("time", "REAL", lambda r: r.time_s),
    ("cpu time", "REAL", lambda r: r.cpu_s),
    ("solved", "BOOLEAN", lambda r: r.status in ("exact", "approximate")),
    ("approximate solution", "BOOLEAN", lambda r: r.status == "approximate"),
    ("correct solution", "BOOLEAN", None),  # the mode's verdict, filled in by `_values`
    ("solution length", "REAL", lambda r: r.length_mm),
    ("solution clearance", "REAL", lambda r: r.dsf_clearance_mm),
    ("surface clearance", "REAL", lambda r: r.min_clearance_mm),
    ("paper clearance", "REAL", lambda r: r.paper_clearance_mm),
    ("graph states", "INTEGER", lambda r: r.graph_states),
    ("time first solution", "REAL", lambda r: r.first_solution_s),
    ("best cost", "REAL", lambda r: r.best_cost),
)
_PROGRESS = (("time", "REAL"), ("best cost", "REAL"))


def _cell(v: object) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return f"{v:.9g}" if math.isfinite(v) else ""
    return str(v)


def _values(r: RunRecord, mode: str) -> str:
    cells = []
    for _, _, get in _PROPERTIES:
        v = (r.paper_success if mode == "paper" else r.success) if get is None else get(r)
        cells.append(_cell(v))
    return "".join(f"{c}; " for c in cells) + "\n"  # OMPL's own layout: every value followed by "; "


def _progress(r: RunRecord) -> str:
    """One run's progress samples: 't,c,;' each (empty line: none)."""
    out = []
    for pair in filter(None, r.cost_progress.split(";")):
        t, c = pair.split(":")
        out.append(f"{float(t):.6g},{float(c):.9g},;")
    return "".join(out) + "\n"


def _clean(text: str) -> str:
    """One line of free text (no line breaks, which would break the grammar)."""
    return " ".join(text.split())


# Long by design: it writes the log top to bottom in the grammar's order (module docstring).
def log_text(
    records: Sequence[RunRecord],
    planners: Sequence[str],
    *,
    experiment: str,
    mode: str,
    time_limit: float,
    setup: str,
    seed: int = 0,
    total_time: float = float("nan"),
    created: str | None = None,
) -> str:
    """The OMPL benchmark log of `records` for `planners` (in this order; runs sorted by scenario index).

    mode: "paper" or "strict", the check whose verdict is ``correct solution``.
    """
    runs = {p: sorted((r for r in records if r.planner == p), key=lambda r: r.index) for p in planners}
    n_runs = max((len(v) for v in runs.values()), default=0)
    total = total_time if math.isfinite(total_time) else sum(r.time_s for v in runs.values() for r in v)
    lines = [
        f"crtraj version {__version__}",
        f"Experiment {_clean(experiment).replace(' ', '_')}",
        "1 experiment properties",
        f"check_mode VARCHAR(16) = {mode}",
        f"Running on {platform.node() or 'unknown'}",
        f"Starting at {created or datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M:%S')}",
        "<<<|",
        *(_clean(s) for s in setup.splitlines()),
        "|>>>",
        "<<<|",
        f"{platform.machine()}, {os.cpu_count()} logical CPUs, {platform.python_implementation()} "
        f"{platform.python_version()}",
        "|>>>",
        f"{seed} is the random seed",
        f"{time_limit:g} seconds per run",
        "0 MB per run",
        f"{n_runs} runs per planner",
        f"{total:.6g} seconds spent to collect the data",
        "0 enum types",
        f"{len(planners)} planners",
    ]
    text = "\n".join(lines) + "\n"
    for p in planners:
        rs = runs[p]
        text += f"{_clean(p)}\n0 common properties\n{len(_PROPERTIES)} properties for each run\n"
        text += "".join(f"{name} {kind}\n" for name, kind, _ in _PROPERTIES)
        text += f"{len(rs)} runs\n" + "".join(_values(r, mode) for r in rs)
        text += f"{len(_PROGRESS)} progress properties for each run\n"
        text += "".join(f"{name} {kind}\n" for name, kind in _PROGRESS)
        text += f"{len(rs)} runs\n" + "".join(_progress(r) for r in rs) + ".\n"
    return text


@dataclass(frozen=True)
class LogSetup:
    """What every log of a run states besides its runs: time_limit (s per run), setup (free text) and seed."""

    time_limit: float
    setup: str
    seed: int = 0


def log_files(
    records: Sequence[RunRecord], modes: dict[str, Sequence[str]], counts: Sequence[int], setup: LogSetup
) -> dict[str, str]:
    """{file name: log text}: one log per (mode, obstacle count), ``table1-<mode>-<count>obs.log``."""
    files = {}
    for mode, planners in modes.items():
        present = [p for p in planners if any(r.planner == p for r in records)]
        for c in counts:
            rs = [r for r in records if r.n_obstacles == c]
            name = f"table1-{mode}-{c}obs"
            files[f"{name}.log"] = log_text(
                rs,
                present,
                experiment=name,
                mode=mode,
                time_limit=setup.time_limit,
                setup=setup.setup,
                seed=setup.seed,
            )
    return files


def write_logs(
    records: Sequence[RunRecord],
    out_dir: str | os.PathLike[str],
    modes: dict[str, Sequence[str]],
    counts: Sequence[int],
    *,
    time_limit: float,
    setup: str,
    seed: int = 0,
) -> list[Path]:
    """One log per (mode, obstacle count): OUT/table1-<mode>-<count>obs.log (all together, `OutputSet`)."""
    out = OutputSet()
    for name, text in log_files(records, modes, counts, LogSetup(time_limit, setup, seed)).items():
        out.file(Path(out_dir) / name, text)
    return out.commit()
