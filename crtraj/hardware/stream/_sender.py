"""The only way a stream's frames leave: the limits gate, sequence numbers, the transport and the run log.

Every set-point, hold and e-stop frame passes `LimitsGate` before it reaches the transport. A refused set-point
is reported, never clamped: the stream latches a hold (status ``refused``) and holds where it is. Values in
actuator units (rad for servos, mm for the z stage), stamps in s of trajectory time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.hardware.limits import LimitPeaks, LimitsGate
from crtraj.hardware.protocol import ESTOP, HOLD, KIND_NAMES, MOVE, Frame, seq_next
from crtraj.hardware.stream._buffer import SetpointBuffer
from crtraj.hardware.stream._log import RunLog
from crtraj.hardware.stream._monitor import StreamMonitor
from crtraj.hardware.stream._state import StreamStateMachine
from crtraj.hardware.transport import Transport


@dataclass(frozen=True)
class StreamParts:
    """The parts of one stream that its sender and its cycle share."""

    machine: StreamStateMachine
    buffer: SetpointBuffer
    monitor: StreamMonitor
    log: RunLog


class FrameSender:
    """Sends one stream's frames through the limits gate and records them.

    transport: the link; gate: the actuator limits (`position` is the last commanded values); session and
    first_seq: this run's session number and the PING's sequence number; parts: the stream's state machine,
    buffer, monitor and log (a refusal latches the machine, holds repeat the buffer's last stamp, sent
    frames await the monitor's acknowledgement check).
    """

    def __init__(
        self,
        transport: Transport,
        gate: LimitsGate,
        session: int,
        first_seq: int,
        parts: StreamParts,
    ) -> None:
        self._transport = transport
        self._gate = gate
        self._session = session
        self.first_seq = first_seq
        self._machine, self._buffer, self._monitor, self._log = parts.machine, parts.buffer, parts.monitor, parts.log
        self._seq = first_seq  # the newest sequence number sent
        self.last_move_seq = first_seq  # the sequence number of the newest move frame
        self.counts = {"frames": 0, MOVE: 0, HOLD: 0, ESTOP: 0}  # frames sent, in all and by kind
        # the largest speed and acceleration of every frame that left, holds included: a hold repeats the last
        # values, so one that latches while moving counts as the stop in one period it commands
        self.peaks = LimitPeaks(gate.actuators, gate.dt)

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of every frame sent (holds too), as fractions of the limits."""
        return self.peaks.as_dict()

    def ping(self, dt: float) -> None:
        """Send the PING that opens the session (dt: the stream period, s). A PING carries no values and
        commands nothing, so it bypasses the limits gate."""
        self._transport.send(Frame.ping(self._session, self.first_seq, dt).encode())
        self._log.write({"type": "tx", "wall": self._machine.wall(), "seq": self.first_seq, "kind": "ping"})

    def hold(self, kind: int = HOLD) -> None:
        """Send a hold (or, kind ESTOP, an e-stop) at the last commanded values, if there are any."""
        p = self._gate.position
        if p is not None:
            self.emit(kind, p, self._buffer.sent_stamp)

    def emit(self, kind: int, values: np.ndarray, stamp: float) -> bool:
        """The only way a frame leaves: gate check, encode, send, record. False if refused."""
        values = np.asarray(values, dtype=float)
        v = self._gate.check(kind, values, stamp)
        if v is not None:
            if kind == MOVE:
                self._machine.latch(f"set-point refused: {v.message()}", self._machine.now(), "refused")
                self.hold(HOLD)
            else:  # cannot happen: hold values are the gate's own position
                reason = f"internal: {KIND_NAMES[kind]} frame refused: {v.message()}"
                self._machine.fail(reason, "error", reason)
            return False
        frame = Frame(kind, seq_next(self._seq), stamp, values, self._session)
        self._transport.send(frame.encode())
        self._seq = frame.seq
        if kind == MOVE:
            self.last_move_seq = self._seq
        if self._transport.has_telemetry:
            self._monitor.sent(frame.seq, self._machine.now(), values)
        self.peaks.add(values[None], self._gate.position, self._gate.velocity)
        self._gate.commit(kind, values)
        self.counts["frames"] += 1
        self.counts[kind] += 1
        self._log.write(
            {
                "type": "tx",
                "wall": self._machine.wall(),
                "seq": frame.seq,
                "kind": KIND_NAMES[kind],
                "stamp": stamp,
                "values": values,
            }
        )
        return True

    def tallies(self) -> dict[str, Any]:
        """What was sent, for the stream's report: frames in all and per kind, and the largest actuator speed and
        acceleration of every frame as fractions of the limits (None before any frame)."""
        c = self.counts
        peaks = {k: (v if math.isfinite(v) else None) for k, v in self.limit_fractions().items()}
        return {"frames": c["frames"], "moves": c[MOVE], "holds": c[HOLD], "estops": c[ESTOP], **peaks}
