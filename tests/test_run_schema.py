"""The declared result schema (crtraj.io.run_schema): files written by the previous version still load with
today's readers and give the values their raw JSON holds; the docs table names every declared field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.core.errors import InputError
from crtraj.io import run_schema as rs
from crtraj.io.results import read_result
from crtraj.io.run_files import read_npz

DATA = Path(__file__).resolve().parent / "data"
# written by the version before the schema was declared (crtraj replan / plan of the paper problems, seed 0)
RUN_JSON, RUN_NPZ, PLAN_JSON = DATA / "run_v1.json", DATA / "run_v1.npz", DATA / "plan_cspace_v1.json"


@pytest.fixture(scope="module")
def raw_run():
    return json.loads(RUN_JSON.read_text())


def test_a_previous_run_json_loads_with_the_values_its_raw_json_holds(raw_run):
    """Step count, final tip error and executed actuation of an old run.json, read back through read_result."""
    res = read_result(RUN_JSON)
    wps = raw_run["waypoints"]
    assert res.kind == "replan" and res.status == raw_run["status"] and res.success is raw_run["success"]
    assert len(res.t) == len(wps) == raw_run["summary"]["steps"] + 1
    np.testing.assert_array_equal(res.t, [w["t"] for w in wps])
    np.testing.assert_array_equal(res.q, [w["q"] for w in wps])
    # the final tip error: the last waypoint's tip to the task's goal, computed here from the raw numbers
    final = np.linalg.norm(np.array(wps[-1]["tip"]) - np.array(raw_run["task"]["goal"]))
    assert final == pytest.approx(raw_run["summary"]["final_tip_error_mm"], abs=1e-9)
    assert np.linalg.norm(res.tip[-1] - res.goal) == pytest.approx(final, abs=1e-12)
    t0, dt, q = res.executed
    assert (t0, dt) == (raw_run["executed"]["t0"], raw_run["executed"]["dt"])
    np.testing.assert_array_equal(q, raw_run["executed"]["q"])
    np.testing.assert_array_equal(res.reference, raw_run["reference"]["tip"])


def test_a_previous_run_npz_loads_and_agrees_with_its_run_json(raw_run):
    """The old run.npz: one clearance and tip per waypoint, and the per-step statuses and iteration times
    that run.json gives each waypoint after the first."""
    arrays = read_npz(RUN_NPZ)
    wps = raw_run["waypoints"]
    assert len(arrays["clearance"]) == len(wps) and arrays["x"].shape == (len(wps), len(wps[0]["x"]))
    np.testing.assert_array_equal(arrays["clearance"], [w["clearance"] for w in wps])
    np.testing.assert_array_equal(arrays["tip"], [w["tip"] for w in wps])
    assert list(arrays["status"]) == [w["status"] for w in wps[1:]]
    np.testing.assert_array_equal(arrays["iter_time"], [w["iteration_time"] for w in wps[1:]])
    assert float(arrays["goal_error"][-1]) == pytest.approx(raw_run["summary"]["final_tip_error_mm"], abs=1e-12)


def test_a_previous_plan_json_loads_with_the_values_its_raw_json_holds():
    """An old plan.json: waypoints, actuation and the planner tree, as its raw JSON has them."""
    raw = json.loads(PLAN_JSON.read_text())
    res = read_result(PLAN_JSON)
    assert res.kind == "plan" and res.status == raw["status"]
    np.testing.assert_array_equal(res.x, [w["x"] for w in raw["waypoints"]])
    np.testing.assert_array_equal(res.q, [w["q"] for w in raw["waypoints"]])
    assert res.edges.shape == (len(raw["tree"]["edges"]), 2, 3)
    np.testing.assert_array_equal(res.start, raw["task"]["start"])


def test_every_key_an_old_file_holds_is_declared(raw_run):
    """Each key of the old files (document, waypoint, executed) has its declaration in the schema."""
    declared = {f.key for f in rs.HEADER + rs.VERDICT + rs.RUN_BODY}
    assert set(raw_run) <= declared
    assert set(raw_run["waypoints"][1]) == {f.key for f in rs.RUN_WAYPOINT}
    assert set(raw_run["waypoints"][0]) == {f.key for f in rs.RUN_WAYPOINT if not f.step}
    assert set(raw_run["executed"]) == {f.key for f in rs.EXECUTED}
    plan = json.loads(PLAN_JSON.read_text())
    assert set(plan) <= {f.key for f in rs.HEADER + rs.VERDICT + rs.PLAN_BODY}
    assert set(plan["waypoints"][0]) == {f.key for f in rs.PLAN_WAYPOINT}


def test_the_docs_table_has_one_row_per_declared_field():
    """schema_table_markdown: per part a table whose rows are that part's fields, with unit and shape."""
    md = rs.schema_table_markdown()
    rows = [line for line in md.splitlines() if line.startswith("| `")]
    assert len(rows) == sum(len(fields) for _, fields in rs.TABLES)
    assert "| `iteration_time` | s | float | no |" in md
    assert "| `x` | rad/mm | (nx,) | yes |" in md
    for title, _ in rs.TABLES:
        assert f"**{title}**" in md


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda d: d["waypoints"][1].pop("x"), r"^waypoints\[1\]\.x: missing \(required\)$"),
        (lambda d: d["executed"].update(dt=-1.0), r"^executed\.dt: "),
        (lambda d: d["executed"].pop("q"), r"^executed\.q: missing \(required\)$"),
        (lambda d: d["reference"].update(tip=[[1.0, 2.0]]), r"^reference\.tip: "),
        (lambda d: d["task"].update(goal="here"), r"^task\.goal: "),
    ],
)
def test_a_missing_or_malformed_field_is_one_line_naming_its_key(raw_run, change, message):
    """The reader's checks come from the declarations: the error names the field's key."""
    doc = json.loads(json.dumps(raw_run))
    change(doc)
    with pytest.raises(InputError, match=message):
        read_result(doc)
