"""A virtual clock for live-feed tests: time advances only when someone sleeps, and callbacks
scheduled at virtual times run, in order, at exactly those times as the sleep passes them."""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable


class VirtualClock:
    """Call it for the time (s); `sleep` advances it. `every(period, fn)` runs fn(now) at
    start, start + period, ... while fn returns True (a sender, a motion-capture frame rate)."""

    def __init__(self, now: float = 0.0) -> None:
        self.now = float(now)
        self._queue: list[tuple[float, int, float, Callable[[float], bool]]] = []
        self._seq = itertools.count()

    def __call__(self) -> float:
        return self.now

    def every(self, period: float, fn: Callable[[float], bool], start: float | None = None) -> None:
        t = self.now if start is None else float(start)
        heapq.heappush(self._queue, (t, next(self._seq), float(period), fn))

    def sleep(self, s: float) -> None:
        self.advance_to(self.now + max(float(s), 0.0))

    def advance_to(self, target: float) -> None:
        while self._queue and self._queue[0][0] <= target:
            t, _, period, fn = heapq.heappop(self._queue)
            self.now = max(self.now, t)
            if fn(self.now):
                heapq.heappush(self._queue, (t + period, next(self._seq), period, fn))
        self.now = max(self.now, target)
