"""A simulated device that speaks the wire protocol over UDP on 127.0.0.1.

The device is three parts: the servo model (`crtraj.hardware.sim._servo`: a time-optimal motion generator per
actuator and a first-order motor, so it never moves faster than its limits, whatever it is told), the protocol
handling without a socket (`crtraj.hardware.sim.DeviceCore`: sessions, sequence numbers, limits
checks, telemetry; on device time in s, so tests drive it with a virtual clock), and here the server loop:
`SimDevice` puts the core behind a UDP socket, sends telemetry at a fixed rate to the host of the current
session, and injects faults.

Faults for testing the streamer: drop (each datagram, both directions, with
a probability), corrupt (flip bits of incoming datagrams and outgoing
telemetry), delay (hold incoming datagrams for a time) and disconnect (go
silent and deaf for a time window).
"""

from __future__ import annotations

import heapq
import logging
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
from crtraj.hardware.sim._device_core import Applied, DeviceCore, LimitViolation

__all__ = ["Faults", "SimDevice"]

logger = logging.getLogger(__name__)


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
                logger.debug("simulated device: datagram from %s raised", addr, exc_info=True)

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
