"""The four scene examples of issue 39 (problems/scene_*.toml) from the command line: each plans, replans (a short
run), streams both results to a dry-run file and draws them as standalone HTML, from a copy of the problem, its
robot and its data in a folder that is then moved (the results name their mesh by a path relative to their own
folder, so they move with it)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import PROBLEMS

from crtraj.cli import main
from crtraj.core.tomledit import set_values
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model
from crtraj.world.geometry import exact_min_clearance

pytestmark = pytest.mark.slow  # end to end: four plans and four replans from the command line (about 1.5 min)

HANG_S = 600.0  # s: a hang bound, never a timing window
NAMES = ("scene_table_wall", "scene_plate_hole", "scene_bent_pipe", "scene_swinging_arm")


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    """{name: (plan result, replan folder, replan exit code)} in a folder written as `before/` and moved to
    `after/` once every command ran: one plan and one replan (1 s of loop time) per problem."""
    root = tmp_path_factory.mktemp("scenes")
    before = root / "before"
    shutil.copytree(PROBLEMS / "data", before / "data")
    shutil.copytree(PROBLEMS / "robots", before / "robots")
    out = {}
    for name in NAMES:
        # the planner's wall-clock limit as a hang bound only: a loaded machine must not turn the seeded search's
        # answer into a timeout
        values = {("loop", "duration"): 1.0, ("planner", "time_limit"): HANG_S}
        text = set_values((PROBLEMS / f"{name}.toml").read_text(), values)
        problem = before / f"{name}.toml"
        problem.write_text(text)
        plan, run = before / "out" / f"{name}.json", before / "out" / f"{name}-run"
        assert main(["plan", str(problem), "--out", str(plan), "-q"]) == 0, name
        code = main(["replan", str(problem), "--out", str(run), "--no-html", "-q"])
        out[name] = (plan.relative_to(before), run.relative_to(before), code)
    shutil.rmtree(before / "robots")
    after = root / "after"
    before.rename(after)
    return {k: (after / a, after / b, c) for k, (a, b, c) in out.items()}


@pytest.mark.parametrize("name", NAMES)
def test_example_plans_and_replans_from_the_command_line(moved, name):
    """The plan succeeds and keeps D_sf every 10 ms by the brute-force distance (40 fresh backbone points); the
    short replan (1 s of the run: it does not reach the goal yet) breaches D_sf nowhere; after the move both
    results read back with their mesh files (relative paths in the files), with the problem's shapes."""
    plan, run, code = moved[name]
    doc = json.loads(plan.read_text())
    files = [s["file"] for s in doc["scene"].get("shape", []) if "file" in s]
    assert all(not Path(f).is_absolute() for f in files), files
    res = read_result(plan)
    assert res.success
    model = Model(res.robot)
    times = np.append(np.arange(res.t[0], res.t[-1], 0.01), res.t[-1])
    configs = np.stack([np.interp(times, res.t, res.x[:, j]) for j in range(res.x.shape[1])], axis=1)
    pts = model.points(configs, 40)
    d = np.min([exact_min_clearance(ms, pts, times) for ms in res.scene.shapes], axis=0)
    assert d.min() - model.robot.body_radius - res.scene.safety_distance >= 0.0
    assert code == 1  # still on its way after 1 s: a "timeout" run, written where asked
    summary = json.loads((run / "run.json").read_text())["summary"]
    assert summary["collisions"] == 0 and summary["safety_violations"] == 0, summary
    assert read_result(run / "run.json").scene.n_shapes == res.scene.n_shapes


@pytest.mark.parametrize("name", NAMES)
def test_example_results_stream_and_view(moved, name, tmp_path):
    """The plan streams to a dry-run frame file (every frame admitted: the stream completes; a run that has not
    reached its goal is never streamed), and both results export the standalone view."""
    plan, run, _ = moved[name]
    frames, log = tmp_path / "frames.bin", tmp_path / "log.jsonl"
    assert main(["stream", str(plan), "--dry-run", str(frames), "--log", str(log), "-q"]) == 0
    assert frames.stat().st_size > 0
    for i, result in enumerate((plan, run / "run.json")):
        html = tmp_path / f"view{i}.html"
        assert main(["view", str(result), "--html", str(html), "-q"]) == 0
        assert html.stat().st_size > 10_000
