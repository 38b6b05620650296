"""The page around the scene: heads-up panel, synchronized plots, events, controls and legend.

`page_data` gathers what the page shows from one or two drawn runs (their `Timeline`s) as JSON-ready values;
`wrap_page` puts it, with the page's own HTML, CSS and JavaScript (package data in ``crtraj/viz/assets/``), into
meshcat's standalone page, so the file stays one self-contained page that opens offline. The page's script reads
meshcat's animation clock (``viewer.animator``) and drives it (seek, play, pause, speed). Lengths in mm, times in s.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from importlib import resources
from typing import Any

import numpy as np

from crtraj.io.results import Result
from crtraj.viz.options import ViewOptions
from crtraj.viz.timeline import Timeline

_DIGITS = 6  # decimals kept in the page's numbers (1 nm in mm, 1 us in s): far below what the panel prints


def _asset(name: str) -> str:
    return resources.files("crtraj.viz").joinpath("assets", name).read_text(encoding="utf-8")


def nums(a: Any) -> Any:
    """Nested lists of rounded floats, None for NaN (JSON has no NaN)."""
    arr = np.asarray(a, dtype=float)
    if arr.ndim == 0:
        v = float(arr)
        return round(v, _DIGITS) if math.isfinite(v) else None
    return [nums(v) for v in arr]


def obstacle_names(run: Result, columns: int) -> list[str]:
    """One name per clearance column: the sphere obstacles', then the other shapes' (their kind and index when
    unnamed), "obstacle i" for any other column."""
    names = [o.name for o in run.scene.obstacles] if run.scene is not None else []
    if run.scene is not None:
        names += [ms.shape.name or f"{ms.shape.kind} {j}" for j, ms in enumerate(run.scene.shapes)]
    return names + [f"obstacle {i}" for i in range(len(names), columns)]


def _run_data(run: Result, tl: Timeline, label: str) -> dict[str, Any]:
    names = obstacle_names(run, tl.clearance.shape[1])
    summary = run.data.get("summary")
    summary = summary if isinstance(summary, dict) else {}
    late, dense = summary.get("deadline_misses"), summary.get("min_distance_mm")
    fields = run_fields(tl, label, run.kind, f"{run.status}: {run.message}", names)
    fields["headline"] = headline(tl, names, late if isinstance(late, int) else None)
    if isinstance(dense, (int, float)) and fields["headline"]:
        # the frames are the loop's steps; the run's own check also covers the executed samples between them
        fields["headline"] += f" \u00b7 smallest distance over the executed motion {dense:.2f} mm"
    return fields


def run_fields(tl: Timeline, label: str, kind: str, verdict: str, names: Sequence[str]) -> dict[str, Any]:
    """One run's part of the page data: its timeline's numbers; names: the obstacles' (one per clearance column)."""
    return {
        "label": label,
        "kind": kind,
        "verdict": verdict[:200],
        "t": nums(tl.t),
        "status": list(tl.status),
        "obstacles": list(names[: tl.clearance.shape[1]]),
        "clearance": nums(tl.clearance.T),
        "near": [int(i) for i in tl.near],
        "tip_error": nums(tl.tip_error),
        "iteration": nums(tl.iteration),
        "velocity": nums(tl.velocity),
        "acceleration": nums(tl.acceleration),
        "deadline": nums(tl.deadline),
        "safety_distance": tl.safety_distance,
        "closest_t": nums(tl.t[tl.closest_index]) if len(tl.t) else 0.0,
        "headline": headline(tl, names, None),
        "events": [{"kind": e.kind, "t": nums(e.t), "text": e.text} for e in tl.events],
    }


def headline(tl: Timeline, names: Sequence[str], late: int | None) -> str:
    """One line that answers what a reader asks first: when and to which obstacle the body came closest, by how
    much, how often the loop held or fell back, and its deadline (`headline_text`); late: the loop's own count of
    horizon solves that came after the deadline and were not used (None: not recorded). A plan, which has no
    loop, gives only the approach."""
    closest = None
    if tl.clearance.shape[1] and len(tl.t):
        k = tl.closest_index
        j = int(tl.near[k])
        closest = (float(tl.clearance[k, j]), names[j] if j < len(names) else f"obstacle {j}", float(tl.t[k]))
    counts = None
    if any(tl.status):
        counts = (sum(s == "hold" for s in tl.status), sum(s == "fallback" for s in tl.status))
    over = int(np.sum(tl.iteration > tl.deadline)) if math.isfinite(tl.deadline) else 0
    return headline_text(closest, tl.safety_distance, counts, late, over, tl.deadline)


def headline_text(
    closest: tuple[float, str, float] | None,
    safety: float,
    counts: tuple[int, int] | None,
    late: int | None,
    over: int,
    deadline: float,
) -> str:
    """The headline's words. closest: (clearance beyond D_sf mm, obstacle, t s) of the closest approach, or
    None; safety: D_sf mm; counts: (hold, fallback) steps, or None without a loop; late: deadline misses (None:
    not recorded); over: iterations longer than the deadline (s; NaN: none)."""
    parts = []
    if closest is not None:
        c, name, t = closest
        inside = ", inside D_sf" if c < 0 else ""
        parts.append(f"closest: {c + safety:.2f} mm to {name} at {t:.2f} s ({c:+.2f} mm beyond D_sf{inside})")
    if counts is not None:
        parts.append(f"{counts[0]} hold steps, {counts[1]} fallback steps")
    if math.isfinite(deadline):
        ms = f"{deadline * 1e3:g} ms"
        missed = "" if late is None else f"{late} deadline misses (solve later than {ms}, unused), "
        parts.append(f"{missed}{over} iterations over {ms}")
    return " \u00b7 ".join(parts)


# the per-step lists of a run's page data (`run_fields`); "clearance" holds one such list per obstacle
ROW_FIELDS = ("t", "status", "near", "tip_error", "iteration", "velocity", "acceleration")


def append_rows(run: dict[str, Any], rows: Mapping[str, Any]) -> None:
    """Add a live run's new steps to its page data `run` (`run_fields`' layout), in place, as the page's script
    does. rows: the ROW_FIELDS lists and "clearance" (one list per obstacle) of the new steps, "k" the index of
    the first, the "events" among them and the run's "closest_t" so far. Steps the run already has are skipped;
    a gap (k beyond the run's length) is a ValueError."""
    n, k = len(run["t"]), int(rows["k"])
    if k > n:
        raise ValueError(f"rows: step {k} does not follow step {n - 1}")
    skip = n - k
    if skip >= len(rows["t"]):
        return
    last = run["t"][-1] if n else -math.inf
    for f in ROW_FIELDS:
        run[f].extend(rows[f][skip:])
    for have, new in zip(run["clearance"], rows["clearance"], strict=True):
        have.extend(new[skip:])
    run["events"].extend(e for e in rows["events"] if e["t"] > last)
    run["closest_t"] = rows["closest_t"]
    run["headline"] = rows.get("headline", run.get("headline", ""))


def page_data(runs: Sequence[tuple[Result, Timeline]], options: ViewOptions) -> dict[str, Any]:
    """The page's data for the drawn run and, if any, the compared one (a ghost), as JSON-ready values."""
    o = options
    labels = ["A", "B"]
    # the planner tree and the replans' references: shown for plans, hidden for runs (as `draw_run_paths` draws them)
    n_seg = runs[0][0].robot.n_segments if runs else 0
    layers_on = o.show_tree if o.show_tree is not None else bool(runs) and runs[0][0].kind == "plan"
    return {
        "runs": [_run_data(r, tl, labels[i] if len(runs) > 1 else "") for i, (r, tl) in enumerate(runs)],
        "legend": legend(o, n_seg, layers_on),
    }


def legend(o: ViewOptions, n_seg: int, layers_on: bool) -> list[dict[str, Any]]:
    """The legend: every colour of the scene; items with a layer can be switched (layers_on: tree, references)."""
    return [
        *({"color": o.segment_colors[k % len(o.segment_colors)], "label": f"segment {k + 1}"} for k in range(n_seg)),
        {"color": o.obstacle_color, "label": "obstacle (faint shell: D_sf)", "layer": "shells"},
        {"color": o.closest_color, "label": "closest approach", "layer": "closest"},
        {"color": o.trail_color, "label": "executed tip path", "layer": "path/executed"},
        {"color": o.path_color, "label": "planned tip path (ghost)", "layer": "path/planned"},
        {"color": o.start_color, "label": "start", "layer": "markers/start"},
        {"color": o.goal_color, "label": "goal", "layer": "markers/goal"},
        {"color": o.tree_color, "label": "planner tree", "layer": "tree", "on": layers_on},
        {"color": o.tree_color, "label": "replanned references", "layer": "references", "on": layers_on},
    ]


def page_json(data: dict[str, Any]) -> str:
    """The page's data as compact JSON (no NaN: `nums` made them null)."""
    return json.dumps(data, separators=(",", ":"), allow_nan=False)


def wrap_page(meshcat_html: str, data: dict[str, Any]) -> str:
    """meshcat's standalone page with the page around the scene added before its end (one file, offline)."""
    return wrap_page_json(meshcat_html, page_json(data))


def wrap_page_json(meshcat_html: str, data_json: str) -> str:
    """`wrap_page` with the data already as JSON (the served page: `crtraj.viz.server`)."""
    # "</" inside a script would end it early; JSON allows the escaped solidus
    blob = data_json.replace("</", "<\\/")
    extra = (
        f"<style>{_asset('page.css')}</style>\n{_asset('page.html')}\n"
        f'<script id="crtraj-data" type="application/json">{blob}</script>\n'
        f"<script>{_asset('page.js')}</script>\n"
    )
    head, sep, tail = meshcat_html.rpartition("</body>")
    if not sep:
        raise ValueError("meshcat's page has no </body>")
    return head.replace("<title>MeshCat</title>", "<title>crtraj view</title>", 1) + extra + sep + tail
