"""Property: whatever datagrams arrive, the keep-out region the feed predicts contains the last measured sphere.

Message sequences are random: tiny and large gaps, jitter, huge and non-finite values, reordered and absurd
timestamps, unknown ids, garbage. The last measured sphere of an id is taken from the test's own record of
which datagrams `ingest` accepted; containment is checked independently: |predicted centre - measured centre| +
measured radius <= keep-out radius, and neither the centre nor the radius moves faster than max_speed.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from crtraj.world.feed import FeedOptions, ObstacleFeed
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene
from crtraj.world.sources import FeedObstacles

pytestmark = pytest.mark.timeout(300)

MAX_AGE = 0.1
OPTS = FeedOptions(max_speed=400.0)
WINDOW = 1.5


def _mostly(good, bad, n: int = 8):
    """`good` n times out of n + 1, else `bad` (so most messages are usable and tracks build up)."""
    return st.integers(0, n).flatmap(lambda k: good if k < n else bad)


_gap = st.one_of(st.just(0.0), st.floats(1e-9, 1e-5), st.floats(1e-3, 0.05), st.floats(0.05, 0.5))
_junk = st.one_of(st.floats(-1e6, 1e6), st.sampled_from([1e300, -1e300, math.nan, math.inf, 1e6, -1e6, 0.0, -1.0]))
_message = st.fixed_dictionaries(
    {
        "id": st.sampled_from(["a", "a", "a", "a", "b", "intruder"]),
        "gap": _gap,  # receiver time since the previous datagram (s)
        # sender step: None = the receiver's gap (a steady sender); else reordered, tiny, or absurd
        "dts": _mostly(
            st.none(), st.one_of(_gap, st.floats(-0.5, 0.0), st.sampled_from([1e9, -1e9, 1e300, math.nan])), 2
        ),
        "jitter": _mostly(st.tuples(*[st.floats(-0.5, 0.5)] * 3), st.tuples(_junk, _junk, _junk)),
        "radius": _mostly(st.floats(0.0, 100.0), _junk),
        "garbage": _mostly(st.none(), st.one_of(st.binary(max_size=40), st.just(b"[" * 20000))),
    }
)


def _tol(*mags: float) -> float:
    return 1e-9 * (1.0 + sum(abs(m) for m in mags))


class _Snapshot:
    """A feed stand-in for FeedObstacles that returns one state."""

    def __init__(self, state) -> None:
        self.state = state

    def latest(self):
        return self.state


def _check(feed: ObstacleFeed, measured: dict, now: float, template: Scene) -> None:
    for q in (now, now + 0.5 * MAX_AGE, now + MAX_AGE):
        s = feed.latest(q)
        assert set(s.ids) <= {"a", "b"}  # the unknown id never became an obstacle
        for j, oid in enumerate(s.ids):
            c_m, r_m = measured[oid]
            np.testing.assert_array_equal(s.centers[j], c_m)  # the feed's state is the last accepted message
            assert s.radii[j] == r_m
            assert np.all(np.isfinite(s.velocities[j])) and np.linalg.norm(s.velocities[j]) <= OPTS.max_speed * (
                1 + 1e-12
            )
            for dt in np.linspace(0.0, s.ages[j] + WINDOW, 7):
                C, R = s.predict(dt)
                d = float(np.linalg.norm(C[j] - c_m))
                assert d + r_m <= R[j] + _tol(*c_m, R[j]), (oid, dt, d, r_m, R[j])
                assert d <= OPTS.max_speed * dt + _tol(*c_m)
                assert R[j] - r_m <= OPTS.max_speed * dt + _tol(R[j])
        if s.stale:
            continue
        # the scene the closed loop plans with: same containment at every time of its window
        t_loop = 3.0
        scene, why = FeedObstacles(_Snapshot(s), template, window=WINDOW).at(t_loop)
        assert why == ""
        taus = np.linspace(0.0, WINDOW, 13)
        C, R = scene.states(t_loop + taus)
        for i, oid in enumerate(template.obstacles):
            c_m, r_m = measured[oid.name]
            d = np.linalg.norm(C[:, i] - c_m, axis=1)
            assert np.all(d + r_m <= R[:, i] + _tol(*c_m, *R[:, i]))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(_message, min_size=8, max_size=40),
    st.floats(-1e6, 1e6),
    st.floats(0.0, 1e6),
    st.tuples(*[st.floats(-2000.0, 2000.0)] * 3),
)
def test_keep_out_always_contains_the_last_measured_sphere(messages, t0_sender, t0_receiver, velocity):
    template = Scene(obstacles=(Obstacle((0, 0, 0), 1.0, name="a"), Obstacle((0, 0, 0), 1.0, name="b")))
    base = np.array([10.0, -20.0, 300.0])
    with ObstacleFeed(max_age=MAX_AGE, expected=["a", "b"], options=OPTS) as feed:
        feed.close()  # datagrams go through ingest only: the receiver thread is not needed
        now, ts = t0_receiver, {"a": t0_sender, "b": t0_sender, "intruder": t0_sender}
        measured: dict[str, tuple[np.ndarray, float]] = {}
        for m in messages:
            now += m["gap"]
            if m["garbage"] is not None:
                assert feed.ingest(m["garbage"], now) == 0
                continue
            ts[m["id"]] += m["gap"] if m["dts"] is None else m["dts"]
            # the true motion (up to 2000 mm/s, beyond max_speed) plus jitter or junk
            with np.errstate(all="ignore"):
                centre = (base + np.array(velocity) * (ts[m["id"]] - t0_sender) + np.array(m["jitter"])).tolist()
            data = json.dumps(
                {"id": m["id"], "center": centre, "radius": m["radius"], "timestamp": ts[m["id"]]}, allow_nan=True
            ).encode()
            if feed.ingest(data, now) == 1:
                assert m["id"] != "intruder"
                measured[m["id"]] = (np.array(centre, dtype=float), float(m["radius"]))
            _check(feed, measured, now, template)
        d = feed.describe()
        assert d["accepted"] + d["rejected"] == len(messages)  # every datagram is used or rejected, and counted
        assert sum(v for k, v in d["counts"].items() if k not in ("resync", "speed_clamped")) == d["rejected"]
