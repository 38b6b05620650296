"""Replanning on live obstacle states (crtraj.world.feed.ObstacleFeed over UDP on 127.0.0.1), on virtual time.

The feed, the loop's real-time pacing and the sender share one virtual clock: the loop's sleeps advance it,
and the sender (a 100 Hz motion-capture bridge) runs at exact virtual times, each datagram delivered over UDP
and received (sequenced by the feed's condition) before time moves on. The outcome does not depend on how
fast the machine is.
"""

from __future__ import annotations

import json

import numpy as np
from conftest import LoopClock
from feed_clock import VirtualClock

from crtraj.app.run_output import run_context
from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._run_record import RunStatus
from crtraj.io.results import run_document
from crtraj.world.feed import ObstacleFeed
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene
from crtraj.world.sources import FeedObstacles

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=2.0, name="ball")


class _Bridge:
    """Sends the ball's state every 10 ms of virtual time until `stop_after` s, then falls silent.
    Each datagram is received by the feed before the clock moves on."""

    def __init__(self, feed: ObstacleFeed, clock: VirtualClock, stop_after: float) -> None:
        self.feed, self.clock, self.stop_after = feed, clock, stop_after
        self.t0 = clock()
        self.sent = 0

    def _send(self, data: bytes) -> None:
        ObstacleFeed.send_raw(self.feed.address, data)
        self.sent += 1
        assert self.feed.wait_for(self.sent), "the feed did not receive a datagram"

    def __call__(self, now: float) -> bool:
        s = now - self.t0
        if s > self.stop_after:
            return False
        r = BALL.radius + BALL.amplitude * np.sin(BALL.omega * s)
        msg = [{"id": "ball", "center": list(BALL.center), "radius": float(r), "timestamp": s}]
        self._send(json.dumps(msg).encode())
        if self.sent == 30:  # hostile datagrams mid-run: each is rejected, recorded, and changes nothing
            self._send(b"[" * 60000)
            self._send(json.dumps([{**msg[0], "id": "intruder", "radius": 900.0}]).encode())
            self._send(json.dumps([{**msg[0], "timestamp": 1e9}]).encode())
        return True


def test_live_feed_run_moves_safely_and_holds_when_the_feed_goes_stale(model):
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    opts = ReplanOptions(horizon=6, points=12, solver="sqp")
    lopts = LoopOptions(duration=2.5)
    clock = VirtualClock(1000.0)
    with ObstacleFeed(0, max_age=0.1, expected=["ball"], clock=clock) as feed:
        bridge = _Bridge(feed, clock, stop_after=1.15)
        clock.every(0.01, bridge)
        clock.sleep(0.0)  # the first state arrives before the loop is built; building takes no virtual time
        source = FeedObstacles(feed, scene, window=1.5)
        loop = ClosedLoop.build(
            model,
            scene,
            model.tip_position(XG),
            XS,
            options=opts,
            loop_options=lopts,
            goal_config=XG,
            obstacles=source,
            clock=LoopClock(clock),
        )
        t_start = clock()
        run = loop.run()
        took = clock() - t_start
    assert run.live
    # paced in real time on the shared clock: every step waited for its time (2.5 s of loop time)
    assert abs(took - 2.5) < 1e-6 and run.late_steps == 0
    st = np.array(run.step_status)
    # while the feed is fresh the robot moves, every move verified against the live states
    early = run.t[1:] <= 1.2 + 1e-9
    assert set(st[early]) <= {"move", "suboptimal"}
    assert np.all(run.clearance_bound[1:][early] >= 0.0)
    assert np.linalg.norm(run.x[10] - run.x[0]) > 0.05
    # the recorded states are the ball's: fixed centre, radius within its breathing range, changing
    rec = run.radii[: int(np.argmax(st == "stale")) + 1, 0]
    assert np.all((rec >= 22.0 - 0.2 * 16.0) & (rec <= 38.0 + 0.2 * 16.0))  # 16 mm/s for at most max_age
    assert np.ptp(rec) > 2.0
    np.testing.assert_allclose(run.centers[: len(rec), 0], np.tile(BALL.center, (len(rec), 1)), atol=1e-9)
    # the feed falls silent after 1.15 s and is stale 0.1 s later, at the step from 1.3 s: from then on the
    # loop holds still and says so
    late = run.t[1:] > 1.3 + 1e-9
    assert np.all(st[late] == "stale") and np.all(st[~late] != "stale")
    assert all(run.solver_status[k].startswith("skipped: obstacle feed stale") for k in np.flatnonzero(late))
    k0 = int(np.flatnonzero(late)[0])
    for k in np.flatnonzero(late):
        np.testing.assert_array_equal(run.x[k + 1], run.x[k0])
    # the hostile datagrams: rejected, each with its reason, in the run's record and its result file
    feed_rec = run.feed
    assert feed_rec["counts"] == {"oversize": 1, "timestamp": 1, "unknown_id": 1}
    assert feed_rec["rejected"] == 3 and run.summary()["feed_rejected"] == 3
    kinds = {e["kind"]: e for e in feed_rec["events"]}
    assert set(kinds) == {"oversize", "timestamp", "unknown_id"}
    assert "'intruder'" in kinds["unknown_id"]["message"] and "60000 bytes" in kinds["oversize"]["message"]
    assert all(0.2 <= e["t"] <= 0.4 for e in feed_rec["events"])  # sent at 0.3 s, logged at the next step
    res = run_document(run, run_context(loop))
    assert res["feed"]["counts"] == feed_rec["counts"] and res["summary"]["feed_events"] == feed_rec["counts"]


def test_live_run_without_any_state_ends_with_no_obstacles_on_virtual_time(model):
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    opts = ReplanOptions(horizon=6, points=12, solver="sqp")
    lopts = LoopOptions(duration=1.0)
    clock = VirtualClock(0.0)
    with ObstacleFeed(0, max_age=0.1, expected=["ball"], clock=clock) as feed:
        source = FeedObstacles(feed, scene, window=1.5)
        loop = ClosedLoop.build(
            model,
            scene,
            model.tip_position(XG),
            XS,
            options=opts,
            loop_options=lopts,
            goal_config=XG,
            obstacles=source,
            clock=LoopClock(clock),
        )
        ObstacleFeed.send(feed.address, [{"id": "intruder", "center": [0, 0, 0], "radius": 1.0, "timestamp": 0.0}])
        assert feed.wait_for(1)
        run = loop.run()
    # waited 2 s of the injected clock for a first state, then said why
    assert run.status is RunStatus.NO_OBSTACLES and clock() >= 2.0
    assert "no obstacle state received yet" in run.message
    assert run.feed["counts"] == {"unknown_id": 1} and run.feed["events"][0]["kind"] == "unknown_id"
