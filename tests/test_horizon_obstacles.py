"""The horizon's obstacle spheres tabulated before the run (`crtraj.control.horizon._obstacles`, issue 29): every
looked-up row is the per-step computation's bit for bit (scenes that fit the QP's slots and scenes the broad
phase packs), a time or scene the table does not hold is computed as before, the table cannot be written, and a
loop over the table takes the same decisions as one without it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_horizon_broad import OPTS, XG, XS, _far_scene, _scene_near

from crtraj.control.horizon._obstacles import ObstacleTable
from crtraj.control.horizon._replanner import Replanner
from crtraj.control.loop import ClosedLoop, LoopOptions, RunStatus

DT = OPTS.dt
TIMES = np.array([0.0] + [round((k + 1) * DT, 12) for k in range(300)])  # the loop's step times


def _direct(rp: Replanner, scene, t0: float, x0=None) -> np.ndarray:
    """`obstacles_from_scene` with no table (the per-step computation)."""
    rp.obstacle_table.tabulate(scene, np.zeros(0))
    return rp.obstacles_from_scene(scene, t0, x0)


@pytest.mark.parametrize("slots", [2, 8])
def test_every_tabulated_row_is_the_per_step_computation_bit_for_bit(model, slots):
    """Moving, breathing spheres (5, more or fewer than the slots; with more, the broad phase packs them from
    the table's centres and radii): at every step time of a 30 s run, and at times off the grid (computed per
    step), the parameter (packed from the table or by the broad phase) equals the untabulated call's bit for bit."""
    rng = np.random.default_rng(3)
    rp = Replanner(model, OPTS, max_obstacles=slots, safety_distance=5.0)
    scene = _scene_near(rng, model, XS, 5)
    off = TIMES[:40] + 0.0371
    want = {float(t): _direct(rp, scene, t, XS) for t in (*TIMES, *off)}
    rp.obstacle_table.tabulate(scene, TIMES)
    assert (
        rp.obstacle_table.row(scene, float(TIMES[-1])) == len(TIMES) - 1
        and rp.obstacle_table.row(scene, 0.0371) is None
    )
    for t, w in want.items():
        got = rp.obstacles_from_scene(scene, t, XS)
        assert got.shape == w.shape and np.array_equal(got, w), t
    assert (rp.obstacle_table.packed is None) == (slots < 5)


def test_another_scene_is_computed_per_step_and_the_table_is_read_only(model):
    """A scene other than the tabulated one (even an equal one) is not looked up; writing into a handed-out row
    raises instead of changing later steps' obstacles."""
    rng = np.random.default_rng(4)
    rp = Replanner(model, OPTS, max_obstacles=8, safety_distance=5.0)
    scene = _scene_near(rng, model, XS, 3)
    other = dataclasses.replace(scene)
    rp.obstacle_table.tabulate(scene, TIMES)
    assert rp.obstacle_table.row(other, 0.5) is None and rp.obstacle_table.row(scene, 0.5) is not None
    row = rp.obstacles_from_scene(scene, 0.5, XS)
    with pytest.raises(ValueError, match="read-only"):
        row[0, 0] = 1.0
    assert np.array_equal(rp.obstacles_from_scene(other, 0.5, XS), _direct(rp, other, 0.5, XS))


def test_a_loop_over_the_table_takes_the_decisions_of_one_without_it(model, monkeypatch):
    """The 12-obstacle scene with a 2-slot QP (the broad phase in every step), run with the table and with it
    empty: the same statuses, configurations and clearances at every step; the tabulated run looked every
    step's obstacles up; it reaches the goal with no collision and no D_sf breach."""
    scene = _far_scene(model)
    opts = dataclasses.replace(OPTS, qp_obstacles=2)
    looked: list[bool] = []
    row, tabulate = ObstacleTable.row, ObstacleTable.tabulate

    def counted(table, s, t0):  # the table's own answer, counted
        j = row(table, s, t0)
        looked.append(j is not None)
        return j

    monkeypatch.setattr(ObstacleTable, "row", counted)

    def run():
        looked.clear()
        loop = ClosedLoop.build(
            model, scene, model.tip_position(XG), XS, options=opts, loop_options=LoopOptions(duration=20.0),
            goal_config=XG,
        )  # fmt: skip
        assert loop.replanner.max_obstacles == 2
        return loop.run(), list(looked)

    with_table, hits = run()
    monkeypatch.setattr(ObstacleTable, "tabulate", lambda table, s, times: tabulate(table, s, np.zeros(0)))
    without, misses = run()
    assert with_table.status is RunStatus.REACHED, with_table.summary_line()
    assert with_table.collisions == 0 and with_table.safety_violations == 0
    assert all(hits) and len(hits) >= with_table.steps and not any(misses)
    assert with_table.step_status == without.step_status
    np.testing.assert_allclose(with_table.x, without.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(with_table.clearance_bound, without.clearance_bound, rtol=0, atol=1e-9)
    np.testing.assert_allclose(with_table.clearance, without.clearance, rtol=0, atol=1e-9)
