"""The rod-correction surrogate (crtraj.model.cosserat._surrogate) against fresh rod solves, its map and its cache.

A small robot keeps the builds cheap: one 100 mm segment with heavy discs (so gravity matters), 20 rod steps (a
node every 5 mm) and 5 collision points at 0, 25, 50, 75 and 100 mm, which fall on rod nodes: the fresh solves
are compared at their raw nodes, not through the surrogate's own spline along the arc."""

from __future__ import annotations

import logging

import casadi as ca
import numpy as np
import pytest

import crtraj.model.cosserat._surrogate as rs
from crtraj.core.errors import InputError
from crtraj.model.cosserat._drive import RodDrive
from crtraj.model.cosserat._surrogate import (
    RodSurrogate,
    SurrogateOptions,
    disc_to_square,
    key_digest,
    square_to_disc,
    surrogate_key,
)
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot, Segment

ROBOT = Robot("small", 2.5, (Segment(100.0, theta_max=2.0),), z_range=(-50.0, 50.0), collision_points=5)
MECH = Mechanics(steps=20, disc_mass=2.0)
OPTIONS = SurrogateOptions(grid=7, holdout=40, seed=1)
NODES = [0, 5, 10, 15, 20]  # the rod nodes at the collision points' arcs


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory):
    return tmp_path_factory.mktemp("surrogate_cache")


@pytest.fixture(scope="module")
def surrogate(cache) -> RodSurrogate:
    return RodSurrogate.load(ROBOT, MECH, OPTIONS, cache_dir=cache)


def _fresh(mech: Mechanics, xs: np.ndarray) -> np.ndarray:
    """The rod's points at the collision points (N, 5, 3) mm, by a new drive solved from the straight rod."""
    out = []
    for x in xs:
        shape = RodDrive(ROBOT, mech, pretension=1.0).shape_config(x)
        assert shape.is_success()
        out.append(shape.points[NODES])
    return np.array(out)


@pytest.mark.parametrize("mode", ["cable_length", "tension"])
def test_the_surrogate_equals_fresh_rod_solves_within_its_stated_bound(cache, mode: str) -> None:
    """On random configurations within the limits (another seed than the held-out set), PCC plus the surrogate
    is within the stated bounds of fresh rod solves, at every collision point and at the tip; PCC alone is
    not (so the surrogate corrects something), and the bound is not loose by more than ten times."""
    mech = MECH.with_(actuation=mode)
    sur = RodSurrogate.load(ROBOT, mech, OPTIONS, cache_dir=cache)
    assert sur.error is not None and sur.key["mechanics"]["actuation"] == mode
    xs = rs.sample_within_limits(ROBOT, 25, np.random.default_rng(99))
    rod = _fresh(mech, xs)
    pcc = np.array([np.asarray(Model(ROBOT).points(x)).reshape(-1, 3) for x in xs])
    mine = pcc + np.array([sur.delta(x) for x in xs])
    body = np.linalg.norm(mine - rod, axis=2).max()
    tip = np.linalg.norm(mine[:, -1] - rod[:, -1], axis=1).max()
    assert body <= sur.error.body_bound and tip <= sur.error.tip_bound, (body, tip, sur.error)
    assert np.linalg.norm(pcc - rod, axis=2).max() > 10.0 * sur.error.body_bound  # PCC misses by far more
    assert body > sur.error.body_bound / 10.0


def test_the_surrogate_is_the_table_at_its_nodes_and_differentiable(surrogate: RodSurrogate) -> None:
    """At grid nodes the spline returns the tabulated corrections; its Jacobian matches central differences."""
    axis = rs.grid_axis(OPTIONS.grid)
    for idx in [(0, 3), (2, 5), (6, 6), (3, 3)]:
        x = np.zeros(ROBOT.nx)
        x[:2] = rs.bending_at(ROBOT, axis[list(idx)]).ravel()
        np.testing.assert_allclose(surrogate.delta(x), surrogate.table[idx], atol=1e-10)
    x = np.array([0.7, -0.4, 12.0])
    xs = ca.MX.sym("x", ROBOT.nx)
    jac = ca.Function("j", [xs], [ca.jacobian(ca.vec(surrogate.function(xs)), xs)])
    got = np.asarray(jac(x))
    h = 1e-6
    fd = np.column_stack(
        [(surrogate.delta(x + h * e).ravel() - surrogate.delta(x - h * e).ravel()) / (2 * h) for e in np.eye(3)]
    )
    np.testing.assert_allclose(got, fd, atol=1e-6 * max(1.0, np.abs(fd).max()))
    assert np.all(got[:, -1] == 0.0)  # the base translation moves both bodies alike: no correction


def test_the_disc_map_round_trips() -> None:
    """square -> disc -> square is the identity on [-1, 1]^2, and the square's image is within the unit disc."""
    ab = np.random.default_rng(2).uniform(-1.0, 1.0, size=(200, 2))
    u, v = square_to_disc(ab[:, 0], ab[:, 1])
    assert np.all(u * u + v * v <= 1.0 + 1e-12)
    a, b = disc_to_square(ca.DM(u), ca.DM(v))
    np.testing.assert_allclose(np.column_stack([np.asarray(a).ravel(), np.asarray(b).ravel()]), ab, atol=1e-9)


def test_a_changed_robot_file_rebuilds_and_an_unchanged_one_loads(surrogate, cache, monkeypatch) -> None:
    """The same robot and mechanics load from the cache (no rod solve); each changed mechanics or model value
    changes the key, so a stale table is never found."""
    calls = []
    real = rs.build_table
    monkeypatch.setattr(rs, "build_table", lambda *a: calls.append(a) or real(*a))
    again = RodSurrogate.load(ROBOT, MECH, OPTIONS, cache_dir=cache)
    assert calls == [] and np.array_equal(again.table, surrogate.table) and again.error == surrogate.error
    base = key_digest(surrogate_key(ROBOT, MECH, OPTIONS))
    for mech in (MECH.with_(disc_mass=2.5), MECH.with_(actuation="tension"), MECH.with_(gravity=(-9.81, 0, 0))):
        assert key_digest(surrogate_key(ROBOT, mech, OPTIONS)) != base
    longer = Robot("small", 2.5, (Segment(101.0, theta_max=2.0),), z_range=(-50.0, 50.0), collision_points=5)
    assert key_digest(surrogate_key(longer, MECH, OPTIONS)) != base
    heavier = RodSurrogate.load(ROBOT, MECH.with_(disc_mass=2.5), SurrogateOptions(grid=5, holdout=5), cache_dir=cache)
    assert len(calls) == 1 and heavier.table.shape[0] == 5


@pytest.mark.parametrize("damage", ["table", "manifest", "truncate"])
def test_a_corrupt_cache_entry_is_rebuilt_not_used(cache, monkeypatch, caplog, damage: str) -> None:
    """A table whose bytes changed, a manifest that is not JSON, or a truncated table: rebuilt (one warning),
    and the rebuilt entry is the same as a clean build."""
    options = SurrogateOptions(grid=4, holdout=5, seed=3)
    clean = RodSurrogate.load(ROBOT, MECH, options, cache_dir=cache)
    table_path, manifest_path = rs.SurrogateStore(cache).paths(clean.digest)
    data = bytearray(table_path.read_bytes())
    if damage == "table":
        data[-20] ^= 0xFF
        table_path.write_bytes(bytes(data))
    elif damage == "truncate":
        table_path.write_bytes(bytes(data[: len(data) // 2]))
    else:
        manifest_path.write_text("{ not json", encoding="utf-8")
    calls = []
    real = rs.build_table
    monkeypatch.setattr(rs, "build_table", lambda *a: calls.append(a) or real(*a))
    with caplog.at_level(logging.WARNING, logger="crtraj"):
        again = RodSurrogate.load(ROBOT, MECH, options, cache_dir=cache)
    assert len(calls) == 1 and "rebuilding" in caplog.text
    np.testing.assert_array_equal(again.table, clean.table)
    assert rs.SurrogateStore(cache).read(ROBOT, again.key) is not None  # whole again


def test_bad_options_are_one_line() -> None:
    """A grid too coarse for a cubic spline, or no held-out configuration: one InputError naming it."""
    with pytest.raises(InputError, match=r"surrogate grid: must be in \[4, 40\]"):
        SurrogateOptions(grid=3)
    with pytest.raises(InputError, match="surrogate holdout"):
        SurrogateOptions(holdout=0)
