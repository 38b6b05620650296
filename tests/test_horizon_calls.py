"""The step's bookkeeping around the compiled call made cheaper (issue 29): `horizon_backends.replace` builds
what `dataclasses.replace` builds, and `Replanner._infeasible` answers what `horizon_status` answers, on calls
looked at by `RowCheck.record` (random points and rows, with NaN, infinities and violations about 1e-6)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from crtraj.control.horizon._backends import HorizonCall, HorizonQuery, RowCheck, ScreenStart, replace
from crtraj.control.horizon._options import HorizonStatus, ReplanOptions, horizon_status
from crtraj.control.horizon._replanner import Replanner

N, NX = 3, 5


def _check(rng: np.random.Generator) -> RowCheck:
    return RowCheck(-np.ones(N * NX), np.ones(N * NX), -np.ones(4), np.ones(4) * rng.uniform(0.5, 2.0), 2, True)


def _call(rng: np.random.Generator, check: RowCheck) -> HorizonCall:
    """A call whose point and rows hold, break by about 1e-6, or carry NaN / infinity; stats with or without the
    compiled call's own violation."""
    x = rng.uniform(-1.0, 1.0, N * NX)
    g = rng.uniform(-1.0, 1.0, 4)
    kind = rng.integers(6)
    if kind == 1:
        x[rng.integers(len(x))] = 1.0 + rng.choice([0.5e-6, 1e-6, 2e-6])
    elif kind == 2:
        g[rng.integers(len(g))] = rng.choice([np.nan, np.inf, -np.inf])
    elif kind == 3:
        x[rng.integers(len(x))] = rng.choice([np.nan, np.inf])
    sol = {"x": x, "g": g, "f": float(rng.normal()), "lam_x": np.zeros_like(x), "lam_g": np.zeros_like(g)}
    stats = {"success": bool(rng.integers(2)), "return_status": "s", "iter_count": 1}
    if kind == 4:
        stats["violation"] = float(rng.choice([0.0, 0.9e-6, 1e-6, 1.1e-6, np.nan]))
    return check.record(sol, stats, 1e-4)


def test_replace_builds_what_dataclasses_replace_builds():
    """For calls and queries, every field of the copy is the same object as `dataclasses.replace`'s, the
    original is unchanged, and an unknown name is a TypeError naming it."""
    rng = np.random.default_rng(0)
    check = _check(rng)
    for _ in range(50):
        r = _call(rng, check)
        changes = {"wall": float(rng.uniform()), "status": "again", "solves": int(rng.integers(1, 4))}
        changes = dict(list(changes.items())[: rng.integers(1, 4)])
        before = dict(vars(r))
        a, b = replace(r, **changes), dataclasses.replace(r, **changes)
        assert type(a) is HorizonCall and vars(a).keys() == vars(b).keys()
        assert all(vars(a)[k] is vars(b)[k] for k in vars(b))
        assert all(vars(r)[k] is before[k] for k in before)
    q = HorizonQuery(np.zeros(3), np.ones(2), start=ScreenStart(None, None))
    x0 = np.zeros(2)
    a, b = replace(q, x0=x0, start=None), dataclasses.replace(q, x0=x0, start=None)
    assert all(vars(a)[k] is vars(b)[k] for k in vars(b)) and a.x0 is x0 and q.x0 is not x0
    with pytest.raises(TypeError, match="no field 'wal'"):
        replace(r, wal=1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.x0 = None


def test_infeasible_is_horizon_status_failed(model):
    """On 400 recorded calls (a quarter of them not finite, some breaking a bound by 0.5-2e-6, some with the
    compiled call's own violation, NaN included), `_infeasible` is `horizon_status(...) is FAILED`; both
    answers occur."""
    rp = Replanner(model, ReplanOptions(horizon=N, points=6, solver="sqp"), max_obstacles=1, safety_distance=5.0)
    rng = np.random.default_rng(1)
    check = _check(rng)
    seen = set()
    for _ in range(400):
        r = _call(rng, check)
        want = horizon_status(False, r.x.reshape(N, NX), r.violation) is HorizonStatus.FAILED
        assert rp._infeasible(r) == want, (r.finite, r.violation)
        seen.add(want)
    assert seen == {True, False}
