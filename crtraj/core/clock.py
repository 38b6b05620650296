"""One injected clock for everything that paces, times or waits: the closed loop, the streamer, the feeds.

A `Clock` gives the time in seconds from an arbitrary origin and can sleep. Production code uses `WallClock`
(monotonic, `time.perf_counter`); tests inject a `VirtualClock`, whose time moves only when something sleeps or
the test advances it, so nothing in a test depends on how fast the machine is.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """A time source (s) with its own sleep."""

    def now(self) -> float:
        """The current time (s), monotonic, from an arbitrary origin."""
        ...

    def sleep(self, seconds: float) -> None:
        """Wait `seconds` (s) on this clock; a non-positive value returns at once."""
        ...


class WallClock:
    """The machine's monotonic high-resolution clock (`time.perf_counter`) and `time.sleep`."""

    def now(self) -> float:
        return time.perf_counter()

    def sleep(self, seconds: float) -> None:
        if seconds > 0.0:
            time.sleep(seconds)


class VirtualClock:
    """A clock that stands still until it sleeps or is advanced: tests run at the machine's speed, timed on it.

    start: the time (s) it starts at.
    """

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        if seconds > 0.0:
            self._t += float(seconds)

    def advance(self, seconds: float) -> None:
        """Move the time on by `seconds` (s) without anyone sleeping (work that 'took' that long)."""
        if seconds < 0.0:
            raise ValueError(f"seconds: must be >= 0, got {seconds}")
        self._t += float(seconds)


# Test seam, not a user-facing option: what `default_clock` makes. Production keeps the wall clock; end-to-end
# tests set it (pytest's monkeypatch) to return one shared `VirtualClock`, so that the command line's streamer,
# homing and Dynamixel link run on the same virtual time as an in-process simulator.
clock_factory: Callable[[], Clock] = WallClock


def default_clock() -> Clock:
    """The clock of a use case that was given none: `clock_factory()` (the `WallClock`)."""
    return clock_factory()
