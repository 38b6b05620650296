"""PNG figures of Table I in both modes: success against obstacle count, time CDF per planner, path length.

matplotlib is imported when a figure is drawn (headless, Agg backend), so
the rest of the benchmark does not need it. Success and length carry their
95 % intervals (`crtraj.bench.modes`); the paper's figures are drawn as
black markers beside the rows that reproduce them. Units s, mm.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.bench.modes import PAPER_OF, cell, label, mean_interval, wilson
from crtraj.bench.outputs import OutputSet
from crtraj.bench.records import PAPER_COUNTS, PAPER_TABLE1, RunRecord


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _png(fig: Any) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return buf.getvalue()


def _shift(k: int, n: int) -> float:
    """Horizontal offset (obstacles) of series k of n, so that error bars at one count stay apart."""
    return 0.5 * ((k + 0.5) / max(n, 1) - 0.5)


def _rows(records: Sequence[RunRecord], rows: dict[str, Sequence[str]]) -> list[tuple[str, str]]:
    """(mode, planner) pairs that have records, in table order."""
    present = {r.planner for r in records}
    return [(mode, p) for mode, ps in rows.items() for p in ps if p in present]


def success_plot(records: Sequence[RunRecord], rows: dict[str, Sequence[str]], counts: Sequence[int]) -> bytes:
    """Success rate (95 % Wilson interval) against obstacle count, one line per (mode, planner)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    series = _rows(records, rows)
    for k, (mode, p) in enumerate(series):
        xs = np.asarray(counts, dtype=float) + _shift(k, len(series))
        cells = [cell(records, p, c, mode) for c in counts]
        rate = np.array([x.rate for x in cells])
        ci = np.array([wilson(x.successes, x.runs) for x in cells])
        style = "-" if mode == "paper" else "--"
        ax.errorbar(
            xs, 100 * rate, yerr=100 * np.abs(ci.T - rate), fmt=style + "o", capsize=3, label=f"{label(p)} [{mode}]"
        )
        if p in PAPER_OF:
            ys = [100 * PAPER_TABLE1[PAPER_OF[p]]["success"][PAPER_COUNTS.index(c)] for c in counts]
            ax.plot(counts, ys, "kx", ms=8)
    ax.plot([], [], "kx", label="paper (Table I)")
    ax.set_xlabel("obstacles")
    ax.set_ylabel("success (%)")
    ax.set_xticks(list(counts))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    data = _png(fig)
    plt.close(fig)
    return data


def time_cdf_plot(records: Sequence[RunRecord], rows: dict[str, Sequence[str]]) -> bytes:
    """Empirical CDF of the CPU time to a success (all counts pooled), one line per (mode, planner);
    the curve ends at the success rate (failures never arrive)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    for mode, p in _rows(records, rows):
        mine = [r for r in records if r.planner == p]
        ok = sorted(r.cpu_s for r in mine if (r.paper_success if mode == "paper" else r.success))
        if not mine or not ok:
            continue
        y = 100 * np.arange(1, len(ok) + 1) / len(mine)
        ax.step(ok, y, where="post", ls="-" if mode == "paper" else "--", label=f"{label(p)} [{mode}]")
    ax.set_xscale("log")
    ax.set_xlabel("CPU time to a success (s)")
    ax.set_ylabel("runs solved (%)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left")
    data = _png(fig)
    plt.close(fig)
    return data


def length_plot(records: Sequence[RunRecord], rows: dict[str, Sequence[str]], counts: Sequence[int]) -> bytes:
    """Mean tip path length of the successes (95 % interval) against obstacle count."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    series = _rows(records, rows)
    for k, (mode, p) in enumerate(series):
        xs = np.asarray(counts, dtype=float) + _shift(k, len(series))
        stats = np.array([mean_interval(cell(records, p, c, mode).lengths) for c in counts])
        m = stats[:, 0]
        err = np.abs(stats[:, 1:].T - m)
        ax.errorbar(
            xs, m, yerr=err, fmt=("-" if mode == "paper" else "--") + "o", capsize=3, label=f"{label(p)} [{mode}]"
        )
        if p in PAPER_OF:
            ys = [PAPER_TABLE1[PAPER_OF[p]]["path_mm"][PAPER_COUNTS.index(c)] for c in counts]
            ax.plot(counts, ys, "kx", ms=8)
    ax.plot([], [], "kx", label="paper (Table I)")
    ax.set_xlabel("obstacles")
    ax.set_ylabel("mean tip path length of successes (mm)")
    ax.set_xticks(list(counts))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    data = _png(fig)
    plt.close(fig)
    return data


def figure_files(
    records: Sequence[RunRecord], rows: dict[str, Sequence[str]], counts: Sequence[int]
) -> dict[str, bytes]:
    """{file name: PNG bytes} of success.png, time_cdf.png and length.png (nothing written)."""
    return {
        "success.png": success_plot(records, rows, counts),
        "time_cdf.png": time_cdf_plot(records, rows),
        "length.png": length_plot(records, rows, counts),
    }


def write_figures(
    records: Sequence[RunRecord],
    out_dir: str | os.PathLike[str],
    rows: dict[str, Sequence[str]],
    counts: Sequence[int],
) -> list[Path]:
    """success.png, time_cdf.png and length.png in out_dir (all together, `OutputSet`)."""
    out = OutputSet()
    for name, data in figure_files(records, rows, counts).items():
        out.file(Path(out_dir) / name, data)
    return out.commit()
