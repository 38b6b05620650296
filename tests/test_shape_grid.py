"""The point sets' distance grid (`GridDistance`, issue 39): below the obstacle's exact distance everywhere, within
its stated error near the set (and the error is not loose: the measured gap uses most of it), the NLPs' CasADi
interpolant and the checker's numpy lookup agree, and the node values come back from the cache unchanged."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from crtraj.world.geometry import (
    BOX_SMOOTH_ERROR,
    Box,
    GridDistance,
    Mesh,
    MovingShape,
    PointCloud,
    Pose,
    exact_distance,
)


def _sets():
    cloud = np.random.default_rng(3).normal(size=(300, 3))
    cloud = 20.0 * cloud / np.linalg.norm(cloud, axis=1, keepdims=True)
    ball = trimesh.creation.icosphere(subdivisions=1, radius=20.0)  # 80 triangles, corners of its box far off
    return {"mesh": Mesh(ball.triangles, 6.0), "points": PointCloud(cloud, 2.0)}


@pytest.fixture(scope="module", params=["mesh", "points"])
def grid(request, tmp_path_factory):
    """(the set, its grid) built into an empty cache folder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CRTRAJ_CACHE_DIR", str(tmp_path_factory.mktemp("grid-cache")))
        shape = _sets()[request.param]
        yield shape, GridDistance(shape)


def test_grid_is_below_the_exact_distance_and_within_its_error(grid):
    """At 4,000 random points in and around the grid: lookup <= exact distance (brute force, every triangle or
    point) everywhere; within 30 mm of the set and inside the grid, exact - lookup <= `error`, and somewhere
    above half of it (a bound tightened to half would fail)."""
    shape, g = grid
    y = np.random.default_rng(0).uniform(g.lo - 30.0, g.hi + 30.0, size=(4000, 3))
    exact = exact_distance(MovingShape(shape), y, 0.0)
    gap = exact - g.lookup(y)
    assert gap.min() >= 0.0
    near = (y > g.lo).all(axis=1) & (y < g.hi).all(axis=1) & (exact < 30.0)
    assert near.sum() > 200
    assert gap[near].max() <= g.error
    assert gap[near].max() > 0.5 * g.error


def test_interpolant_and_lookup_agree_and_the_cache_returns_the_grid(grid, monkeypatch, tmp_path):
    """The CasADi expression the NLPs use gives the numpy lookup's numbers (to 1e-9 mm) where the grid decides,
    and where the set's bounding box does, at most the smooth box's shortfall below them (outside the grid too);
    a second build with the same cache folder reads the same node values."""
    shape, g = grid
    y = np.random.default_rng(1).uniform(g.lo - 20.0, g.hi + 20.0, size=(500, 3))
    nlp, checker = g.numeric(y), g.lookup(y)
    assert np.all(nlp <= checker + 1e-9)
    assert np.all(checker - nlp <= BOX_SMOOTH_ERROR * 0.5 + 1e-9)
    lo, hi = shape.points.min(axis=0) - shape.ball, shape.points.max(axis=0) + shape.ball
    box = MovingShape(Box(tuple(0.5 * (hi - lo)), Pose(tuple(0.5 * (hi + lo))))).distance(y, 0.0)
    grid_decides = checker > box + 1e-6
    assert grid_decides.sum() > 20
    np.testing.assert_allclose(nlp[grid_decides], checker[grid_decides], atol=1e-9)
    monkeypatch.setenv("CRTRAJ_CACHE_DIR", str(tmp_path))
    first = GridDistance(shape)
    assert list((tmp_path / "grids").glob("*.npy"))
    again = GridDistance(shape)
    np.testing.assert_array_equal(first.values, again.values)
    np.testing.assert_array_equal(first.values, g.values)
