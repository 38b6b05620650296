"""The stream's fixed-rate loop: one step every period on the stream's clock, and how late the steps started.

A step that starts more than one period late counts as a late tick; when the loop falls more than five periods
behind (the machine stalled), it resynchronises to now rather than sending a burst. Times in s.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from crtraj.core.clock import Clock


class RatePacer:
    """Runs a step every `dt` s on a clock and keeps the lateness statistics."""

    def __init__(self, dt: float) -> None:
        self.dt = dt
        self.late_ticks = 0  # steps started more than one period late
        self.max_lateness = 0.0  # s, the latest start (negative: every step started early)

    def run(self, clock: Clock, step: Callable[[float], bool], stop: threading.Event) -> None:
        """Call `step(now)` once per period until it returns False or `stop` is set."""
        dt = self.dt
        nxt = clock.now()
        while not stop.is_set():
            now = clock.now()
            late = now - nxt
            if late > dt:
                self.late_ticks += 1
            self.max_lateness = max(self.max_lateness, late)
            if not step(now):
                return
            nxt += dt
            delay = nxt - clock.now()
            if delay > 0:
                clock.sleep(delay)
            elif -delay > 5 * dt:
                nxt = clock.now()  # far behind (machine stalled): resynchronise rather than burst
