"""A simulated device that speaks the wire protocol over UDP on 127.0.0.1.

Each actuator is a servo with a first-order lag ``tau x' = u - x`` (python-
control state space, discretised exactly with zero-order hold at the physics
step and advanced by however many steps elapsed). The device checks every
frame's CRC and sequence number, applies only intact frames newer than the
last applied one, enforces the actuators' position limits itself (a second,
independent check), and sends telemetry at a fixed rate to the last host
that sent a valid frame.

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

import control as ct
import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import (
    ESTOP,
    HOLD,
    MOVE,
    PING,
    STATUS_ESTOP,
    STATUS_HOLDING,
    STATUS_LINK_LOST,
    STATUS_REFUSED,
    Frame,
    FrameError,
    Telemetry,
)


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
    """A set-point frame the device applied: wall time since start (s), seq, kind, stamp, values."""

    wall: float
    seq: int
    kind: int
    stamp: float
    values: np.ndarray


class SimDevice:
    """Simulated servo controller behind a UDP socket bound to 127.0.0.1.

    actuators: limits (and the number of actuators); initial: start positions
    (actuator values; default the straight pose, every actuator at its zero
    offset). tau: servo time constant(s) (s). physics_dt: simulation step (s).
    telemetry_rate: Hz. link_timeout: s without a valid frame before the
    device flags LINK_LOST (it keeps holding its last target). seed: fault RNG.
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
        self.actuators = actuators
        n = actuators.n
        taus = np.broadcast_to(np.asarray(tau, dtype=float), (n,)).copy()
        if not np.all(np.isfinite(taus) & (taus > 0)):
            raise InputError(f"--tau: must be > 0, got {tau}")
        if not (physics_dt > 0 and telemetry_rate > 0 and link_timeout > 0):
            raise InputError("physics_dt, telemetry_rate and link_timeout must be > 0")
        # n independent first-order lags as one diagonal state-space system, ZOH-discretised once.
        sys_c = ct.ss(np.diag(-1.0 / taus), np.diag(1.0 / taus), np.eye(n), np.zeros((n, n)))
        sys_d = ct.c2d(sys_c, physics_dt, method="zoh")
        self._Ad = np.asarray(sys_d.A)
        self._Bd = np.asarray(sys_d.B)
        self._dc = np.linalg.solve(np.eye(n) - self._Ad, self._Bd)  # steady state per unit input
        self.tau = taus
        self.physics_dt = float(physics_dt)
        self.faults = faults or Faults()
        self._rng = np.random.default_rng(seed)
        x0 = actuators.zero_offset.copy() if initial is None else np.asarray(initial, dtype=float).copy()
        if x0.shape != (n,) or not np.all(np.isfinite(x0)):
            raise InputError(f"initial: expected {n} finite actuator values")
        self._x = x0
        self._target = x0.copy()
        self._tel_dt = 1.0 / telemetry_rate
        self._link_timeout = link_timeout
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
        self._last_seq = 0
        self._status = STATUS_HOLDING
        self._estop = False
        self._refused_latched = False
        self._counts = {
            "received": 0,
            "applied": 0,
            "crc_errors": 0,
            "missed": 0,
            "stale": 0,
            "refused": 0,
            "dropped_in": 0,
            "dropped_out": 0,
            "corrupted_in": 0,
            "corrupted_out": 0,
            "telemetry": 0,
        }
        self._tel_seq = 0
        self._pending: list[tuple[float, int, bytes]] = []
        self._pending_n = 0
        self._pending_addr: tuple[str, int] = ("127.0.0.1", 0)
        self.applied: deque[Applied] = deque(maxlen=history)
        self._t0 = 0.0
        self._last_valid = 0.0

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
        self._last_valid = self._t0
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
        self._last_valid = self._t0
        self._loop(duration)

    # ------------------------------------------------------------- snapshot
    def state(self) -> dict[str, Any]:
        """Positions, target, status bits and counters (a copy)."""
        with self._lock:
            return {
                "positions": self._x.copy(),
                "target": self._target.copy(),
                "status": self._status,
                "last_seq": self._last_seq,
                **self._counts,
            }

    # ----------------------------------------------------------------- loop
    def _loop(self, duration: float | None = None) -> None:
        t_phys = time.monotonic()
        t_tel = t_phys
        end = None if duration is None else t_phys + duration
        while not self._stop.is_set():
            now = time.monotonic()
            if end is not None and now >= end:
                return
            deaf = self._disconnected(now)
            self._receive(now, deaf)
            self._release_delayed(now)
            steps = int((now - t_phys) / self.physics_dt)
            if steps > 0:
                with self._lock:
                    self._advance(steps)
                t_phys += steps * self.physics_dt
            if now - self._last_valid > self._link_timeout and self._last_seq > 0:
                self._status |= STATUS_LINK_LOST
            if now >= t_tel:
                if not deaf:
                    self._send_telemetry(now)
                t_tel += self._tel_dt
                if t_tel < now:
                    t_tel = now + self._tel_dt
            wait = min(t_tel, t_phys + self.physics_dt) - time.monotonic()
            if self._pending:
                wait = min(wait, self._pending[0][0] - time.monotonic())
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
        since = now - self._t0
        return f.disconnect_after <= since < f.disconnect_after + f.disconnect_for

    def _advance(self, steps: int) -> None:
        # exact for a constant input over `steps` ZOH steps: x_k = A^k (x - x_ss) + x_ss
        x_ss = self._dc @ self._target
        Ak = np.linalg.matrix_power(self._Ad, steps) if steps > 1 else self._Ad
        self._x = Ak @ (self._x - x_ss) + x_ss

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
            if deaf:
                continue
            f = self.faults
            if f.drop and self._rng.random() < f.drop:
                self._counts["dropped_in"] += 1
                continue
            if f.corrupt and self._rng.random() < f.corrupt:
                data = self._flip_bits(data)
                self._counts["corrupted_in"] += 1
            if f.delay > 0:
                self._pending_n += 1
                heapq.heappush(self._pending, (now + f.delay, self._pending_n, data))
                self._pending_addr = addr
                continue
            self._handle(data, addr, now)

    def _release_delayed(self, now: float) -> None:
        while self._pending and self._pending[0][0] <= now:
            _, _, data = heapq.heappop(self._pending)
            self._handle(data, self._pending_addr, now)

    def _flip_bits(self, data: bytes) -> bytes:
        b = bytearray(data)
        for _ in range(int(self._rng.integers(1, 4))):
            i = int(self._rng.integers(0, len(b) * 8))
            b[i // 8] ^= 1 << (i % 8)
        return bytes(b)

    def _handle(self, data: bytes, addr: tuple[str, int], now: float) -> None:
        with self._lock:
            self._counts["received"] += 1
            try:
                msg = Frame.decode(data)
            except FrameError:
                self._counts["crc_errors"] += 1
                return
            if not isinstance(msg, Frame):
                self._counts["crc_errors"] += 1  # telemetry is never addressed to a device
                return
            if msg.kind == PING:
                # a new session: telemetry goes to this host, sequence numbering restarts
                self._peer = addr
                self._last_seq = 0
                self._last_valid = now
                return
            if msg.values.size != self.actuators.n:
                self._counts["crc_errors"] += 1  # well-formed but not for this device: rejected likewise
                return
            self._peer = addr
            if msg.seq <= self._last_seq:
                self._counts["stale"] += 1
                return
            if msg.seq > self._last_seq + 1:
                self._counts["missed"] += msg.seq - self._last_seq - 1
            self._last_seq = msg.seq
            self._last_valid = now
            self._status &= ~STATUS_LINK_LOST
            if self._estop:
                return  # latched until the device restarts
            if msg.kind == ESTOP:
                self._estop = True
                self._target = self._x.copy()  # freeze where the servos are
                self._status |= STATUS_ESTOP | STATUS_HOLDING
                self._record(now, msg)
                return
            viol = self.actuators.position_violation(msg.values)
            if np.any(viol > 1e-9 * np.maximum(np.abs(msg.values), 1.0)):
                self._counts["refused"] += 1
                self._status |= STATUS_REFUSED | STATUS_HOLDING
                return
            self._target = msg.values.copy()
            if msg.kind == HOLD:
                self._status |= STATUS_HOLDING
            elif msg.kind == MOVE:
                self._status &= ~STATUS_HOLDING
            self._record(now, msg)

    def _record(self, now: float, msg: Frame) -> None:
        self._counts["applied"] += 1
        self.applied.append(Applied(now - self._t0, msg.seq, msg.kind, msg.stamp, msg.values.copy()))

    def _send_telemetry(self, now: float) -> None:
        with self._lock:
            peer = self._peer
            if peer is None:
                return
            self._tel_seq += 1
            tel = Telemetry(
                seq=self._tel_seq,
                stamp=now - self._t0,
                ack=self._last_seq,
                status=self._status,
                positions=self._x.copy(),
                crc_errors=self._counts["crc_errors"],
                missed=self._counts["missed"],
                stale=self._counts["stale"],
                refused=self._counts["refused"],
            )
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
