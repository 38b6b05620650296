"""The result schema (crtraj.io.results): what is written is what is read, for plans and runs; a document that
does not follow the schema gives one line naming the field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.plan import plan_problem
from crtraj.app.run_output import run_context
from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import ClosedLoop, LoopOptions
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_json
from crtraj.io.problem import Problem
from crtraj.io.results import SCHEMA_VERSION, read_result, run_document
from crtraj.io.run_files import read_npz, save_npz
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"


@pytest.fixture(scope="module")
def plan():
    return plan_problem(Problem.load(PROBLEMS / "paper_static.toml"), seed=3)


@pytest.fixture(scope="module")
def run(model):
    xs, xg = np.array([0.3, 0.0, 0.0, 0.0, 0.0]), np.array([-0.3, 0.2, -0.1, 0.1, -10.0])
    scene = Scene(obstacles=(Obstacle(center=(-3.5, 76.8, 394.4), radius=20.0, amplitude=4.0, omega=0.5),))
    opts = ReplanOptions(horizon=6, points=12, solver="sqp")
    loop = ClosedLoop.build(
        model, scene, model.tip_position(xg), xs, options=opts, loop_options=LoopOptions(duration=1.0), goal_config=xg
    )
    return loop, loop.run()


def test_plan_document_round_trips_through_a_file(plan, tmp_path):
    assert plan.result.is_success()
    path = atomic_write_json(tmp_path / "p.json", plan.document())
    res = read_result(path)
    r = plan.result
    assert (res.kind, res.schema, res.source) == ("plan", SCHEMA_VERSION, str(path))
    assert res.robot == plan.model.robot and res.scene == plan.scene
    assert (res.status, res.success, res.safety) == (str(r.status), True, True)
    assert (res.collisions, res.safety_violations) == (0, 0)
    # the arrays survive JSON exactly (repr round trip of float64)
    np.testing.assert_array_equal(res.t, r.t)
    np.testing.assert_array_equal(res.x, r.configs)
    np.testing.assert_array_equal(res.q, r.cables)
    np.testing.assert_array_equal(res.tip, r.tips)
    # obstacle states per waypoint: the scene's own time functions at the waypoint times
    centers, radii = plan.scene.states(r.t)
    np.testing.assert_allclose(res.centers, centers.reshape(len(r.t), -1, 3), rtol=0, atol=0)
    np.testing.assert_allclose(res.radii, radii.reshape(len(r.t), -1), rtol=0, atol=0)
    np.testing.assert_array_equal(res.start, plan.problem.require_task().start)
    rec = res.motion_record()
    assert rec.success and rec.scene == plan.scene and rec.q is res.q


def test_run_document_round_trips_through_a_file(model, run, tmp_path):
    loop, r = run
    doc = run_document(r, run_context(loop), seed=4)
    path = atomic_write_json(tmp_path / "run.json", doc)
    res = read_result(path)
    assert (res.kind, res.schema) == ("replan", SCHEMA_VERSION)
    assert res.robot == model.robot and res.scene == loop.scene
    assert (res.status, res.success, res.safety) == (str(r.status), r.is_success(), True)
    assert (res.collisions, res.safety_violations) == (r.collisions, r.safety_violations)
    np.testing.assert_array_equal(res.t, r.t)
    np.testing.assert_array_equal(res.x, r.x)
    np.testing.assert_array_equal(res.q, r.q)
    np.testing.assert_array_equal(res.centers, r.centers)
    np.testing.assert_array_equal(res.radii, r.radii)
    assert doc["problem"]["seed"] == 4


def test_plan_and_run_documents_share_one_header(plan, run):
    loop, r = run
    plan_doc, run_doc = plan.document(), run_document(r, run_context(loop))
    keys = ("kind", "schema", "crtraj_version", "casadi_version", "numpy_version", "created", "problem", "robot")
    keys += ("scene", "task", "options")
    assert list(plan_doc)[: len(keys)] == list(keys) and list(run_doc)[: len(keys)] == list(keys)
    assert plan_doc["schema"] == run_doc["schema"] == SCHEMA_VERSION
    assert set(plan_doc["problem"]) == set(run_doc["problem"]) == {"name", "path", "seed"}


def test_a_document_without_schema_is_version_1(plan):
    doc = json.loads(json.dumps(plan.document()))
    doc.pop("schema")
    assert read_result(doc).schema == 1
    doc.pop("kind")  # version 1 files may omit the kind: they are plans
    assert read_result(doc).kind == "plan"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(schema=2), r"^schema: unsupported version 2 \(this crtraj reads version 1\)$"),
        (lambda d: d.update(schema="1"), r"^schema: unsupported version '1'"),
        (lambda d: d.update(schema=True), r"^schema: unsupported version True"),
        (lambda d: d.update(kind="fly"), r"^kind: must be plan or replan, got 'fly'$"),
        (lambda d: d.pop("kind"), r"^kind: missing \(required\)$"),
        (lambda d: d.pop("robot"), r"^robot: missing \(required\)$"),
        (lambda d: d.pop("waypoints"), r"^waypoints: missing \(required\)$"),
        (lambda d: d["waypoints"][2].pop("x"), r"^waypoints\[2\]\.x: missing \(required\)$"),
        (lambda d: d["waypoints"][3].pop("q"), r"^waypoints\[3\]\.q: missing \(required\)$"),
        (lambda d: d.update(success="yes"), r"^success: expected true or false, got 'yes'$"),
        (lambda d: d["summary"].update(collisions=-1), r"^summary\.collisions: expected a count >= 0, got -1$"),
        (lambda d: d.update(scene=[1]), r"^scene: expected an object, got list$"),
        (lambda d: d["scene"].update(safety_distance=-1), r"^scene\.safety_distance: must be >= 0"),
    ],
)
def test_a_document_off_the_schema_gives_one_line_naming_the_field(plan, tmp_path, edit, message):
    doc = json.loads(json.dumps(plan.document()))
    edit(doc)
    with pytest.raises(InputError, match=message) as info:
        read_result(doc)
    assert "\n" not in str(info.value)
    # from a file, the same line with the file's name in front
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as info:
        read_result(path)
    assert str(info.value) == f"{path}: " + str(read_error(doc))


def read_error(doc: dict) -> InputError:
    try:
        read_result(doc)
    except InputError as exc:
        return exc
    raise AssertionError("no error")


def test_a_plan_below_the_safety_distance_counts_as_a_violation(plan):
    doc = json.loads(json.dumps(plan.document()))
    doc["summary"]["min_clearance_mm"] = -0.5
    assert read_result(doc).safety_violations == 1


def test_run_npz_round_trips_every_array_of_the_run(run, tmp_path):
    """save_npz writes, and read_npz reads back, the run's own arrays under the schema's keys."""
    _, r = run
    arrays = read_npz(save_npz(r, tmp_path / "run.npz"))
    np.testing.assert_array_equal(arrays["t"], r.t)
    np.testing.assert_array_equal(arrays["dense_x"], r.dense_x)
    np.testing.assert_array_equal(arrays["iter_time"], r.iter_time)
    np.testing.assert_array_equal(arrays["executed"], r.executed)
    assert tuple(arrays["status"]) == r.step_status and tuple(arrays["reason"]) == r.reason
    for i, (k, tips) in enumerate(r.reference_tips):
        assert int(arrays[f"reference_{i}_step"]) == k
        np.testing.assert_array_equal(arrays[f"reference_{i}_tip"], tips)


def test_run_npz_missing_or_inconsistent_array_is_one_line_naming_the_key(run, tmp_path):
    """A run.npz without an array, or with per-step arrays of the wrong length, is refused naming the key."""
    _, r = run
    with np.load(save_npz(r, tmp_path / "run.npz"), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    short = {**arrays, "nlp_time": arrays["nlp_time"][:-1]}
    np.savez(tmp_path / "short.npz", **short)
    with pytest.raises(InputError, match=r"short\.npz: nlp_time: \d+ steps, but t has \d+ times$"):
        read_npz(tmp_path / "short.npz")
    del arrays["clearance"]
    np.savez(tmp_path / "gone.npz", **arrays)
    with pytest.raises(InputError, match=r"gone\.npz: clearance: missing \(required\)$"):
        read_npz(tmp_path / "gone.npz")
