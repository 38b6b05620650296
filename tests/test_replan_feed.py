"""Replanning on live obstacle states (crtraj.world.feed.ObstacleFeed over UDP on 127.0.0.1), in real time."""

from __future__ import annotations

import threading
import time

import numpy as np

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import ClosedLoop, FeedObstacles
from crtraj.world.feed import ObstacleFeed
from crtraj.world.scene import Obstacle, Scene

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=2.0, name="ball")


def _sender(address, stop_after: float, stop: threading.Event) -> None:
    """A motion-capture bridge: the ball's state at 100 Hz for `stop_after` s, then silence."""
    t0 = time.monotonic()
    while not stop.is_set():
        s = time.monotonic() - t0
        if s > stop_after:
            return
        r = BALL.radius + BALL.amplitude * np.sin(BALL.omega * s)
        ObstacleFeed.send(address, [{"id": "ball", "center": list(BALL.center), "radius": float(r), "timestamp": s}])
        time.sleep(0.01)


def test_live_feed_run_moves_safely_and_holds_when_the_feed_goes_stale(model):
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    opts = ReplanOptions(horizon=6, points=12, solver="sqp", duration=2.5)
    stop = threading.Event()
    with ObstacleFeed(0, max_age=0.1, expected=["ball"]) as feed:
        th = threading.Thread(target=_sender, args=(feed.address, 1.2, stop), daemon=True)
        th.start()
        try:
            source = FeedObstacles(feed, scene, window=1.5)
            loop = ClosedLoop(model, scene, model.tip_position(XG), XS, options=opts, goal_config=XG, obstacles=source)
            t_start = time.monotonic()
            run = loop.run()
            took = time.monotonic() - t_start
        finally:
            stop.set()
            th.join(1.0)
    assert run.live
    assert took >= 2.0  # paced by the wall clock (2.5 s of loop time)
    st = np.array(run.status)
    # while the feed is fresh the robot moves, every move verified against the live states
    early = run.t[1:] <= 0.9
    assert set(st[early]) <= {"move", "suboptimal"}
    assert np.all(run.clearance_bound[1:][early] >= 0.0)
    assert np.linalg.norm(run.x[10] - run.x[0]) > 0.05
    # the recorded states are the ball's: fixed centre, radius within its breathing range, changing
    rec = run.radii[: int(np.argmax(st == "stale")) + 1, 0]
    assert np.all((rec >= 22.0 - 0.2 * 16.0) & (rec <= 38.0 + 0.2 * 16.0))  # 16 mm/s for at most max_age
    assert np.ptp(rec) > 2.0
    # once the feed is silent the loop holds still and says so
    late = run.t[1:] >= 1.6
    assert np.all(st[late] == "stale")
    assert all(run.solver_status[k].startswith("skipped: obstacle feed stale") for k in np.flatnonzero(late))
    k0 = int(np.flatnonzero(late)[0])
    for k in np.flatnonzero(late):
        np.testing.assert_array_equal(run.x[k + 1], run.x[k0])


class _FakeFeed:
    """An ObstacleFeed stand-in that returns one fixed state."""

    def __init__(self, state) -> None:
        self.state = state

    def latest(self):
        return self.state


def test_feed_snapshot_bounds_the_constant_velocity_prediction():
    from crtraj.world.feed import FeedState

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
