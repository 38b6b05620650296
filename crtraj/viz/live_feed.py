"""A live view of a running loop: the loop hands each step's state over without waiting; a separate thread draws.

`LiveFeed.publish` is the hook a closed loop calls once per step (it only stores the newest state under a lock, so
the loop's timing does not change); the feed's thread draws the newest state at most `rate` times a second and
counts the states it never drew (`dropped`). Drawing goes to anything with ``display(x)`` and
``set_obstacles(centers, radii)`` (a live `crtraj.viz.view.Visualizer`). Lengths in mm, times in s.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

log = logging.getLogger(__name__)

MAX_RATE_HZ = 30.0


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
        self._lock = threading.Condition()
        self._pending: LiveState | None = None
        self._closed = False
        self.published = 0  # states handed over by the loop
        self.drawn = 0  # states drawn
        self.dropped = 0  # states replaced by a newer one before they were drawn
        self.failed = 0  # draws that raised (logged; the loop is never stopped by its view)
        self._thread = threading.Thread(target=self._run, name="crtraj-live-view", daemon=True)
        self._thread.start()

    def publish(self, t: float, x: Any, centers: Any, radii: Any) -> None:
        """The loop's hook, once per step: keep this state as the newest (never blocks on drawing)."""
        state = LiveState(
            float(t), np.array(x, dtype=float), np.array(centers, dtype=float), np.array(radii, dtype=float)
        )
        with self._lock:
            if self._pending is not None:
                self.dropped += 1
            self._pending = state
            self.published += 1
            self._lock.notify()

    def _take(self) -> LiveState | None:
        with self._lock:
            while self._pending is None and not self._closed:
                self._lock.wait()
            state, self._pending = self._pending, None
            return state

    def _run(self) -> None:
        next_at = self._clock()
        while True:
            state = self._take()
            if state is None:
                return
            try:
                self.drawer.display(state.x)
                self.drawer.set_obstacles(state.centers, state.radii)
                self.drawn += 1
            except Exception:  # a failed draw must not stop the feed nor reach the loop
                self.failed += 1
                log.warning("live view: drawing the state at t = %.3f s failed", state.t, exc_info=True)
            next_at += self.period
            wait = next_at - self._clock()
            if wait > 0:
                self._sleep(wait)
            else:
                next_at = self._clock()  # late: do not try to catch up with a burst

    def close(self) -> None:
        """Draw what is pending, stop the thread and wait for it (idempotent)."""
        with self._lock:
            self._closed = True
            self._lock.notify()
        self._thread.join()

    def summary(self) -> dict[str, int]:
        """Counters: published, drawn, dropped, failed."""
        return {"published": self.published, "drawn": self.drawn, "dropped": self.dropped, "failed": self.failed}
