"""Table I in both checking modes: figures, confidence intervals against the paper, and what the strict check rejects.

Input: `RunRecord`s of `crtraj.bench.paper_mode`'s planners (each judged by both
checks). The paper mode's rows (`PAPER_ROWS`) count a run as a success when
the paper's check passes (`paper_success`); the strict mode's rows
(`STRICT_ROWS`) when the dense check keeps D_sf (`success`). Units s, mm.

Statistics: a success rate's 95 % interval is Wilson's score interval; the
paper's figure is "in" when it lies in the interval of our rate (which
carries our sample size: a partial table is judged fairly); the interval of
the paper's rate at its 100 scenarios is shown beside it. A mean path length's 95 % interval is mean +- 1.96
standard errors (normal approximation, n >= 30 in a full table); the paper
gives no spread, so its mean is compared with our interval.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from crtraj.bench.paper_mode import PAPER_ROWS, STRICT_ROWS
from crtraj.bench.records import LABELS, PAPER_COUNTS, PAPER_TABLE1, RunRecord

# z of a two-sided 95 % interval.
_Z = 1.959963984540054
# The paper's scenarios per obstacle count (sec. IV-B).
PAPER_N = 100
# Paper-mode rows and the paper's planner whose figures they reproduce.
PAPER_OF = {"rrt-paper": "rrt", "rrtstar-paper": "rrtstar"}


def wilson(k: int, n: int, z: float = _Z) -> tuple[float, float]:
    """Wilson score interval of a proportion k / n (nan, nan when n = 0)."""
    if n <= 0:
        return float("nan"), float("nan")
    p = k / n
    den = 1.0 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, mid - half), min(1.0, mid + half)


def mean_interval(values: Sequence[float], z: float = _Z) -> tuple[float, float, float]:
    """(mean, low, high) of a 95 % normal interval of the mean (nan when empty; no width for one value)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not len(v):
        return float("nan"), float("nan"), float("nan")
    m = float(v.mean())
    if len(v) < 2:
        return m, m, m
    half = z * float(v.std(ddof=1)) / math.sqrt(len(v))
    return m, m - half, m + half


def label(planner: str) -> str:
    """A table label: the registry's description, or the name."""
    if planner.endswith("-paper"):
        return f"{LABELS.get(planner[: -len('-paper')], planner)}, paper check"
    return LABELS.get(planner, planner)


@dataclass(frozen=True)
class Cell:
    """One planner at one obstacle count in one mode."""

    planner: str
    count: int
    mode: str  # "paper" or "strict": which check decides success
    runs: int
    successes: int
    lengths: tuple[float, ...]  # tip path lengths of the successes (mm)
    cpu: tuple[float, ...]  # CPU time of every run (s)
    wall: tuple[float, ...]  # wall time of every run (s)
    within5: int  # successes found within 5 s of CPU time

    @property
    def rate(self) -> float:
        return self.successes / self.runs if self.runs else float("nan")


def _ok(r: RunRecord, mode: str) -> bool:
    return r.paper_success if mode == "paper" else r.success


def cell(records: Sequence[RunRecord], planner: str, count: int, mode: str) -> Cell:
    """The figures of one planner at one count, success judged by `mode`'s check."""
    rows = [r for r in records if r.planner == planner and r.n_obstacles == count]
    ok = [r for r in rows if _ok(r, mode)]
    return Cell(
        planner,
        count,
        mode,
        len(rows),
        len(ok),
        tuple(r.length_mm for r in ok),
        tuple(r.cpu_s for r in rows),
        tuple(r.time_s for r in rows),
        sum(1 for r in ok if r.cpu_s <= 5.0),
    )


@dataclass(frozen=True)
class Rejections:
    """Paper-mode successes of one planner at one count, and how the strict dense check judged them."""

    planner: str
    count: int
    paper_successes: int
    rejected: int  # the strict check (D_sf) rejects them
    collisions: int  # of which the body touches an obstacle (surface clearance <= 0)
    within_dsf: int  # of which the body stays clear but comes within D_sf


def rejections(records: Sequence[RunRecord], planner: str, count: int) -> Rejections:
    """How many of the planner's paper-check successes at `count` the strict dense check rejects, and why."""
    ok = [r for r in records if r.planner == planner and r.n_obstacles == count and r.paper_success]
    bad = [r for r in ok if not r.success]
    hits = sum(1 for r in bad if r.min_clearance_mm <= 0.0)
    near = sum(1 for r in bad if r.min_clearance_mm > 0.0 and r.dsf_clearance_mm <= 0.0)
    return Rejections(planner, count, len(ok), len(bad), hits, near)


def _f(v: float, d: int = 2) -> str:
    return "—" if not math.isfinite(v) else f"{v:.{d}f}"


def _pct(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{100 * v:.0f}%"


def _paper(planner: str, key: str, count: int) -> float:
    p = PAPER_OF.get(planner)
    if p is None or count not in PAPER_COUNTS:
        return float("nan")
    return PAPER_TABLE1[p][key][PAPER_COUNTS.index(count)]


def _median(v: Sequence[float]) -> float:
    a = np.asarray(v, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.median(a)) if len(a) else float("nan")


def _mean(v: Sequence[float]) -> float:
    a = np.asarray(v, dtype=float)
    a = a[np.isfinite(a)]
    return float(a.mean()) if len(a) else float("nan")


def comparison(c: Cell) -> tuple[str, str]:
    """(success verdict, length verdict) against the paper: 'in' / 'OUT' / '' (no paper figure)."""
    p_succ, p_len = _paper(c.planner, "success", c.count), _paper(c.planner, "path_mm", c.count)
    succ = ""
    if math.isfinite(p_succ) and c.runs:
        lo, hi = wilson(c.successes, c.runs)
        succ = "in" if lo <= p_succ <= hi else "OUT"
    length = ""
    m, lo, hi = mean_interval(c.lengths)
    if math.isfinite(p_len) and math.isfinite(m):
        length = "in" if lo <= p_len <= hi else "OUT"
    return succ, length


def detour(
    records: Sequence[RunRecord], straight: Mapping[tuple[int, int], float], planner: str, count: int, mode: str
) -> float:
    """Mean of (tip path length / straight start-to-goal distance) over the successes (nan without distances)."""
    ratios = [
        r.length_mm / straight[(r.n_obstacles, r.index)]
        for r in records
        if r.planner == planner and r.n_obstacles == count and _ok(r, mode) and (r.n_obstacles, r.index) in straight
    ]
    return float(np.mean(ratios)) if ratios else float("nan")


def markdown(
    records: Sequence[RunRecord],
    counts: Sequence[int],
    header: str,
    straight: Mapping[tuple[int, int], float] | None = None,
) -> str:
    """The two modes' tables, the comparison with the paper and the rejection counts.

    straight: the straight start-to-goal tip distance (mm) of each scenario by (count, index), for the
    detour column (the paper does not publish its start and goal draws; this says how long our queries are).
    """
    straight = straight or {}
    present = {r.planner for r in records}
    paper_rows = [p for p in PAPER_ROWS if p in present]
    strict_rows = [p for p in STRICT_ROWS if p in present]
    return (
        "# Table I in the paper's terms (paper check) and in crtraj's (strict dense check)\n\n"
        + header.rstrip()
        + "\n\n"
        + _paper_table(records, counts, straight, paper_rows)
        + _straight_distances(counts, straight)
        + _strict_table(records, counts, strict_rows)
        + _rejection_table(records, counts, paper_rows)
    )


def _paper_table(
    records: Sequence[RunRecord], counts: Sequence[int], straight: Mapping[tuple[int, int], float], rows: list[str]
) -> str:
    """The paper mode's section: success by the paper's check, beside the paper's figures."""
    out = [
        "## Paper mode: success by the paper's check, against the paper's figures\n\n",
        "Success: the path reaches the goal and the robot's 10 collision points keep D_sf at every 1-s step end "
        '(`crtraj.bench.check.paper_check`). RRT and RRT* plan with that check too (`check = "paper"`); '
        "C-space and OMPL plan with the strict check (their paper-mode figures are the same runs judged by the "
        "paper's check). 95 % Wilson intervals; *succ.* is *in* when the paper's rate lies in ours; *paper CI*: "
        "the interval of the paper's rate at its n = 100. Length: mean tip path of the successes, +- 1.96 s.e.; "
        "*in* when the paper's mean lies in our interval. *Tree*: the planner's own "
        "cost, the tip length of the tree path before smoothing (RRT, RRT*). Detour: mean of path length / straight "
        "start-to-goal tip distance. "
        'Time: mean over all runs (the paper\'s "average running time"), CPU and wall.\n\n',
        "| Method | obs | n | success (95% CI) | ≤ 5 s CPU | paper (paper CI) | succ. | length mm (95% CI) | paper mm "
        "| length | tree mm | detour | CPU s | wall s | paper s |\n",
        "|---|---:|---:|---|---:|---|:-:|---|---:|:-:|---:|---:|---:|---:|---:|\n",
    ]
    out += [_paper_row(records, straight, p, c) for p in rows for c in counts]
    return "".join(out)


def _paper_row(records: Sequence[RunRecord], straight: Mapping[tuple[int, int], float], p: str, c: int) -> str:
    """One planner's row of the paper-mode table at c obstacles."""
    x = cell(records, p, c, "paper")
    lo, hi = wilson(x.successes, x.runs)
    ps = _paper(p, "success", c)
    plo, phi = wilson(round(ps * PAPER_N), PAPER_N) if math.isfinite(ps) else (math.nan, math.nan)
    m, llo, lhi = mean_interval(x.lengths)
    vs, vl = comparison(x)
    tree = [r.best_cost for r in records if r.planner == p and r.n_obstacles == c and r.paper_success]
    paper_succ = f"{_pct(ps)} ({_pct(plo)}–{_pct(phi)})" if math.isfinite(ps) else "—"
    return (
        f"| {label(p)} | {c} | {x.runs} | {_pct(x.rate)} ({_pct(lo)}–{_pct(hi)}) | "
        f"{_pct(x.within5 / x.runs if x.runs else math.nan)} | {paper_succ} | {vs} | "
        f"{_f(m, 0)} ({_f(llo, 0)}–{_f(lhi, 0)}) | {_f(_paper(p, 'path_mm', c))} | {vl} | "
        f"{_f(_mean(tree), 0) if p in PAPER_OF else '—'} | {_f(detour(records, straight, p, c, 'paper'))} | "
        f"{_f(_mean(x.cpu))} | {_f(_mean(x.wall))} | {_f(_paper(p, 'time_s', c))} |\n"
    )


def _straight_distances(counts: Sequence[int], straight: Mapping[tuple[int, int], float]) -> str:
    """The line on the scenarios' straight start-to-goal distances ("" without them)."""
    if not straight:
        return ""
    dist = {c: [d for (k, _), d in straight.items() if k == c] for c in counts}
    return (
        "\nStraight start-to-goal tip distance of the scenarios run, mean (min–max) mm: "
        + "; ".join(
            f"{c} obs {_f(float(np.mean(v)), 0)} ({_f(min(v), 0)}–{_f(max(v), 0)})" for c, v in dist.items() if v
        )
        + ".\n"
    )


def _strict_table(records: Sequence[RunRecord], counts: Sequence[int], rows: list[str]) -> str:
    """The strict mode's section: success means the continuous body keeps D_sf."""
    out = [
        "\n## Strict mode: success means the continuous body keeps D_sf\n\n",
        "Success: the planner claims an exact solution and the dense check (128 backbone points as a polyline "
        "with the disc radius, samples <= 0.01 s and <= 1 mm apart, obstacles at each sample's time) keeps more "
        "than D_sf from every sphere. Clearances over the claimed paths: *surface* = body surface to sphere "
        "surface, *D_sf* = the same minus D_sf (>= 0 is safe); smallest and median. OMPL RRTstar runs to its "
        "budget: *first sol.* is its mean time to the first solution (s, from the plan call, goal IK included), "
        "*cost* its mean best cost at the budget (OMPL's path-length objective in its own state space: body-motion "
        "mm and scaled time, not tip mm).\n\n",
        "| Method | obs | n | success (95% CI) | length mm (95% CI) | median CPU s | median wall s "
        "| surface clr min / median | D_sf clr min / median | first sol. s | cost at budget |\n",
        "|---|---:|---:|---|---|---:|---:|---|---|---:|---:|\n",
    ]
    out += [_strict_row(records, p, c) for p in rows for c in counts]
    return "".join(out)


def _strict_row(records: Sequence[RunRecord], p: str, c: int) -> str:
    """One planner's row of the strict-mode table at c obstacles."""
    x = cell(records, p, c, "strict")
    lo, hi = wilson(x.successes, x.runs)
    m, llo, lhi = mean_interval(x.lengths)
    claimed = [r for r in records if r.planner == p and r.n_obstacles == c and r.claimed]
    surf = [r.min_clearance_mm for r in claimed]
    dsf = [r.dsf_clearance_mm for r in claimed]
    first = [r.first_solution_s for r in claimed]
    cost = [r.best_cost for r in claimed]
    omplstar = p == "ompl-rrtstar"
    return (
        f"| {label(p)} | {c} | {x.runs} | {_pct(x.rate)} ({_pct(lo)}–{_pct(hi)}) | "
        f"{_f(m, 0)} ({_f(llo, 0)}–{_f(lhi, 0)}) | {_f(_median(x.cpu), 3)} | {_f(_median(x.wall), 3)} | "
        f"{_f(min(surf, default=math.nan))} / {_f(_median(surf))} | "
        f"{_f(min(dsf, default=math.nan))} / {_f(_median(dsf))} | "
        f"{_f(_mean(first), 3) if omplstar else '—'} | {_f(_mean(cost), 0) if omplstar else '—'} |\n"
    )


def _rejection_table(records: Sequence[RunRecord], counts: Sequence[int], rows: list[str]) -> str:
    """Paper-check successes the strict check rejects, and why."""
    out = [
        "\n## The cost of the paper's shortcut: paper-check successes the strict check rejects\n\n",
        "Per planner and obstacle count: runs the paper's check accepts, how many of those the strict dense "
        "check rejects, and why (the body touches a sphere between step ends or between the points; or it stays "
        "clear but comes within D_sf).\n\n",
        "| Method | obs | paper-check successes | rejected by strict | collisions | within D_sf only |\n",
        "|---|---:|---:|---:|---:|---:|\n",
    ]
    for p in rows:
        for c in counts:
            j = rejections(records, p, c)
            share = f" ({_pct(j.rejected / j.paper_successes)})" if j.paper_successes else ""
            out.append(
                f"| {label(p)} | {c} | {j.paper_successes} | {j.rejected}{share} | {j.collisions} | {j.within_dsf} |\n"
            )
    return "".join(out)
