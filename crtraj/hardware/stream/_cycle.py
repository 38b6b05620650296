"""One period of a stream: read the device's telemetry, run the watchdogs, move the state machine, send one frame.

The decisions per state: waiting holds until enough is buffered; streaming sends the buffer's next set-point (or
holds through an underrun until the watchdog latches ``stalled``); settling holds at the final set-point until the
device acknowledges it and arrives within ``settle_tolerance`` (``not-settled`` after ``settle_timeout``); held
repeats hold frames; an e-stop repeats e-stop frames. Times in s on the stream's clock.
"""

from __future__ import annotations

import numpy as np

from crtraj.control.braking import BrakeCounts, StopVerifier
from crtraj.hardware.limits import LimitsGate
from crtraj.hardware.protocol import ESTOP, HOLD, MOVE, STATUS_ESTOP, Telemetry
from crtraj.hardware.stream._braking import Braking
from crtraj.hardware.stream._options import StreamOptions
from crtraj.hardware.stream._sender import FrameSender, StreamParts
from crtraj.hardware.stream._state import (
    CHECKED,
    CLOSED,
    DONE,
    ERROR,
    ESTOPPED,
    HELD,
    IDLE,
    LIVE,
    SETTLING,
    STREAMING,
    WAITING,
)
from crtraj.hardware.transport import Transport, TransportError


class StreamCycle:
    """The per-period work of one stream.

    options: the `StreamOptions`; transport: the link (its telemetry is read here); gate: the limits gate
    (`position` is the last commanded values); parts: the stream's state machine, buffer, monitor and log;
    sender: where frames leave. braking: plans the stop of a hold or e-stop (None: latch at once).
    """

    def __init__(
        self,
        options: StreamOptions,
        transport: Transport,
        gate: LimitsGate,
        parts: StreamParts,
        sender: FrameSender,
        braking: Braking | None = None,
    ) -> None:
        self._options = options
        self._transport = transport
        self._gate = gate
        self._machine, self._buffer, self._monitor = parts.machine, parts.buffer, parts.monitor
        self._sender = sender
        self.final_error: float | None = None  # max |measured - final| on arrival (rad or mm)
        self.braking = braking
        self._brake: list[tuple[float, np.ndarray]] = []  # the stop's frames still to send
        self._braked_for: float | None = None  # the latch time whose stop was planned

    def check_stops_with(self, verifier: StopVerifier) -> None:
        """Verify every stop's frames with `verifier` (an admitted motion's `FrameVerifier`) from now on, as its
        frames are; the stop counts start again."""
        if self.braking is not None:
            self.braking = self.braking.checked_by(verifier)

    def count_latched(self) -> None:
        """A stop cut short by the latch (the stream closed before it ended)."""
        if self.braking is not None:
            self.braking.count_latched()

    @property
    def brake_counts(self) -> BrakeCounts:
        """How the stream's stops went (planned, latched, frames sent, unverified)."""
        return self.braking.counts if self.braking is not None else BrakeCounts()

    @property
    def is_braking(self) -> bool:
        """A planned stop still has frames to send."""
        return bool(self._brake)

    def clear_brake(self) -> None:
        """Forget a stop in progress (`Streamer.resume`, or a latch the device made itself)."""
        self._brake = []
        self._braked_for = self._machine.latched_at

    def brake_step(self, now: float) -> bool:
        """Send the next frame of the stop of the current hold or e-stop (planning it first); False when
        there is none (at rest, no braking, or the stop failed its check: the caller latches)."""
        if self.braking is None:
            return False
        m = self._machine
        if self._braked_for != m.latched_at:
            self._braked_for = m.latched_at
            self._plan_brake(now)
        if not self._brake:
            return False
        stamp, values = self._brake.pop(0)
        if not self._sender.emit(MOVE, values, stamp):  # refused: the sender already held at the last frame
            self._brake = []
            self.braking.count_latched()
            return True
        self.braking.count_frame()
        self._buffer.sent_stop_frame(stamp)
        if not self._brake:  # at rest: the hold or e-stop frames now repeat for a watchdog period from here
            m.stopped(now)
            self._braked_for = now
        return True

    def _plan_brake(self, now: float) -> None:
        gate, braking = self._gate, self.braking
        if gate.position is None or braking is None:
            return
        plan = braking.plan(gate.position, gate.velocity, self._buffer.sent_stamp)
        if not len(plan.values):
            return
        if not plan.ok:
            braking.count_latched()
            self._machine.event("brake-refused", f"the stop failed its check ({plan.why}): latched", now)
            return
        braking.count_braked()
        self._machine.event("brake", f"stopping within the acceleration limits in {len(plan.values)} frames", now)
        self._brake = list(zip(plan.stamps.tolist(), plan.values, strict=True))

    def tick(self, now: float) -> None:
        """One period at clock time `now` (s). Caller holds the stream's lock."""
        state = self._machine
        if state.state in (DONE, ERROR, CLOSED, IDLE):
            return
        try:
            self.poll_telemetry(now)
            if state.state == ESTOPPED:
                if not self.brake_step(now):
                    self._sender.hold(ESTOP)
                return
            if state.state not in (HELD, DONE) and self._transport.has_telemetry:
                silent = self._monitor.silence(now)
                if silent > self._options.watchdog:
                    state.latch(f"telemetry lost: nothing valid for {silent * 1000:.0f} ms", now, "telemetry-lost")
            if state.state == HELD:
                if not self.brake_step(now):
                    self._sender.hold(HOLD)
            elif state.state == WAITING:
                self._tick_waiting(now)
            elif state.state == STREAMING:
                self._tick_streaming(now)
            elif state.state == SETTLING:
                self._tick_settling(now)
        except TransportError as exc:
            if self.braking is not None and np.any(self._gate.velocity != 0.0):
                self.braking.count_latched()  # moving when the link failed: the device's latch is all there is
            state.transport_failed(exc)

    def _tick_waiting(self, now: float) -> None:
        if not self._buffer.ready(self._options.prebuffer):
            self._sender.hold(HOLD)
            return
        origin = self._buffer.begin()
        self._monitor.source_ok()
        self._machine.stream(origin)
        self._tick_streaming(now)

    def _tick_streaming(self, now: float) -> None:
        due = self._buffer.due()
        if due.kind == "settle":
            self._machine.settle(due.stamp)
            self._monitor.start_settling(now)
            self._tick_settling(now)
            return
        if due.kind == "underrun":
            self._underrun(now, due.stamp)
            return
        self._monitor.source_ok()
        if self._sender.emit(MOVE, due.values, due.stamp):
            self._buffer.advance(due)

    def _underrun(self, now: float, stamp: float) -> None:
        """No set-point for `stamp` (s) yet. At rest the stream holds and waits up to the watchdog for the source.
        Moving, a hold frame would be a stop in one period (outside the acceleration limits, and the gate, now at
        rest, would refuse the late set-points' velocity): the stream latches the recoverable ``source stalled``
        hold at once and brakes within the limits; the source resumes from rest where the stop ends."""
        if np.any(self._gate.velocity != 0.0):
            self._machine.latch(f"source stalled: no set-point for t={stamp:g} s while moving: braking", now, "stalled")
            if not self.brake_step(now):
                self._sender.hold(HOLD)
            return
        first, waited = self._monitor.underrun(now)
        if first:
            self._machine.event("underrun", f"no set-point for t={stamp:g} s yet: holding", now)
        if waited > self._options.watchdog:
            self._machine.latch(
                f"source stalled: no set-point for t={stamp:g} s within {self._options.watchdog * 1000:.0f} ms",
                now,
                "stalled",
            )
        self._sender.hold(HOLD)

    def _tick_settling(self, now: float) -> None:
        self._sender.hold(HOLD)
        if not self._transport.has_telemetry:
            self._arrived(None)
            return
        err = self._monitor.arrival_error(self._sender.last_move_seq, self._gate.position)
        if err is not None and err <= self._options.settle_tolerance:
            self._arrived(err)
            return
        if self._monitor.settle_overdue(now):
            tel = self._monitor.last
            err = None if tel is None else float(np.max(np.abs(tel.positions - self._gate.position)))
            reason = (
                f"device did not reach the final set-point within {self._options.settle_timeout:g} s "
                f"(error {err if err is None else f'{err:.4g}'})"
            )
            self._machine.fail(reason, "not-settled", reason, status="not-settled")

    def _arrived(self, err: float | None) -> None:
        self.final_error = err
        self._machine.done(err)

    # ------------------------------------------------------------- telemetry
    def poll_telemetry(self, now: float) -> None:
        """Read every datagram the device sent since the last poll, at clock time `now` (s), and act on it."""
        if not self._transport.has_telemetry:
            return
        newest: Telemetry | None = None
        for data in self._transport.receive():
            tel = self._monitor.accept(data, now, now - self._machine.t_start)
            if tel is not None:
                self._on_telemetry(tel, now)
                newest = tel
        trip = self._transport.trip()
        if trip is not None and self._machine.state in LIVE and self._machine.state != HELD:
            self._machine.latch(trip[1], now, trip[0])  # the verified stop, then a hold; the report names it
        # after the whole batch: telemetry that queued up while this thread was starved must not
        # make frames it sent just before the stall look unacknowledged
        if newest is not None and self._machine.state in CHECKED:
            why = self._monitor.ack_stall(newest, now)
            if why is not None:
                self._machine.latch(why, now, "ack-stalled")

    def _on_telemetry(self, tel: Telemetry, now: float) -> None:
        """Act on one valid telemetry frame: the device's e-stop, refusals, limited steps, following error."""
        machine = self._machine
        if machine.state in LIVE:
            if tel.status & STATUS_ESTOP:
                machine.estop("device reports an e-stop", now)
                self.clear_brake()  # the device stopped itself: nothing to plan
            elif self._monitor.device_refused(tel):
                machine.latch(
                    "device refused a set-point (its limits are stricter than the robot file's)", now, "refused"
                )
        limited = self._monitor.device_limited(tel)
        if limited:
            # the device's servo limited a step (it still follows, slower): the following-error
            # check decides whether that matters
            machine.event("device-limited", f"device flagged {limited} set-point(s)")
        if machine.state in CHECKED:
            why = self._monitor.following_error(tel)
            if why is not None:
                machine.latch(why, machine.now(), "following-error")
