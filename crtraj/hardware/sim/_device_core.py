"""The protocol side of the simulated device: frames in, servo commands and telemetry out, no socket.

`DeviceCore` handles one datagram at a time (`handle`), advances its servos (`crtraj.hardware.sim._servo`) to a
time (`advance`) and builds `telemetry`; every time is the device's own clock in s, so tests drive it with a
virtual clock. It checks every frame's CRC, session and sequence number (serial-number arithmetic, a bounded
forward window; see `crtraj.hardware.protocol`), refuses set-points outside the position limits (a second,
independent check), and flags set-points whose step from the previous one needs more than a velocity or
acceleration limit over the host's declared frame period (`STATUS_LIMITED`, counter ``limited``, `violations`;
it still moves, at its limits). Values in rad (servos) or mm (z stage).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import (
    ESTOP,
    HOLD,
    MOVE,
    PING,
    SEQ_WINDOW,
    STATUS_ESTOP,
    STATUS_HOLDING,
    STATUS_LIMITED,
    STATUS_LINK_LOST,
    STATUS_REFUSED,
    Frame,
    FrameError,
    Telemetry,
    seq_distance,
)
from crtraj.hardware.sim._servo import SimServos

# Relative slack of the device's rate checks (round-off in the host's own checks at 1e-9).
_RATE_TOL = 1e-6


@dataclass(frozen=True)
class Applied:
    """A set-point frame the device applied: device time (s), seq, kind, stamp, values."""

    wall: float
    seq: int
    kind: int
    stamp: float
    values: np.ndarray


@dataclass(frozen=True)
class LimitViolation:
    """A set-point whose step needed more than a limit. wall: device time (s); value and limit
    in rad/s, mm/s (velocity) or rad/s^2, mm/s^2 (acceleration)."""

    wall: float
    seq: int
    actuator: str
    quantity: str  # velocity | acceleration
    value: float
    limit: float

    def message(self) -> str:
        return f"seq {self.seq}: {self.actuator} {self.quantity} {self.value:.6g} exceeds limit {self.limit:g}"


class DeviceCore:
    """The device's protocol handling and physics, without a socket; times are device time (s).

    actuators: limits (and the number of actuators); initial: start positions
    (actuator values; default every actuator at its zero offset). tau: motor
    time constant(s) (s, >= 0). physics_dt: longest integration step (s).
    link_timeout: s without a valid set-point before LINK_LOST.
    """

    def __init__(
        self,
        actuators: Actuators,
        *,
        initial: np.ndarray | None = None,
        tau: float | np.ndarray = 0.03,
        physics_dt: float = 0.002,
        link_timeout: float = 0.25,
        history: int = 200_000,
    ) -> None:
        self.actuators = actuators
        n = actuators.n
        taus = np.broadcast_to(np.asarray(tau, dtype=float), (n,)).copy()
        if not np.all(np.isfinite(taus) & (taus >= 0)):
            raise InputError(f"--tau: must be >= 0, got {tau}")
        if not (physics_dt > 0 and link_timeout > 0):
            raise InputError("physics_dt and link_timeout must be > 0")
        x0 = actuators.zero_offset.copy() if initial is None else np.asarray(initial, dtype=float).copy()
        if x0.shape != (n,) or not np.all(np.isfinite(x0)):
            raise InputError(f"initial: expected {n} finite actuator values")
        self._link_timeout = float(link_timeout)
        self.servos = SimServos(actuators.vmax, actuators.amax, x0, taus, physics_dt)
        self._session = 0
        self._period = 0.0
        self._last_seq = 0
        self._has_setpoint = False
        self._prev_cmd: np.ndarray | None = None
        self._prev_v = np.zeros(n)
        self._last_valid = 0.0
        self._status = STATUS_HOLDING
        self._estop = False
        self._tel_seq = 0
        self.counts = {
            "received": 0,
            "applied": 0,
            "crc_errors": 0,
            "missed": 0,
            "stale": 0,
            "refused": 0,
            "foreign": 0,
            "limited": 0,
            "sessions": 0,
        }
        self.applied: deque[Applied] = deque(maxlen=history)
        self.violations: deque[LimitViolation] = deque(maxlen=1000)

    @property
    def time(self) -> float:
        """Device time (s) the physics has reached; it never goes back."""
        return self.servos.time

    @property
    def tau(self) -> np.ndarray:
        """Motor time constants (s), one per actuator."""
        return self.servos.tau

    @property
    def physics_dt(self) -> float:
        """Longest integration step (s)."""
        return self.servos.physics_dt

    # -------------------------------------------------------------- physics
    def advance(self, now: float) -> None:
        """Integrate the servos up to device time `now` (s); earlier times are ignored."""
        self.servos.advance(now)
        if self._has_setpoint and now - self._last_valid > self._link_timeout:
            self._status |= STATUS_LINK_LOST

    # ------------------------------------------------------------- protocol
    def handle(self, data: bytes, now: float) -> bool:
        """Process one datagram received at device time `now` (s).

        True when it came from the current session's host (a PING that opened or
        refreshed the session, or a well-formed set-point frame of the session):
        telemetry then goes to its sender. Never raises for any input.
        """
        self.counts["received"] += 1
        try:
            msg = Frame.decode(data)
        except FrameError:
            self.counts["crc_errors"] += 1
            return False
        if not isinstance(msg, Frame):
            self.counts["crc_errors"] += 1  # telemetry is never addressed to a device
            return False
        now = max(float(now), self.servos.time)  # a clock that steps back must not rewind the servos
        self.advance(now)
        if msg.kind == PING:
            return self._ping(msg, now)
        if msg.session == 0 or msg.session != self._session:
            self.counts["foreign"] += 1  # another (or a stale) session: never acted on
            return False
        if msg.values.size != self.actuators.n:
            self.counts["crc_errors"] += 1  # well-formed but not for this device: rejected likewise
            return False
        gap = seq_distance(msg.seq, self._last_seq)
        if not 0 < gap <= SEQ_WINDOW:
            self.counts["stale"] += 1  # older, a duplicate, or implausibly far ahead
            return True
        self.counts["missed"] += gap - 1
        self._last_seq = msg.seq
        self._last_valid = now
        self._has_setpoint = True
        self._status &= ~STATUS_LINK_LOST
        if self._estop:
            return True  # latched until the device restarts
        if msg.kind == ESTOP:
            self._estop = True
            self.servos.brake(now)
            self._status |= STATUS_ESTOP | STATUS_HOLDING
            self._record(now, msg)
            return True
        viol = self.actuators.position_violation(msg.values)
        if np.any(viol > 1e-9 * np.maximum(np.abs(msg.values), 1.0)):
            self.counts["refused"] += 1
            self._status |= STATUS_REFUSED | STATUS_HOLDING
            return True
        self._check_rates(msg, gap, now)
        self.servos.command(msg.values, now)
        if msg.kind == HOLD:
            self._status |= STATUS_HOLDING
        else:
            self._status &= ~STATUS_HOLDING
        self._record(now, msg)
        return True

    def _ping(self, msg: Frame, now: float) -> bool:
        if msg.session == 0:
            self.counts["crc_errors"] += 1  # session 0 means "none"
            return False
        if msg.session == self._session:
            return True  # a repeated PING of this session: the host may have missed telemetry
        # a new session: sequence tracking restarts at the PING's seq, per-session flags clear
        self.counts["sessions"] += 1
        self._session = msg.session
        self._last_seq = msg.seq
        self._period = float(msg.values[0])
        self._has_setpoint = False
        self._prev_cmd = None
        self._prev_v = np.zeros(self.actuators.n)
        self._last_valid = now
        self._status &= ~(STATUS_LINK_LOST | STATUS_REFUSED | STATUS_LIMITED)
        return True

    def _check_rates(self, msg: Frame, gap: int, now: float) -> None:
        """Flag a step that needs more than a velocity (any set-point) or acceleration (MOVE) limit.

        The step's duration is gap x the host's declared period, as the host's own
        gate computes it; the first set-point of a session is measured from where
        the servos are, at rest. A HOLD commands zero velocity (braking): exempt
        from the acceleration limit.
        """
        acts = self.actuators
        dt = gap * self._period
        ref = self.servos.measured if self._prev_cmd is None else self._prev_cmd
        v = (msg.values - ref) / dt
        a = (v - self._prev_v) / dt
        checks = [("velocity", v, acts.vmax)]
        if msg.kind == MOVE:
            checks.append(("acceleration", a, acts.amax))
        for quantity, val, lim in checks:
            bad = np.flatnonzero(np.abs(val) > lim * (1 + _RATE_TOL))
            if bad.size:
                i = int(bad[0])
                self.violations.append(LimitViolation(now, msg.seq, acts.names[i], quantity, float(val[i]), lim[i]))
                self.counts["limited"] += 1
                self._status |= STATUS_LIMITED
                break
        self._prev_cmd = msg.values.copy()
        self._prev_v = v if msg.kind == MOVE else np.zeros(acts.n)

    def _record(self, now: float, msg: Frame) -> None:
        self.counts["applied"] += 1
        self.applied.append(Applied(now, msg.seq, msg.kind, msg.stamp, msg.values.copy()))

    def telemetry(self, now: float) -> Telemetry | None:
        """The telemetry frame for device time `now` (None before any session)."""
        if self._session == 0:
            return None
        now = max(float(now), self.servos.time)
        self.advance(now)
        self._tel_seq += 1
        c = self.counts
        return Telemetry(
            seq=self._tel_seq,
            stamp=now,
            ack=self._last_seq,
            status=self._status,
            positions=self.servos.measured.copy(),
            crc_errors=c["crc_errors"],
            missed=c["missed"],
            stale=c["stale"],
            refused=c["refused"],
            foreign=c["foreign"],
            limited=c["limited"],
            session=self._session,
        )

    def state(self) -> dict[str, Any]:
        """Positions, reference, velocity, target, status bits, session and counters (a copy)."""
        r, v = self.servos.reference(self.servos.time)
        return {
            "positions": self.servos.measured.copy(),
            "reference": r,
            "velocity": v,
            "target": self.servos.target,
            "status": self._status,
            "session": self._session,
            "last_seq": self._last_seq,
            **self.counts,
        }
