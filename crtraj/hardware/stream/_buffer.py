"""The streamer's set-point buffer: queued time-stamped actuator values and the cursor that walks them at the rate.

A source queues set-points (trajectory time in s, actuator values in rad for servos and mm for the z stage) with
increasing times. Once streaming starts, the cursor steps through trajectory time at the stream period from the
first queued time; between queued set-points the values are interpolated linearly, and a stamp on the set-points'
own grid sends that set-point bit for bit. `finish` marks the end: the last set-point is then sent at its own
time (maybe off the rate grid).
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from crtraj.core.errors import InputError

_GRID_TOL = 1e-9  # s: a cursor stamp this close to the last queued time counts as reaching it
_KEEP_CONSUMED = 4096  # consumed set-points a long live stream keeps before dropping them


@dataclass(frozen=True)
class Due:
    """What the cursor asks for next. kind: ``move`` (send `values` stamped `stamp` s; `final`: the last one),
    ``settle`` (the final set-point was sent) or ``underrun`` (nothing queued yet for `stamp`)."""

    kind: str
    stamp: float
    values: np.ndarray | None = None
    final: bool = False


class SetpointBuffer:
    """Queued set-points and the streaming cursor. dt: the stream period (s)."""

    def __init__(self, dt: float) -> None:
        self.dt = dt
        self._stamps: list[float] = []  # s, increasing
        self._values: list[np.ndarray] = []  # actuator values (rad, mm), one array per stamp
        self.finished = False  # no more set-points will come
        self._origin = 0.0  # s: trajectory time of the cursor's tick 0
        self._ticks = 0  # move frames sent since streaming started
        self.sent_stamp = 0.0  # s: stamp of the last move frame sent; hold frames repeat it
        self._final_sent = False

    # ------------------------------------------------------------ queue
    @property
    def stamps(self) -> list[float]:
        """A copy of the queued (not yet dropped) set-point times (s)."""
        return list(self._stamps)

    @property
    def values(self) -> list[np.ndarray]:
        """A copy of the list of queued set-point values (rad, mm)."""
        return list(self._values)

    def __len__(self) -> int:
        return len(self._stamps)

    def _check_after_last(self, t: float) -> None:
        if self._stamps and not t > self._stamps[-1]:
            raise InputError(f"t: set-point times must increase (got {t:g} s after {self._stamps[-1]:g} s)")

    def append(self, t: float, values: np.ndarray) -> None:
        """Queue one set-point at time t (s); `InputError` unless t is after the last queued time."""
        self._check_after_last(t)
        self._stamps.append(t)
        self._values.append(values)

    def extend(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """Queue increasing stamps (M,) s with values (M, n); `InputError` unless the first is after the last."""
        if stamps.size:
            self._check_after_last(stamps[0])
        self._stamps.extend(stamps.tolist())
        self._values.extend(values)

    def finish(self) -> None:
        """No more set-points will come."""
        self.finished = True

    def clear(self) -> None:
        """Drop every queued set-point and the end mark (after a hold, a source starts again)."""
        self._stamps.clear()
        self._values.clear()
        self.finished = False

    def ready(self, prebuffer: float) -> bool:
        """Enough is queued to start moving: the end is marked or the queue spans `prebuffer` s."""
        return bool(self._stamps) and (self.finished or self._stamps[-1] - self._stamps[0] >= prebuffer)

    # ----------------------------------------------------------- cursor
    def begin(self) -> float:
        """Put the cursor on the first queued time and return it (s)."""
        self._origin = self._stamps[0]
        self.sent_stamp = self._origin
        self._ticks = 0
        self._final_sent = False
        return self._origin

    @property
    def last_stamp(self) -> float:
        """The last queued time (s)."""
        return self._stamps[-1]

    def due(self) -> Due:
        """The frame the cursor's next tick calls for (see `Due`)."""
        tau = self._origin + self._ticks * self.dt
        last = self._stamps[-1]
        if tau < last - _GRID_TOL:
            return Due("move", tau, self._interpolate(tau))
        if self.finished:
            if self._final_sent:
                return Due("settle", last)
            return Due("move", last, self._values[-1], final=True)  # the final set-point, maybe off the rate grid
        if tau <= last + _GRID_TOL:
            return Due("move", tau, self._values[-1])
        return Due("underrun", tau)

    def sent_stop_frame(self, stamp: float) -> None:
        """A frame of a stop left, stamped `stamp` (s): the hold frames after the stop repeat it (stamps never go
        back)."""
        self.sent_stamp = stamp

    def advance(self, due: Due) -> None:
        """The move frame `due` left: step the cursor on."""
        self.sent_stamp = due.stamp
        self._ticks += 1
        self._final_sent = due.final

    def _interpolate(self, tau: float) -> np.ndarray:
        j = bisect.bisect_right(self._stamps, tau)
        if j <= 0:
            return self._values[0]
        if j >= len(self._stamps):
            return self._values[-1]
        t0, t1 = self._stamps[j - 1], self._stamps[j]
        # a stamp on the set-points' own grid (up to rounding: tau0 + k dt vs t0 + (k - n) dt) sends that
        # set-point exactly, so what leaves is bit for bit what was verified
        eps = 1e-9 * max(1.0, abs(tau))
        if tau - t0 <= eps:
            out = self._values[j - 1]
        elif t1 - tau <= eps:
            out = self._values[j]
        else:
            w = (tau - t0) / (t1 - t0)
            out = (1 - w) * self._values[j - 1] + w * self._values[j]
        if j > _KEEP_CONSUMED:  # drop consumed set-points of long live streams
            del self._stamps[: j - 2]
            del self._values[: j - 2]
        return out
