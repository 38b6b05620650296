"""Obstacle sources (crtraj.world.sources): known motion and a live feed's constant-velocity prediction,
both usable as the closed loop's obstacle-source port."""

from __future__ import annotations

import numpy as np

from crtraj.control.ports import ObstacleSource
from crtraj.world.feed import FeedState
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene
from crtraj.world.sources import FeedObstacles, SceneObstacles


def test_scene_obstacles_are_the_scene_itself_at_every_time():
    scene = Scene(obstacles=(Obstacle((0.0, 0.0, 300.0), 20.0, amplitude=5.0, omega=1.0, name="a"),))
    src = SceneObstacles(scene)
    assert isinstance(src, ObstacleSource) and not src.live
    for t in (0.0, 1.7, 42.0):
        snap, why = src.at(t)
        assert snap is scene and why == ""
    assert src.new_events() == [] and src.describe() == {}


class _FakeFeed:
    """An ObstacleFeed stand-in that returns one fixed state."""

    def __init__(self, state) -> None:
        self.state = state

    def latest(self):
        return self.state


def test_feed_snapshot_bounds_the_constant_velocity_prediction():
    c = np.array([[10.0, 20.0, 300.0], [-40.0, 0.0, 200.0]])
    v = np.array([[5.0, -3.0, 1.0], [0.0, 0.0, 0.0]])
    r = np.array([30.0, 20.0])
    rd = np.array([6.0, -4.0])  # one grows, one shrinks
    ages = np.array([0.03, 0.05])
    state = FeedState(("a", "b"), c, r, v, rd, np.zeros(2), ages, 0.05, False)
    template = Scene(obstacles=(Obstacle((0, 0, 0), 1.0, name="a"), Obstacle((0, 0, 0), 1.0, name="b")))
    W, t = 1.2, 7.3
    snap, why = FeedObstacles(_FakeFeed(state), template, window=W).at(t)
    assert why == ""
    tau = np.linspace(0.0, W, 61)
    C, R = snap.states(t + tau)
    for j in range(2):
        # centre exactly on the extrapolated line, radius never below the extrapolated one
        np.testing.assert_allclose(C[:, j], c[j] + (ages[j] + tau)[:, None] * v[j], atol=1e-9)
        assert np.all(R[:, j] >= r[j] + (ages[j] + tau) * rd[j] - 1e-9)
    stale = FeedState(("a",), c[:1], r[:1], v[:1], rd[:1], np.zeros(1), ages[:1], 0.05, False)
    snap, why = FeedObstacles(_FakeFeed(stale), template, window=W).at(t)
    assert snap is None and "no state for b" in why


def test_feed_obstacles_implement_the_port_and_pass_on_the_feed_events():
    class Event:
        def __init__(self, i: int) -> None:
            self.i = i

    class Feed:
        """Keeps every event; `events(start)` returns those from index start on, as ObstacleFeed does."""

        def __init__(self) -> None:
            self.all = [Event(i) for i in range(3)]

        def events(self, start: int):
            return self.all[start:]

        def describe(self):
            return {"accepted": 7, "events": ["dropped from the source's description"]}

    template = Scene(obstacles=(Obstacle((0, 0, 0), 1.0, name="a"),))
    feed = Feed()
    src = FeedObstacles(feed, template, window=1.0)
    assert isinstance(src, ObstacleSource) and src.live
    assert [e.i for e in src.new_events()] == [0, 1, 2]
    assert src.new_events() == []  # each event is handed over once
    feed.all.append(Event(3))
    assert [e.i for e in src.new_events()] == [3]
    assert src.describe() == {"accepted": 7}
