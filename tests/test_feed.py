"""Live obstacle feed: UDP JSON messages, ordering, rates, stale detection, bad messages."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from crtraj.core.errors import InputError
from crtraj.world.feed import ObstacleFeed, StaleFeedError

pytestmark = pytest.mark.timeout(30)


def _msg(oid, c, r, ts):
    return json.dumps({"id": oid, "center": c, "radius": r, "timestamp": ts}).encode()


def test_states_rates_and_prediction_from_messages():
    with ObstacleFeed(max_age=0.1) as feed:
        feed.ingest(_msg("a", [0, 90, 330], 60.0, 10.0), now=100.0)
        feed.ingest(_msg("b", [-10, -70, 250], 45.0, 10.0), now=100.0)
        feed.ingest(_msg("a", [1, 92, 330], 61.0, 10.5), now=100.02)
        st = feed.latest(now=100.05)
        assert st.ids == ("a", "b") and not st.stale
        np.testing.assert_allclose(st.centers, [[1, 92, 330], [-10, -70, 250]])
        np.testing.assert_allclose(st.radii, [61.0, 45.0])
        # finite differences over the sender's time stamps: 2 mm/s in x, 4 mm/s in y, 2 mm/s radius
        np.testing.assert_allclose(st.velocities, [[2, 4, 0], [0, 0, 0]])
        np.testing.assert_allclose(st.radius_rates, [2.0, 0.0])
        np.testing.assert_allclose(st.ages, [0.03, 0.05])
        c, r = st.predict(0.5)
        np.testing.assert_allclose(c[0], [2, 94, 330])
        np.testing.assert_allclose(r, [62.0, 45.0])
        # an older or equal time stamp for the same id is ignored
        assert feed.ingest(_msg("a", [500, 500, 500], 1.0, 10.5), now=100.06) == 0
        assert feed.out_of_order == 1
        np.testing.assert_allclose(feed.latest(100.06).centers[0], [1, 92, 330])


def test_stale_missing_and_empty_feeds():
    with ObstacleFeed(max_age=0.1, expected=["a", "b"]) as feed:
        st = feed.latest(now=5.0)
        assert st.stale and st.reason == "no obstacle state received yet" and st.age == np.inf
        feed.ingest(_msg("a", [0, 0, 0], 1.0, 0.0), now=5.0)
        assert feed.latest(5.01).reason == "no state for obstacle(s) b"
        feed.ingest(_msg("b", [0, 0, 0], 1.0, 0.0), now=5.05)
        assert not feed.latest(5.09).stale
        st = feed.latest(5.12)
        assert st.stale and st.reason == "obstacle a state is 120 ms old (limit 100 ms)"
        with pytest.raises(StaleFeedError, match="obstacle feed stale: obstacle a state is 120 ms old"):
            feed.require_fresh(5.12)


@pytest.mark.parametrize(
    ("payload", "error"),
    [
        (b"{not json", "Expecting property name"),
        (_msg("a", [0, 0], 1.0, 0.0), "message.center: expected 3 finite numbers"),
        (_msg("a", [0, 0, 0], -1.0, 0.0), "message.radius: expected a finite number >= 0"),
        (b'{"id": "a", "center": [0, 0, 0], "radius": 1, "timestamp": 0, "colour": 1}', "message.colour: unknown"),
        (b'{"id": "a", "center": [0, 0, 0], "radius": 1}', "message.timestamp: missing"),
        (b'{"id": true, "center": [0, 0, 0], "radius": 1, "timestamp": 0}', "message.id: expected"),
        (b'{"id": "a", "center": [0, 0, NaN], "radius": 1, "timestamp": 0}', "message.center: expected 3 finite"),
        (b"[1, 2]", "message: expected a JSON object"),
    ],
)
def test_bad_messages_are_counted_not_fatal(payload, error):
    with ObstacleFeed() as feed:
        assert feed.ingest(payload, now=1.0) == 0
        assert feed.rejected == 1 and error in feed.last_error
        assert feed.ingest(_msg(7, [1, 2, 3], 4.0, 0.0), now=1.0) == 1  # integer ids are fine
        assert feed.latest(1.0).ids == ("7",)


def test_udp_loopback_end_to_end():
    with ObstacleFeed(max_age=0.2) as feed:
        host, port = feed.address
        assert host == "127.0.0.1" and port > 0
        for k in range(5):
            states = [
                {"id": "A", "center": [125.0, 105.0 + k, 335.0], "radius": 20.0 + k, "timestamp": 0.01 * k},
                {"id": "B", "center": [175.0, 175.0, 360.0], "radius": 35.0, "timestamp": 0.01 * k},
            ]
            ObstacleFeed.send(feed.address, states)
        deadline = time.monotonic() + 5.0
        while feed.received < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        st = feed.require_fresh()
        assert st.ids == ("A", "B")
        np.testing.assert_allclose(st.centers[0], [125, 109, 335])
        np.testing.assert_allclose(st.velocities[0], [0, 100, 0])
        np.testing.assert_allclose(st.radius_rates[0], 100.0)
        time.sleep(0.3)
        assert feed.latest().stale  # nothing new for longer than max_age


def test_feed_options():
    with pytest.raises(InputError, match=r"feed\.max_age: must be > 0"):
        ObstacleFeed(max_age=0.0)
