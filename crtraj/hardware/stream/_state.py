"""The stream's state machine: its states, the transitions between them and the events they record.

States: idle -> waiting (connected, buffering) -> streaming -> settling -> done. ``held`` is latched (hold frames
until `resume` or close); done, estop, error and closed are terminal. Every transition records an event (time in
s since the stream started, name, message) in the report and in the run log.
"""

from __future__ import annotations

import logging

from crtraj.core.clock import Clock
from crtraj.hardware.stream._log import RunLog
from crtraj.hardware.transport import LinkLostError

IDLE, WAITING, STREAMING, SETTLING, HELD, DONE, ESTOPPED, ERROR, CLOSED = (
    "idle",
    "waiting",
    "streaming",
    "settling",
    "held",
    "done",
    "estop",
    "error",
    "closed",
)
TERMINAL = (DONE, ESTOPPED, ERROR, CLOSED)
CHECKED = (WAITING, STREAMING, SETTLING)  # states in which the device must follow
LIVE = (WAITING, STREAMING, SETTLING, HELD)  # states in which frames go out and telemetry matters
_MAX_EVENTS = 1000  # events kept for the report (the run log keeps them all)

logger = logging.getLogger(__name__)


class StreamError(RuntimeError):
    """The stream cannot go on (no device, terminal state, held); the message says why."""


class StreamStateMachine:
    """The stream's state, why it is held or stopped, and its events.

    clock: the stream's clock (events are timed on it); log: the run log the events go to.
    """

    def __init__(self, clock: Clock, log: RunLog) -> None:
        self.clock = clock
        self._log = log
        self.state = IDLE
        self.reason = ""  # why held or stopped ('' while running normally)
        self.status_override: str | None = None  # the report's status when it is not the state's name
        self.latched_at: float | None = None  # s (clock time) of the latched hold or e-stop
        self.t_start = 0.0  # s (clock time) the stream started; event times count from it
        self.events: list[tuple[float, str, str]] = []

    def use_clock(self, clock: Clock) -> None:
        """Run on `clock` (a dry run's virtual time); only before the stream starts."""
        if self.state != IDLE:
            raise StreamError(f"use_clock: the stream is already {self.state}")
        self.clock = clock

    def mark_start(self) -> None:
        """The stream starts now: event times count from the clock's reading."""
        self.t_start = self.clock.now()

    def now(self) -> float:
        """The stream clock's reading (s)."""
        return self.clock.now()

    def wall(self, now: float | None = None) -> float:
        """Time since the start (s), of `now` or of the clock's reading."""
        return (self.clock.now() if now is None else now) - self.t_start

    def event(self, name: str, message: str, now: float | None = None) -> None:
        """Record an event. now: the clock reading the decision behind it used."""
        # `now`: the clock reading the decision behind the event used, so that the logged times are the ones the
        # rules compared (a fresh reading here would come microseconds later, and differ between two events)
        wall = self.wall(now)
        logger.debug("stream event at %.4f s: %s %s", wall, name, message)
        if len(self.events) < _MAX_EVENTS:
            self.events.append((wall, name, message))
        self._log.write({"type": "event", "wall": wall, "event": name, "message": message})

    # ----------------------------------------------------------- transitions
    def begin(self, message: str) -> None:
        """Connected: buffer set-points, holding still."""
        self.state = WAITING
        self.event("start", message)

    def stream(self, origin: float) -> None:
        """Enough is buffered: move from trajectory time `origin` (s)."""
        self.state = STREAMING
        self.event("streaming", f"from t={origin:g} s")

    def settle(self, last: float) -> None:
        """The final set-point (at trajectory time `last`, s) was sent: wait for the device to arrive."""
        self.state = SETTLING
        self.event("settling", f"final set-point at t={last:g} s")

    def done(self, err: float | None) -> None:
        """Arrived (final error `err`, rad or mm; None: no telemetry to tell)."""
        self.state = DONE
        self.event("done", "" if err is None else f"final error {err:.3g}")

    def latch(self, reason: str, now: float, status: str = "held") -> None:
        """Latch a hold (no-op when already held or terminal); `status`: the report's status if it stays."""
        if self.state in (HELD, *TERMINAL):
            return
        self.state = HELD
        self.reason = reason
        self.latched_at = now
        self.status_override = None if status == "held" else status
        self.event(status, reason, now)

    def stopped(self, now: float) -> None:
        """A planned stop of the latched hold or e-stop reached rest at clock time `now` (s): its hold or e-stop
        frames repeat for a watchdog period from here."""
        self.latched_at = now

    def resume(self) -> None:
        """Leave a latched hold for waiting."""
        if self.state != HELD:
            raise StreamError(f"resume: stream is {self.state}, not held")
        self.latched_at = None
        self.status_override = None
        self.reason = ""
        self.state = WAITING
        self.event("resume", "")

    def estop(self, reason: str, now: float) -> None:
        """Emergency stop at clock time `now` (s); terminal, e-stop frames repeat for one watchdog period."""
        self.state = ESTOPPED
        self.reason = reason
        self.latched_at = now
        self.event("estop", reason)

    def fail(self, reason: str, event: str, message: str, status: str | None = None) -> None:
        """Stop with an error: `reason` for the report, an event `event` with `message`."""
        self.state = ERROR
        if status is not None:
            self.status_override = status
        self.reason = reason
        self.event(event, message)

    def transport_failed(self, exc: Exception) -> None:
        """Stop on a transport error; a lost link (the adapter gone, not a servo) reports status link_lost."""
        lost = "link_lost" if isinstance(exc, LinkLostError) else None
        self.fail(f"transport error: {exc}", "transport-error", str(exc), status=lost)

    def close(self) -> None:
        """The stream closed: a state that is not an outcome becomes closed."""
        if self.state not in (DONE, ESTOPPED, ERROR):
            self.state = CLOSED

    # ------------------------------------------------------------- queries
    def loop_ends(self, now: float, watchdog: float, stop_when_latched: bool) -> bool:
        """The fixed-rate loop ends at clock time `now` (s): a stop or error at once, an e-stop (and, with
        `stop_when_latched`, a latched hold) once its frames repeated for one `watchdog` period (s)."""
        # hold / e-stop frames repeat for one watchdog period so a lossy link delivers them
        repeated = self.latched_at is not None and now - self.latched_at >= watchdog
        if self.state == ESTOPPED:
            return repeated
        if self.state in TERMINAL:
            return True
        return stop_when_latched and self.state == HELD and repeated

    def check_accepting(self, finished: bool) -> None:
        """`StreamError` unless a source may queue set-points now (`finished`: the source said it was done)."""
        if self.state == IDLE:
            raise StreamError("streamer not started: call start() first")
        if finished:
            raise StreamError("finish() was called: no more set-points")
        if self.state == HELD:
            raise StreamError(f"stream is held ({self.reason}); call resume() to continue from `position`")
        if self.state in TERMINAL:
            raise StreamError(f"stream is {self.state}: {self.reason}")

    def final_status(self, status: str | None) -> str:
        """The report's status: `status` if given, else the override, else the state (closed while running)."""
        running = {WAITING: CLOSED, STREAMING: CLOSED, SETTLING: CLOSED, IDLE: CLOSED}
        return status or self.status_override or running.get(self.state, self.state)
