"""Live obstacle feed: UDP JSON messages, ordering, rates, stale detection, hostile datagrams."""

from __future__ import annotations

import json

import numpy as np
import pytest
from feed_clock import VirtualClock

import crtraj.world.feed as feedmod
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import Problem
from crtraj.world.feed import MAX_DATAGRAM_BYTES, FeedOptions, ObstacleFeed, StaleFeedError, nesting_depth_exceeds

pytestmark = pytest.mark.timeout(60)


def _msg(oid, c, r, ts):
    return json.dumps({"id": oid, "center": c, "radius": r, "timestamp": ts}).encode()


def test_states_rates_and_prediction_from_messages():
    with ObstacleFeed(max_age=1.0) as feed:
        feed.ingest(_msg("a", [0, 90, 330], 60.0, 10.0), now=100.0)
        feed.ingest(_msg("b", [-10, -70, 250], 45.0, 10.0), now=100.0)
        # sent 0.5 s later, arrived 20 ms late: its data is as old as its sender time says
        feed.ingest(_msg("a", [1, 92, 330], 61.0, 10.5), now=100.52)
        st = feed.latest(now=100.55)
        assert st.ids == ("a", "b") and not st.stale
        np.testing.assert_allclose(st.centers, [[1, 92, 330], [-10, -70, 250]])
        np.testing.assert_allclose(st.radii, [61.0, 45.0])
        # slopes over the sender's time stamps: 2 mm/s in x, 4 mm/s in y, 2 mm/s radius
        np.testing.assert_allclose(st.velocities, [[2, 4, 0], [0, 0, 0]])
        np.testing.assert_allclose(st.radius_rates, [2.0, 0.0])
        np.testing.assert_allclose(st.ages, [0.05, 0.55])
        # the keep-out sphere: centre on the line, radius grown at max(rate, speed) = sqrt(20) mm/s
        c, r = st.predict(0.5)
        np.testing.assert_allclose(c[0], [2, 94, 330])
        np.testing.assert_allclose(r, [61.0 + 0.5 * np.sqrt(20.0), 45.0])
        # an older or equal time stamp for the same id is ignored, and recorded
        assert feed.ingest(_msg("a", [500, 500, 500], 1.0, 10.5), now=100.56) == 0
        assert feed.out_of_order == 1 and feed.counts == {"out_of_order": 1}
        assert "not after" in feed.events()[-1].message
        np.testing.assert_allclose(feed.latest(100.56).centers[0], [1, 92, 330])


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
    ("payload", "kind", "error"),
    [
        (b"{not json", "decode", "Expecting property name"),
        (b"\xff\xfe{\x00", "decode", "not UTF-8"),
        (_msg("a", [0, 0], 1.0, 0.0), "invalid", "message.center: expected 3 finite numbers"),
        (_msg("a", [0, 0, 1e300], 1.0, 0.0), "invalid", "message.center: expected 3 finite numbers"),
        (_msg("a", [0, 0, 0], -1.0, 0.0), "invalid", "message.radius: expected a finite number in [0"),
        (_msg("a", [0, 0, 0], 1.0, 1e300), "invalid", "message.timestamp: expected a finite number within"),
        (b'{"id": "a", "center": [0, 0, 0], "radius": 1, "timestamp": 0, "colour": 1}', "invalid", "message.colour"),
        (b'{"id": "a", "center": [0, 0, 0], "radius": 1}', "invalid", "message.timestamp: missing"),
        (b'{"id": true, "center": [0, 0, 0], "radius": 1, "timestamp": 0}', "invalid", "message.id: expected"),
        (b'{"id": "a", "center": [0, 0, NaN], "radius": 1, "timestamp": 0}', "invalid", "message.center: expected"),
        # a 5000-digit integer: Python's int parser refuses it (ValueError, not a JSONDecodeError)
        (b'{"id": "a", "center": [0, 0, 0], "radius": ' + b"9" * 5000 + b', "timestamp": 0}', "decode", "not JSON"),
        (b'{"id": "a", "center": [0, 0, 0], "radius": 1e400, "timestamp": 0}', "invalid", "message.radius"),
        (b"[1, 2]", "invalid", "message: expected a JSON object"),
    ],
)
def test_bad_messages_are_counted_recorded_not_fatal(payload, kind, error):
    with ObstacleFeed() as feed:
        assert feed.ingest(payload, now=1.0) == 0
        assert feed.rejected == 1 and error in feed.last_error
        assert feed.counts == {kind: 1}
        (ev,) = feed.events()
        assert ev.kind == kind and error in ev.message and ev.received == 1.0 and "\n" not in ev.message
        assert feed.ingest(_msg(7, [1, 2, 3], 4.0, 0.0), now=1.0) == 1  # integer ids are fine
        assert feed.latest(1.0).ids == ("7",)


def test_oversize_datagrams_are_rejected_before_parsing(monkeypatch):
    calls = []
    real = feedmod.json.loads
    monkeypatch.setattr(feedmod.json, "loads", lambda s: calls.append(len(s)) or real(s))
    good = _msg("a", [1, 2, 3], 4.0, 0.0)
    with ObstacleFeed() as feed:
        at_limit = good + b" " * (MAX_DATAGRAM_BYTES - len(good))
        assert len(at_limit) == MAX_DATAGRAM_BYTES and feed.ingest(at_limit, now=0.0) == 1
        assert calls == [MAX_DATAGRAM_BYTES]
        big = _msg("a", [9, 9, 9], 4.0, 1.0) + b" " * MAX_DATAGRAM_BYTES
        assert feed.ingest(big, now=0.01) == 0
        assert calls == [MAX_DATAGRAM_BYTES]  # never decoded
        assert feed.counts == {"oversize": 1}
        assert f"{len(big)} bytes exceeds the {MAX_DATAGRAM_BYTES}-byte limit" in feed.events()[0].message
        np.testing.assert_allclose(feed.latest(0.01).centers[0], [1, 2, 3])


def test_nesting_depth_scan_skips_strings():
    assert not nesting_depth_exceeds('[{"id": "[[[[[[", "center": [1, 2, 3]}]', 3)
    assert not nesting_depth_exceeds(r'{"id": "\"[[[[\\", "center": [1, 2, 3]}', 3)
    assert nesting_depth_exceeds('[{"id": "a", "center": [[1], 2, 3]}]', 3)
    assert nesting_depth_exceeds("[" * 60000, 3)


def test_deep_nesting_never_kills_the_receiver_thread(monkeypatch):
    clock = VirtualClock(10.0)
    with ObstacleFeed(max_age=0.5, expected=["[x]"], clock=clock) as feed:
        ok = [{"id": "[x]", "center": [1.0, 2.0, 3.0], "radius": 4.0, "timestamp": 0.0}]  # brackets in a string
        ObstacleFeed.send(feed.address, ok)
        for data in (b"[" * 60000, b"[" * 16000, b"{" * 16000, b'{"a":' * 3000):
            ObstacleFeed.send_raw(feed.address, data)
        assert feed.wait_for(5)
        assert feed.alive
        assert feed.counts == {"oversize": 1, "nesting": 3}
        # the parser's own recursion limit is a second line of defence: caught, recorded, not fatal
        monkeypatch.setattr(feedmod, "MAX_NESTING", 10**9)
        ObstacleFeed.send_raw(feed.address, b"[" * 8000 + b"]" * 8000)
        assert feed.wait_for(6) and feed.alive
        assert feed.counts.get("decode") == 1
        # a bug while handling a datagram is recorded, and the thread goes on
        monkeypatch.setattr(feedmod, "_decode", lambda data: 1 / 0)
        ObstacleFeed.send(feed.address, ok)
        assert feed.wait_for(7) and feed.alive
        assert feed.counts.get("internal") == 1 and "ZeroDivisionError" in feed.events()[-1].message
        monkeypatch.undo()
        clock.sleep(0.1)
        ok[0]["timestamp"] = 0.1
        ObstacleFeed.send(feed.address, ok)
        assert feed.wait_for(8)
        st = feed.require_fresh()
        assert st.ids == ("[x]",) and st.timestamps[0] == 0.1 and st.ages[0] == 0.0
        assert feed.rejected == 6


def test_absurd_timestamps_never_make_later_messages_stale():
    with ObstacleFeed(max_age=0.1, expected=["a"]) as feed:
        for k in range(5):
            assert feed.ingest(_msg("a", [0, 0, 0], 10.0, 50.0 + 0.01 * k), now=1.0 + 0.01 * k) == 1
        # beyond the timestamp bound: invalid; within it but far from the receiver's clock: out of window
        assert feed.ingest(_msg("a", [0, 0, 0], 10.0, 1e300), now=1.05) == 0
        assert feed.ingest(_msg("a", [0, 0, 0], 10.0, 1e9), now=1.05) == 0
        assert feed.counts == {"invalid": 1, "timestamp": 1}
        assert "maps +1e+09 s from its arrival" in feed.events()[-1].message
        for k in range(5, 30):
            assert feed.ingest(_msg("a", [0, 0, 0], 10.0, 50.0 + 0.01 * k), now=1.0 + 0.01 * k) == 1
        st = feed.require_fresh(1.3)
        assert st.timestamps[0] == pytest.approx(50.29) and st.ages[0] == pytest.approx(0.01)


def test_absurd_first_timestamp_resynchronises_after_max_age():
    with ObstacleFeed(max_age=0.1, expected=["a"]) as feed:
        assert feed.ingest(_msg("a", [0, 0, 0], 10.0, 1e9), now=1.0) == 1  # nothing to compare it with yet
        h = 1.0 / 64.0  # s, exact in binary: the step where 0.1 s of silence is passed is unambiguous
        accepted = [feed.ingest(_msg("a", [0, 0, 0], 10.0, h * k), now=1.0 + h * k) for k in range(1, 20)]
        # rejected while the absurd state was fresh (up to 6/64 s), then the id restarts from the sane sender
        assert accepted == [0] * 6 + [1] * 13
        assert feed.counts == {"out_of_order": 6, "resync": 1}
        st = feed.require_fresh(1.0 + 19 * h)
        assert st.timestamps[0] == 19 * h and st.ages[0] == 0.0


def test_unknown_ids_are_ignored_counted_and_recorded():
    with ObstacleFeed(max_age=0.1, expected=["a"]) as feed:
        both = json.dumps(
            [
                {"id": "intruder", "center": [0, 0, 0], "radius": 500.0, "timestamp": 0.0},
                {"id": "a", "center": [1, 2, 3], "radius": 4.0, "timestamp": 0.0},
            ]
        ).encode()
        assert feed.ingest(both, now=2.0) == 1
        assert feed.ingest(_msg("intruder", [0, 0, 0], 5.0, 0.01), now=2.01) == 0
        st = feed.require_fresh(2.05)  # the unknown id never made the feed stale or incomplete
        assert st.ids == ("a",)
        assert feed.counts == {"unknown_id": 2} and feed.rejected == 2
        assert all("unknown obstacle 'intruder'" in e.message for e in feed.events())
    with ObstacleFeed(max_age=0.1) as feed:  # without expected ids every id is taken, up to a bound
        for k in range(feedmod.MAX_TRACKS + 3):
            feed.ingest(_msg(f"o{k}", [0, 0, 0], 1.0, 0.0), now=0.0)
        assert len(feed.latest(0.0).ids) == feedmod.MAX_TRACKS and feed.counts == {"too_many_ids": 3}


def test_velocity_is_fitted_over_a_window_and_bounded():
    with ObstacleFeed(max_age=0.2, options=FeedOptions(max_speed=300.0)) as feed:
        # two messages 1 us apart with 0.5 mm jitter: no speed can be told from that
        feed.ingest(_msg("a", [0.0, 0.0, 100.0], 20.0, 0.0), now=0.0)
        feed.ingest(_msg("a", [0.5, 0.0, 100.0], 20.0, 1e-6), now=1e-6)
        st = feed.latest(1e-6)
        np.testing.assert_array_equal(st.velocities[0], 0.0)
        c, r = st.predict(0.1)
        assert np.linalg.norm(c[0] - st.centers[0]) == 0.0 and r[0] == 20.0
        # a still ball measured with +-0.5 mm jitter at 100 Hz: the windowed fit stays near zero
        rng = np.random.default_rng(1)
        for k in range(1, 40):
            p = np.array([0.0, 0.0, 100.0]) + rng.uniform(-0.5, 0.5, 3)
            feed.ingest(_msg("a", p.tolist(), 20.0, 0.01 * k), now=0.01 * k)
        assert np.linalg.norm(feed.latest(0.39).velocities[0]) < 15.0
        # a ball moving at 100 mm/s along y: recovered
        for k in range(40, 80):
            feed.ingest(_msg("a", [0.0, 100.0 * 0.01 * (k - 40), 100.0], 20.0, 0.01 * k), now=0.01 * k)
        np.testing.assert_allclose(feed.latest(0.79).velocities[0], [0, 100, 0], atol=1e-6)
        assert "speed_clamped" not in feed.counts
        # a 1 m jump in 60 ms (16,700 mm/s): clamped to max_speed, logged, never beyond it
        feed.ingest(_msg("a", [1000.0, 39.0, 100.0], 20.0, 0.85), now=0.85)
        st = feed.latest(0.85)
        assert np.linalg.norm(st.velocities[0]) == pytest.approx(300.0)
        assert feed.counts["speed_clamped"] == 1 and "clamped to 300 mm/s" in feed.events()[-1].message
        c, r = st.predict(0.1)
        assert np.linalg.norm(c[0] - st.centers[0]) <= 30.0 + 1e-9
        assert np.linalg.norm(c[0] - st.centers[0]) + st.radii[0] <= r[0] + 1e-9


def test_udp_loopback_end_to_end_on_virtual_time():
    clock = VirtualClock(100.0)
    with ObstacleFeed(max_age=0.2, clock=clock) as feed:
        host, port = feed.address
        assert host == "127.0.0.1" and port > 0
        for k in range(11):
            states = [
                {"id": "A", "center": [125.0, 105.0 + k, 335.0], "radius": 20.0 + k, "timestamp": 0.01 * k},
                {"id": "B", "center": [175.0, 175.0, 360.0], "radius": 35.0, "timestamp": 0.01 * k},
            ]
            ObstacleFeed.send(feed.address, states)
            assert feed.wait_for(k + 1)  # arrived, stamped with the virtual time
            clock.sleep(0.01)
        st = feed.require_fresh()
        assert st.ids == ("A", "B")
        np.testing.assert_allclose(st.centers[0], [125, 115, 335])
        np.testing.assert_allclose(st.velocities[0], [0, 100, 0])
        np.testing.assert_allclose(st.radius_rates[0], 100.0)
        np.testing.assert_allclose(st.ages, [0.01, 0.01], atol=1e-9)
        assert feed.describe()["accepted"] == 22 and feed.rejected == 0
        clock.sleep(0.2)
        assert feed.latest().stale  # nothing new for longer than max_age


def test_feed_options():
    with pytest.raises(InputError, match=r"feed\.max_age: must be > 0"):
        ObstacleFeed(max_age=0.0)
    assert FeedOptions.from_table(Table({}, "feed")) == FeedOptions()
    o = FeedOptions.from_table(Table({"max_speed": 80.0, "min_span": 0.02}, "feed"))
    assert o.max_speed == 80.0 and o.min_span == 0.02 and o.to_dict()["velocity_window"] == 0.25
    for bad, msg in (
        ({"max_speed": 0.0}, r"feed\.max_speed: must be > 0"),
        ({"max_speed": float("nan")}, r"feed\.max_speed: must be finite"),
        ({"max_speed": 1e6}, r"feed\.max_speed: must be <= 100000"),
        ({"max_speed": 1e300}, r"feed\.max_speed: must be within"),
        ({"min_span": 1.0}, r"feed\.min_span: must not exceed feed\.velocity_window"),
        ({"colour": 1}, r"feed\.colour: unknown key"),
    ):
        with pytest.raises(InputError, match=msg):
            FeedOptions.from_table(Table(bad, "feed"))
    # a problem file's [feed] section reaches the options
    prob = Problem.from_dict(_problem_with_feed({"max_speed": 42.0}))
    assert prob.options(FeedOptions, "feed").max_speed == 42.0


def _problem_with_feed(feed: dict) -> dict:
    from pathlib import Path

    from crtraj.core.fileio import read_toml

    root = Path(__file__).resolve().parent.parent / "problems"
    data = read_toml(root / "paper_dynamic.toml")
    data["robot"] = str(root / "robots" / "cdsr2.toml")
    data["feed"] = feed
    return data
