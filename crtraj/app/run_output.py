"""Use case: write a replan run's folder (run.json, run.npz, run.png and the run.html replay) as one set."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from crtraj.control.loop import ClosedLoop, ReplanRun
from crtraj.core.fileio import StagedDir, atomic_write_json, atomic_write_text
from crtraj.io.plots import plot_run
from crtraj.io.results import RunContext, relative_shape_files, run_document
from crtraj.io.run_files import RUN_FILES, save_npz
from crtraj.viz.view import Visualizer


def run_context(loop: ClosedLoop) -> RunContext:
    """The plain data a run document records about the loop that made the run: model, scene, goal tolerance
    (mm) and every option section (``replan``, ``tracking``, then ``loop`` and the loop's extra sections)."""
    options = {"replan": loop.options, "tracking": loop.tracking_options, **loop.extra_options}
    return RunContext(loop.model, loop.scene, loop.goal_tolerance, options)


def write_run_files(
    run: ReplanRun,
    loop: ClosedLoop,
    folder: str | os.PathLike[str],
    *,
    problem: Any = None,
    seed: int | None = None,
    html: bool = True,
) -> dict[str, Any]:
    """Write run.json, run.npz, run.png and (html=True) run.html into an existing folder, one file at a
    time (`write_run` stages them and swaps the folder in whole). Returns the paths (keys json, npz, png,
    html) and, under "result", the result document as plain JSON data."""
    out = Path(folder)
    context = run_context(loop)
    result = run_document(run, context, problem, seed)
    # the shapes' data files relative to the folder in the file (it moves with them), absolute for the view here
    paths: dict[str, Any] = {"json": atomic_write_json(out / "run.json", relative_shape_files(result, out))}
    paths["npz"] = save_npz(run, out / "run.npz")
    paths["png"] = plot_run(run, context, out / "run.png")
    if html:
        vis = Visualizer.for_result(result, play=True)
        try:
            paths["html"] = atomic_write_text(out / "run.html", vis.static_html())
        finally:
            vis.close()
    paths["result"] = result
    return paths


def write_run(
    run: ReplanRun,
    loop: ClosedLoop,
    out_dir: str | os.PathLike[str],
    *,
    problem: Any = None,
    seed: int | None = None,
    html: bool = True,
) -> dict[str, Any]:
    """Write run.json, run.npz, run.png and (html=True) run.html into out_dir, as one set: they are
    written into a temporary sibling folder that then replaces out_dir in one atomic step
    (`crtraj.core.fileio.StagedDir`), so a crash or kill leaves the previous set or the new one, never a
    mix. out_dir must be new, or hold only files named in `crtraj.io.run_files.RUN_FILES`.

    Returns the paths (keys json, npz, png, html) and, under "result", the result document as plain
    JSON data.
    """
    with StagedDir(out_dir, RUN_FILES) as stage:
        paths = write_run_files(run, loop, stage.path, problem=problem, seed=seed, html=html)
        dest = stage.commit()
    return {k: (dest / v.name if k != "result" else v) for k, v in paths.items()}
