"""A simulated device that speaks the wire protocol over UDP on 127.0.0.1.

Each actuator is a servo controller with a motion generator: on every new
set-point it plans the time-optimal motion from its current reference
position and velocity to the set-point at rest, with the actuator's
velocity and acceleration limits (a trapezoidal or triangular velocity
profile, `ServoProfile`). The measured position follows that reference
through a first-order lag ``tau x' = r - x`` (the motor; ``tau = 0``: an
ideal servo), integrated exactly for a reference that is linear over each
physics step. So the device never moves faster than its limits, whatever
it is told.

`DeviceCore` is the protocol and physics without a socket: `handle` one
datagram, `advance` the physics to a time, build `telemetry`; every time is
the device's own clock in s, so tests drive it with a virtual clock. It
checks every frame's CRC, session and sequence number (serial-number
arithmetic, a bounded forward window; see `crtraj.hardware.protocol`), refuses
set-points outside the position limits (a second, independent check), and
flags set-points whose step from the previous one needs more than a
velocity or acceleration limit over the host's declared frame period
(`STATUS_LIMITED`, counter ``limited``, `violations`; it still moves, at
its limits). `SimDevice` puts it behind a UDP socket, sends telemetry at a
fixed rate to the host of the current session, and injects faults.

Faults for testing the streamer: drop (each datagram, both directions, with
a probability), corrupt (flip bits of incoming datagrams and outgoing
telemetry), delay (hold incoming datagrams for a time) and disconnect (go
silent and deaf for a time window).
"""

from __future__ import annotations

import heapq
import math
import select
import socket
import threading
import time
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

# Relative slack of the device's rate checks (round-off in the host's own checks at 1e-9).
_RATE_TOL = 1e-6


@dataclass(frozen=True)
class Faults:
    """Fault injection. drop, corrupt: probabilities per datagram in [0, 1). delay: s added to
    every incoming datagram. disconnect_after / disconnect_for: s after start, and how long the
    device is silent and deaf (0: never)."""

    drop: float = 0.0
    corrupt: float = 0.0
    delay: float = 0.0
    disconnect_after: float = 0.0
    disconnect_for: float = 0.0

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt"):
            v = getattr(self, name)
            if not (0.0 <= v < 1.0):
                raise InputError(f"--{name}: must be in [0, 1), got {v}")
        for name in ("delay", "disconnect_after", "disconnect_for"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise InputError(f"--{name.replace('_', '-')}: must be >= 0, got {v}")


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


class ServoProfile:
    """Time-optimal motion of independent axes to a target at rest, |v| <= vmax, |a| <= amax.

    From position p0 and velocity v0 (clipped to the velocity limit) at time t0,
    each axis accelerates at amax toward the target (direction chosen so that it
    can still stop there), cruises at vmax if it reaches it, and brakes at amax
    to arrive at rest: the textbook trapezoidal (or triangular) profile.
    Positions in rad or mm, times in s.
    """

    def __init__(self, vmax: np.ndarray, amax: np.ndarray, position: np.ndarray) -> None:
        self.vmax = np.asarray(vmax, dtype=float)
        self.amax = np.asarray(amax, dtype=float)
        self.plan(position, np.zeros_like(self.vmax), position, 0.0)

    @property
    def target(self) -> np.ndarray:
        return self._target.copy()

    @property
    def end_time(self) -> float:
        """Time (s) when every axis has arrived."""
        return self._t0 + float(np.max(self._t1 + self._t2 + self._t3, initial=0.0))

    def plan(self, p0: np.ndarray, v0: np.ndarray, target: np.ndarray, t0: float) -> None:
        """Start a new motion from (p0, v0) at time t0 to `target`."""
        a, vm = self.amax, self.vmax
        p0 = np.asarray(p0, dtype=float).copy()
        v0 = np.clip(np.asarray(v0, dtype=float), -vm, vm)
        d = np.asarray(target, dtype=float) - p0
        # direction of the first acceleration: toward the target unless the axis must brake first
        s = np.sign(d - v0 * np.abs(v0) / (2 * a))
        s = np.where(s == 0, np.sign(v0), s)
        w = s * v0  # velocity along s
        dist = s * d  # distance along s
        vp = np.minimum(vm, np.sqrt(np.maximum(a * dist + 0.5 * w * w, 0.0)))
        t1 = np.maximum(vp - w, 0.0) / a
        d1 = (vp * vp - w * w) / (2 * a)
        d3 = vp * vp / (2 * a)
        d2 = np.maximum(dist - d1 - d3, 0.0)
        t2 = np.divide(d2, vp, out=np.zeros_like(d2), where=vp > 0)
        self._t0, self._p0, self._target = float(t0), p0, np.asarray(target, dtype=float).copy()
        self._s, self._w, self._vp = s, w, vp
        self._t1, self._t2, self._t3, self._d1, self._d2 = t1, t2, vp / a, d1, d2

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) at time t >= t0 (closed form)."""
        tau = max(float(t) - self._t0, 0.0)
        a, s, w, vp = self.amax, self._s, self._w, self._vp
        t1, t12 = self._t1, self._t1 + self._t2
        sig = tau - t12
        along = np.where(
            tau < t1,
            w * tau + 0.5 * a * tau * tau,
            np.where(tau < t12, self._d1 + vp * (tau - t1), self._d1 + self._d2 + vp * sig - 0.5 * a * sig * sig),
        )
        vel = np.where(tau < t1, w + a * tau, np.where(tau < t12, vp, vp - a * sig))
        done = tau >= t12 + self._t3
        p = np.where(done, self._target, self._p0 + s * along)
        v = np.where(done, 0.0, s * vel)
        return p, v


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
        self.tau = taus
        self.physics_dt = float(physics_dt)
        self._link_timeout = float(link_timeout)
        self._servo = ServoProfile(actuators.vmax, actuators.amax, x0)
        self._x = x0  # measured (motor) positions
        self._r = x0.copy()  # servo reference at _t
        self._t = 0.0
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
        return self._t

    # -------------------------------------------------------------- physics
    def advance(self, now: float) -> None:
        """Integrate the servos up to device time `now` (s); earlier times are ignored."""
        h = self.physics_dt
        tau = self.tau
        while self._t < now:
            t1 = min(self._t + h, now)
            dt = t1 - self._t
            r1, _ = self._servo.sample(t1)
            # exact solution of tau x' = r - x for r linear from _r to r1 over dt (tau = 0: x = r)
            e = np.exp(-np.divide(dt, tau, out=np.full_like(tau, np.inf), where=tau > 0))
            c = 1.0 - np.divide(tau, dt, out=np.zeros_like(tau), where=tau > 0) * (1.0 - e)
            self._x = e * self._x + (1.0 - e) * self._r + (r1 - self._r) * c
            self._r, self._t = r1, t1
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
        now = max(float(now), self._t)  # a clock that steps back must not rewind the servos
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
            # brake at the acceleration limit: the target is where each axis can stop
            r, v = self._servo.sample(now)
            self._servo.plan(r, v, r + v * np.abs(v) / (2 * self.actuators.amax), now)
            self._status |= STATUS_ESTOP | STATUS_HOLDING
            self._record(now, msg)
            return True
        viol = self.actuators.position_violation(msg.values)
        if np.any(viol > 1e-9 * np.maximum(np.abs(msg.values), 1.0)):
            self.counts["refused"] += 1
            self._status |= STATUS_REFUSED | STATUS_HOLDING
            return True
        self._check_rates(msg, gap, now)
        r, v = self._servo.sample(now)
        self._servo.plan(r, v, msg.values, now)
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
        ref = self._x if self._prev_cmd is None else self._prev_cmd
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
        now = max(float(now), self._t)
        self.advance(now)
        self._tel_seq += 1
        c = self.counts
        return Telemetry(
            seq=self._tel_seq,
            stamp=now,
            ack=self._last_seq,
            status=self._status,
            positions=self._x.copy(),
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
        r, v = self._servo.sample(self._t)
        return {
            "positions": self._x.copy(),
            "reference": r,
            "velocity": v,
            "target": self._servo.target,
            "status": self._status,
            "session": self._session,
            "last_seq": self._last_seq,
            **self.counts,
        }


class SimDevice:
    """Simulated servo controller behind a UDP socket bound to 127.0.0.1.

    actuators, initial, tau, physics_dt, link_timeout: see `DeviceCore`.
    telemetry_rate: Hz. seed: fault RNG.
    """

    def __init__(
        self,
        actuators: Actuators,
        port: int = 0,
        *,
        host: str = "127.0.0.1",
        initial: np.ndarray | None = None,
        tau: float | np.ndarray = 0.03,
        physics_dt: float = 0.002,
        telemetry_rate: float = 100.0,
        link_timeout: float = 0.25,
        faults: Faults | None = None,
        seed: int = 0,
        history: int = 200_000,
    ) -> None:
        if host not in ("127.0.0.1", "localhost"):
            raise InputError(f"--udp: the simulated device binds 127.0.0.1 only, got {host!r}")
        if not (math.isfinite(telemetry_rate) and telemetry_rate > 0):
            raise InputError(f"--telemetry-rate: must be > 0, got {telemetry_rate}")
        self.core = DeviceCore(
            actuators, initial=initial, tau=tau, physics_dt=physics_dt, link_timeout=link_timeout, history=history
        )
        self.actuators = actuators
        self.faults = faults or Faults()
        self._rng = np.random.default_rng(seed)
        self._tel_dt = 1.0 / telemetry_rate
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(("127.0.0.1", port))
        except OSError as exc:
            self._sock.close()
            raise InputError(f"--udp: cannot bind 127.0.0.1:{port} ({exc.strerror})") from None
        self._sock.settimeout(0.0)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._peer: tuple[str, int] | None = None
        self._counts = {
            "dropped_in": 0,
            "dropped_out": 0,
            "corrupted_in": 0,
            "corrupted_out": 0,
            "telemetry": 0,
            "internal_errors": 0,
        }
        self._pending: list[tuple[float, int, bytes, tuple[str, int]]] = []
        self._pending_n = 0
        self._t0 = time.monotonic()

    @property
    def clock_origin(self) -> float:
        """`time.monotonic()` (s) at device time 0: device time t is monotonic time clock_origin + t."""
        return self._t0

    @property
    def applied(self) -> deque[Applied]:
        """Set-point frames applied (device time since start, s)."""
        return self.core.applied

    @property
    def violations(self) -> deque[LimitViolation]:
        return self.core.violations

    # -------------------------------------------------------------- control
    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    @property
    def url(self) -> str:
        h, p = self.address
        return f"udp://{h}:{p}"

    def start(self) -> SimDevice:
        """Run the device loop in a background thread."""
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._loop, name="crtraj-sim-device", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._sock.close()

    def __enter__(self) -> SimDevice:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def serve(self, duration: float | None = None) -> None:
        """Run in the calling thread (for the CLI) until `duration` s or KeyboardInterrupt."""
        self._t0 = time.monotonic()
        self._loop(duration)

    # ------------------------------------------------------------- snapshot
    def state(self) -> dict[str, Any]:
        """Positions, target, status bits and counters (a copy)."""
        with self._lock:
            return {**self.core.state(), **self._counts}

    # ----------------------------------------------------------------- loop
    def _now(self) -> float:
        return time.monotonic() - self._t0

    def _loop(self, duration: float | None = None) -> None:
        t_tel = self._now()
        while not self._stop.is_set():
            now = self._now()
            if duration is not None and now >= duration:
                return
            deaf = self._disconnected(now)
            self._receive(now, deaf)
            self._release_delayed(now)
            with self._lock:
                self.core.advance(now)
            if now >= t_tel:
                if not deaf:
                    self._send_telemetry(now)
                t_tel += self._tel_dt
                if t_tel < now:
                    t_tel = now + self._tel_dt
            wait = min(t_tel, now + self.core.physics_dt) - self._now()
            if self._pending:
                wait = min(wait, self._pending[0][0] - self._now())
            self._wait_readable(max(wait, 0.0))

    def _wait_readable(self, timeout: float) -> None:
        try:
            select.select([self._sock], [], [], timeout)
        except (OSError, ValueError):
            self._stop.wait(timeout)

    def _disconnected(self, now: float) -> bool:
        f = self.faults
        if f.disconnect_for <= 0:
            return False
        return f.disconnect_after <= now < f.disconnect_after + f.disconnect_for

    def _receive(self, now: float, deaf: bool) -> None:
        while True:
            try:
                data, addr = self._sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                if self._stop.is_set():
                    return
                continue  # e.g. ICMP from a host that went away: keep serving
            if not deaf:
                self.ingest(data, addr, now)

    def ingest(self, data: bytes, addr: tuple[str, int], now: float) -> None:
        """One received datagram at device time `now` (s): faults, then `DeviceCore.handle`."""
        f = self.faults
        if f.drop and self._rng.random() < f.drop:
            self._counts["dropped_in"] += 1
            return
        if f.corrupt and self._rng.random() < f.corrupt:
            data = self._flip_bits(data)
            self._counts["corrupted_in"] += 1
        if f.delay > 0:
            self._pending_n += 1
            heapq.heappush(self._pending, (now + f.delay, self._pending_n, data, addr))
            return
        self._handle(data, addr, now)

    def _release_delayed(self, now: float) -> None:
        while self._pending and self._pending[0][0] <= now:
            _, _, data, addr = heapq.heappop(self._pending)
            self._handle(data, addr, now)

    def _flip_bits(self, data: bytes) -> bytes:
        if not data:
            return data  # nothing to flip (an empty datagram stays empty and is rejected)
        b = bytearray(data)
        for _ in range(int(self._rng.integers(1, 4))):
            i = int(self._rng.integers(0, len(b) * 8))
            b[i // 8] ^= 1 << (i % 8)
        return bytes(b)

    def _handle(self, data: bytes, addr: tuple[str, int], now: float) -> None:
        with self._lock:
            try:
                if self.core.handle(data, now):
                    self._peer = addr
            except Exception:  # last resort: no datagram may stop the device (fuzz tests assert it never fires)
                self._counts["internal_errors"] += 1

    def _send_telemetry(self, now: float) -> None:
        with self._lock:
            peer = self._peer
            tel = None if peer is None else self.core.telemetry(now)
        if tel is None or peer is None:
            return
        data = tel.encode()
        f = self.faults
        if f.drop and self._rng.random() < f.drop:
            self._counts["dropped_out"] += 1
            return
        if f.corrupt and self._rng.random() < f.corrupt:
            data = self._flip_bits(data)
            self._counts["corrupted_out"] += 1
        try:
            self._sock.sendto(data, peer)
            self._counts["telemetry"] += 1
        except OSError:
            pass  # the host went away; it is the host's job to notice silence
