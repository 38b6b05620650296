"""A live view of a running loop: the loop hands each step's state over without waiting; a separate thread draws.

`LiveFeed.observe` is the closed loop's observer port (`crtraj.control.ports.StepObserver`): the loop calls it once
per recorded step and it only puts a reference to the (frozen) record in a queue, one C call whose cost does not
depend on what the view's thread is doing (waiting or drawing), so the loop's timing does not change;
`LiveFeed.publish` does the same for a bare state. The feed's thread draws the newest state at most `rate`
times a second (each draw a full period after the previous one started) and counts the states it never drew
(`dropped`). Drawing goes to anything with ``display(x)`` and ``set_obstacles(centers, radii)`` (a live
`crtraj.viz.view.Visualizer`); a drawer that also has ``extend(entries)`` gets every (state, step) observed since
its last draw, so its plots miss no step; a drawer with ``draw(state, entries)`` gets both at once instead
(`crtraj.viz.live._child.ChildDrawer`: another process draws, with `crtraj.viz.live._page.LivePage`). Lengths in
mm, times in s.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

log = logging.getLogger(__name__)

MAX_RATE_HZ = 30.0
_CLOSE = object()  # the queue's last item: draw what is pending, then stop


class Drawer(Protocol):
    """What the feed draws on (a `crtraj.viz.view.Visualizer`)."""

    def display(self, x: Any) -> None: ...

    def set_obstacles(self, centers: Any, radii: Any) -> None: ...


@dataclasses.dataclass(frozen=True)
class LiveState:
    """One step of a loop: time t (s), configuration x (nx,), obstacle centres (m, 3) and radii (m,) mm."""

    t: float
    x: np.ndarray
    centers: np.ndarray
    radii: np.ndarray


class LiveFeed:
    """Draws a loop's newest state from its own thread, at most `rate` Hz (<= 30).

    drawer: what to draw on; clock/sleep: the time source (s) and the wait, injectable for tests.
    """

    def __init__(
        self,
        drawer: Drawer,
        rate: float = MAX_RATE_HZ,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not 0.0 < rate <= MAX_RATE_HZ:
            raise ValueError(f"rate: expected (0, {MAX_RATE_HZ:g}] Hz, got {rate}")
        self.drawer = drawer
        self.period = 1.0 / rate
        self._clock = clock
        self._sleep = sleep
        # the loop's hand-off: a C queue whose put costs the loop's thread the same whether the view's thread waits
        # on it or not (a Condition's notify does more work when a waiter is there), and never blocks on drawing
        self._inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        # every observed (state, step), by reference: a record's last reference goes with the feed, so neither
        # thread frees records (nor runs their deallocators) while the loop runs
        self._history: list[tuple[Any, Any]] = []
        self.published = 0  # states handed over by the loop
        self.drawn = 0  # states drawn
        self.dropped = 0  # states replaced by a newer one before they were drawn
        self.failed = 0  # draws that raised (logged; the loop is never stopped by its view)
        # s of this thread's CPU time spent drawing: while it runs Python it holds the GIL the loop's thread needs
        self.draw_cpu = 0.0
        self.first_draw: float | None = None  # clock time (s) the first and the last draw ended
        self.last_draw: float | None = None
        self._thread = threading.Thread(target=self._run, name="crtraj-live-view", daemon=True)
        self._thread.start()

    def publish(self, t: float, x: Any, centers: Any, radii: Any) -> None:
        """The loop's hook, once per step: keep this state as the newest (never blocks on drawing)."""
        state = LiveState(
            float(t), np.array(x, dtype=float), np.array(centers, dtype=float), np.array(radii, dtype=float)
        )
        self._keep(state, None, history=False)

    def observe(self, state: Any, step: Any) -> None:
        """The loop's observer port (`crtraj.control.ports.StepObserver`), once per recorded state: keeps a
        reference to the frozen `StateRecord` (and its `StepRecord`, None at the start); O(1), no copy."""
        self._keep(state, step, history=True)

    def _keep(self, state: Any, step: Any, history: bool) -> None:
        self.published += 1
        self._inbox.put((state, step, history))

    def _take(self) -> tuple[Any, list[tuple[Any, Any]], bool]:
        """On the view's thread: wait for the loop's next state, then take all it handed over since the last draw;
        (the newest state or None, the new (state, step) records, whether the feed is closing)."""
        items = [self._inbox.get()]
        while True:
            try:
                items.append(self._inbox.get_nowait())
            except queue.Empty:
                break
        closing = any(item is _CLOSE for item in items)
        kept = [item for item in items if item is not _CLOSE]
        new = [(state, step) for state, step, history in kept if history]
        self._history.extend(new)
        self.dropped += max(len(kept) - 1, 0)
        return (kept[-1][0] if kept else None), new, closing

    def _run(self) -> None:
        extend = getattr(self.drawer, "extend", None)
        draw = getattr(self.drawer, "draw", None)  # a drawer that takes the whole draw at once (another process)
        while True:
            state, new, closing = self._take()
            if state is None:
                return
            cpu, started = time.thread_time(), self._clock()
            try:
                if draw is not None:
                    draw(state, new)
                else:
                    if extend is not None and new:
                        extend(new)
                    self.drawer.display(state.x)
                    self.drawer.set_obstacles(state.centers, state.radii)
                self.drawn += 1
                self.last_draw = self._clock()
                self.first_draw = self.last_draw if self.first_draw is None else self.first_draw
            except Exception as exc:  # a failed draw must not stop the feed nor reach the loop
                self.failed += 1
                log.warning("live view: drawing the state at t = %.3f s failed: %s", state.t, exc)
                log.debug("live view: the failed draw", exc_info=True)
            self.draw_cpu += time.thread_time() - cpu
            # the next draw starts a period after this one started, never sooner: no burst to catch up after a
            # slow draw, nor after a wait for the loop's next state
            wait = started + self.period - self._clock()
            if wait > 0:
                self._sleep(wait)
            if closing:
                return

    def close(self) -> None:
        """Draw what is pending, stop the thread and wait for it (idempotent)."""
        self._inbox.put(_CLOSE)
        self._thread.join()

    def draw_rate(self) -> float:
        """Frames drawn per second between the first draw and the last (NaN with fewer than two)."""
        if self.drawn < 2 or self.first_draw is None or self.last_draw is None or self.last_draw <= self.first_draw:
            return float("nan")
        return (self.drawn - 1) / (self.last_draw - self.first_draw)

    def summary(self) -> dict[str, int]:
        """Counters: published, drawn, dropped, failed."""
        return {"published": self.published, "drawn": self.drawn, "dropped": self.dropped, "failed": self.failed}
