"""crtraj.viz.live._feed: the loop's hook never waits for drawing; the view draws the newest state at most
30 times a second and counts what it dropped."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import pytest
from conftest import calls_of

from crtraj.viz.live._feed import LiveFeed, LiveState

HANG_S = 60.0  # a hang bound only; nothing here waits for time to pass


class _Drawer:
    """Records what it draws; the first draw waits until `release` is set."""

    def __init__(self, fail_at: int = -1) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.xs: list[np.ndarray] = []
        self.obstacles: list[tuple[np.ndarray, np.ndarray]] = []
        self.fail_at = fail_at

    def display(self, x):
        self.entered.set()
        assert self.release.wait(HANG_S)
        if len(self.xs) == self.fail_at:
            self.xs.append(None)
            raise RuntimeError("draw failed")
        self.xs.append(np.array(x))

    def set_obstacles(self, centers, radii):
        self.obstacles.append((np.array(centers), np.array(radii)))


class _VirtualClock:
    """Time stands still except when the view sleeps; every sleep is recorded."""

    def __init__(self) -> None:
        self.now = 0.0
        self.waits: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.waits.append(s)
        self.now += s


def _state(i):
    return float(i), np.full(5, float(i)), np.full((2, 3), float(i)), np.full(2, 10.0 + i)


def test_publishing_while_the_view_draws_drops_all_but_the_newest():
    """While the first state is being drawn, 9 more are published without waiting: the view then draws only
    the newest, and counts the 8 it never drew."""
    drawer, clock = _Drawer(), _VirtualClock()
    feed = LiveFeed(drawer, clock=clock, sleep=clock.sleep)
    feed.publish(*_state(0))
    assert drawer.entered.wait(HANG_S)
    for i in range(1, 10):
        feed.publish(*_state(i))  # returns although the view is stuck drawing state 0
    drawer.release.set()
    feed.close()
    assert [x[0] for x in drawer.xs] == [0.0, 9.0]
    np.testing.assert_array_equal(drawer.obstacles[-1][1], [19.0, 19.0])
    assert feed.summary() == {"published": 10, "drawn": 2, "dropped": 8, "failed": 0}
    # drawing takes no virtual time: after each draw the view waits one full 1/30 s period
    assert clock.waits == pytest.approx([1 / 30, 1 / 30])


def test_a_late_view_does_not_burst_and_a_failed_draw_is_counted():
    """A clock that jumps past the period: no wait, no catching up; a draw that raises is counted and logged,
    the next state is still drawn."""
    drawer, waits = _Drawer(fail_at=0), []
    ticks = iter(np.arange(0.0, 100.0, 1.0))
    feed = LiveFeed(drawer, rate=10.0, clock=lambda: float(next(ticks)), sleep=waits.append)
    drawer.release.set()
    feed.publish(*_state(0))
    feed.close()
    assert feed.summary() == {"published": 1, "drawn": 0, "dropped": 0, "failed": 1}
    assert waits == []


@pytest.mark.parametrize("rate", [0.0, 31.0, -1.0])
def test_rate_is_at_most_30_hz(rate):
    with pytest.raises(ValueError, match=r"^rate: expected \(0, 30\] Hz"):
        LiveFeed(_Drawer(), rate=rate)


def test_draws_stay_a_period_apart_after_a_quiet_spell():
    """The view starts, nothing comes for 5 s (the loop's set-up), then states: every draw is still followed by a
    full period's wait (1/30 s on the virtual clock, where drawing takes no time), so no two draws come closer
    than a period, also right after the quiet spell."""
    drawer, clock = _Drawer(), _VirtualClock()
    drawer.release.set()
    feed = LiveFeed(drawer, clock=clock, sleep=clock.sleep)
    clock.now = 5.0
    feed.publish(*_state(0))
    assert drawer.entered.wait(HANG_S)
    feed.publish(*_state(1))
    feed.close()
    assert feed.drawn >= 1 and clock.waits == pytest.approx([1 / 30] * feed.drawn)


def _until(condition) -> None:
    """Wait for `condition()` (a state of the view's thread), bounded by HANG_S only."""
    for _ in range(int(HANG_S / 0.001)):
        if condition():
            return
        time.sleep(0.001)
    raise AssertionError("the view's thread never got there")


def test_the_loops_hand_off_costs_the_same_whether_the_view_waits_or_draws():
    """The loop's `observe` makes the same calls on the loop's thread while the view's thread is stuck drawing
    and while it waits for the next state (a Condition's notify, for one, does more when a waiter is there): what
    the loop's thread does never depends on where the view's thread is."""
    drawer, clock = _Drawer(), _VirtualClock()
    feed = LiveFeed(drawer, clock=clock, sleep=clock.sleep)
    record = LiveState(0.0, np.zeros(5), np.zeros((2, 3)), np.ones(2))  # the frozen record the loop hands over
    feed.observe(record, None)
    assert drawer.entered.wait(HANG_S)
    drawing = [calls_of(lambda: feed.observe(record, None)) for _ in range(3)]
    drawer.release.set()

    def waiting() -> bool:
        """The view's thread is blocked waiting for the loop's next state (in the feed's `_take`)."""
        frame = sys._current_frames().get(feed._thread.ident)
        names = []
        while frame is not None:
            names.append(frame.f_code.co_name)
            frame = frame.f_back
        return bool(names) and names[0] in ("_take", "wait") and "_take" in names

    _until(lambda: feed.drawn == 2 and waiting())
    waited = [calls_of(lambda: feed.observe(record, None))]
    _until(lambda: feed.drawn == 3 and waiting())
    waited.append(calls_of(lambda: feed.observe(record, None)))
    feed.close()
    assert drawing == [drawing[0]] * 3 and waited == [drawing[0]] * 2, (drawing, waited)
    assert feed.published == 6 and feed.drawn == 4 and feed.dropped == 2
