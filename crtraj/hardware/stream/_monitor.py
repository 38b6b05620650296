"""The stream's watch on the device: its telemetry, its acknowledgements, how well it follows, and the timeouts.

`StreamMonitor` reads what the device sends back (decoded, checked against this run's session and actuator count,
logged), remembers which set-points it has not acknowledged yet, and answers the watchdog questions the stream
asks every tick: has telemetry gone silent, has the device stopped acknowledging (``ack_timeout``), does it lag
the acknowledged set-point by more than ``following_tolerance``, has the source run dry, has it settled. Times in
s (the stream's clock), values in actuator units (rad for servos, mm for the z stage).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import Frame, FrameError, Telemetry, seq_after
from crtraj.hardware.stream._log import RunLog
from crtraj.hardware.stream._options import StreamOptions

_MAX_UNACKED = 1 << 16  # unacknowledged set-points remembered (a dead link while held keeps the newest only)


class StreamMonitor:
    """Telemetry, acknowledgements and watchdog timers of one stream.

    session: this run's session number; actuators: names, units and count of the values; options: the
    `StreamOptions` (timeouts in s, tolerances in rad or mm); log: the run log; first_seq: the PING's sequence
    number (nothing after it is acknowledged yet).
    """

    def __init__(self, session: int, actuators: Actuators, options: StreamOptions, log: RunLog, first_seq: int) -> None:
        self._session = session
        self._actuators = actuators
        self._options = options
        self._log = log
        self._sent_seq = first_seq  # the newest sequence number sent
        # set-points not yet acknowledged: (seq, send time s, values); the values of the last acknowledged one
        self._unacked: deque[tuple[int, float, np.ndarray]] = deque()
        self._ack = first_seq
        self._acked_values: np.ndarray | None = None
        self.last: Telemetry | None = None  # the last valid telemetry frame
        self.last_time = 0.0  # s: when it arrived
        self.received = 0  # valid telemetry frames
        self.errors = 0  # invalid ones
        self._refused_base: int | None = None  # the device's refused / limited counters at the first telemetry
        self._limited_base: int | None = None
        self._underrun_since: float | None = None  # s: when the source last ran dry (None: it has not)
        self._settle_since: float | None = None  # s: when settling started

    # ----------------------------------------------------------- sending
    def sent(self, seq: int, now: float, values: np.ndarray) -> None:
        """A frame `seq` with `values` left at `now` (s): it awaits acknowledgement."""
        self._sent_seq = seq
        self._unacked.append((seq, now, values))
        if len(self._unacked) > _MAX_UNACKED:  # a dead link while held: keep the newest only
            self._unacked.popleft()

    # --------------------------------------------------------- receiving
    def _bad(self, wall: float, error: str) -> None:
        self.errors += 1
        self._log.write({"type": "rx-bad", "wall": wall, "error": error})

    def accept(self, data: bytes, now: float, wall: float) -> Telemetry | None:
        """Decode and check one datagram received at `now` (s; `wall`: since the start); log it, take its
        acknowledgement, and return it if it is this session's newest valid telemetry (None otherwise)."""
        try:
            msg = Frame.decode(data)
        except FrameError as exc:
            self._bad(wall, str(exc))
            return None
        if not isinstance(msg, Telemetry):
            self._bad(wall, "not a telemetry frame")
            return None
        if msg.session != self._session:
            self._bad(wall, f"telemetry of session {msg.session}")
            return None
        if self.last is not None and not seq_after(msg.seq, self.last.seq):
            return None  # reordered or duplicated: keep the newest
        if msg.positions.size != self._actuators.n:
            self._bad(wall, f"{msg.positions.size} positions")
            return None
        self.last = msg
        self.last_time = now
        self.received += 1
        self._log.write(
            {
                "type": "rx",
                "wall": wall,
                "seq": msg.seq,
                "stamp": msg.stamp,
                "ack": msg.ack,
                "status": msg.status,
                "counters": msg.counters(),
                "positions": msg.positions,
            }
        )
        if self._refused_base is None:
            self._refused_base = msg.refused
        if self._limited_base is None:
            self._limited_base = msg.limited
        self._take_ack(msg.ack)
        return msg

    def _take_ack(self, ack: int) -> None:
        """Drop the set-points the device acknowledged; remember the values of the acknowledged one."""
        if seq_after(ack, self._sent_seq) or not seq_after(ack, self._ack):
            return  # not one we sent, or no news
        self._ack = ack
        while self._unacked and not seq_after(self._unacked[0][0], ack):
            seq, _, values = self._unacked.popleft()
            if seq == ack:
                self._acked_values = values

    def device_refused(self, tel: Telemetry) -> bool:
        """The device refused a set-point since the last time this was asked."""
        if tel.refused > self._refused_base:
            self._refused_base = tel.refused
            return True
        return False

    def device_limited(self, tel: Telemetry) -> int:
        """How many set-points the device's servo limited since the last time this was asked."""
        if tel.limited > self._limited_base:
            n = tel.limited - self._limited_base
            self._limited_base = tel.limited
            return n
        return 0

    # ---------------------------------------------------------- watchdogs
    def silence(self, now: float) -> float:
        """Time (s) since the last valid telemetry."""
        return now - self.last_time

    def ack_stall(self, tel: Telemetry, now: float) -> str | None:
        """Why the device has stopped acknowledging (a set-point older than ``ack_timeout``), or None."""
        if self._unacked and now - self._unacked[0][1] > self._options.ack_timeout:
            seq, sent, _ = self._unacked[0]
            return (
                f"device stopped acknowledging: set-point seq {seq} unacknowledged after "
                f"{(now - sent) * 1000:.0f} ms (last ack {tel.ack}; device counts stale {tel.stale}, "
                f"other session {tel.foreign})"
            )
        return None

    def following_error(self, tel: Telemetry) -> str | None:
        """Why the measured positions do not follow the acknowledged set-point, or None."""
        if self._acked_values is None:
            return None
        err = np.abs(tel.positions - self._acked_values)
        i = int(np.argmax(err))
        if err[i] > self._options.following_tolerance:
            u = self._actuators.units[i]
            return (
                f"following error: {self._actuators.names[i]} measured {tel.positions[i]:.4g} {u}, "
                f"commanded {self._acked_values[i]:.4g} {u} (|error| {err[i]:.4g} > following_tolerance "
                f"{self._options.following_tolerance:g})"
            )
        return None

    def underrun(self, now: float) -> tuple[bool, float]:
        """The source has nothing for this tick: (whether this starts an underrun, its length in s)."""
        first = self._underrun_since is None
        if first:
            self._underrun_since = now
        return first, now - self._underrun_since

    def source_ok(self) -> None:
        """The source had a set-point for this tick (or starts afresh): no underrun."""
        self._underrun_since = None

    def start_settling(self, now: float) -> None:
        """The final set-point went out at `now` (s)."""
        self._settle_since = now

    def settle_overdue(self, now: float) -> bool:
        """Settling has taken longer than ``settle_timeout``."""
        return now - (self._settle_since or now) > self._options.settle_timeout

    def arrival_error(self, last_move_seq: int, position: np.ndarray) -> float | None:
        """max |measured - position| (rad or mm) once the device acknowledged the last move frame, else None."""
        tel = self.last
        if tel is not None and not seq_after(last_move_seq, tel.ack):
            return float(np.max(np.abs(tel.positions - position)))
        return None
