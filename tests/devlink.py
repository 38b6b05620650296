"""Test helper: a Streamer link to an in-process `DeviceCore` on the streamer's own virtual clock.

No socket, no thread, no wall clock: every frame the streamer sends is handled
by the device at the clock's current time, and telemetry is produced at the
device's rate as the clock advances. `inject` hands the device hostile
datagrams; `intercept` may rewrite or drop frames on the way to the device.
"""

from __future__ import annotations

from collections.abc import Callable

from crtraj.core.clock import VirtualClock
from crtraj.hardware.sim._device_core import DeviceCore
from crtraj.hardware.transport import Transport


class CoreLink(Transport):
    """Streamer <-> DeviceCore on a shared virtual clock. telemetry_dt: s between telemetry frames."""

    has_telemetry = True
    description = "core-link"

    def __init__(self, core: DeviceCore, clock: VirtualClock, telemetry_dt: float = 0.01) -> None:
        self.core = core
        self.clock = clock
        clock.advance(max(core.time - clock.now(), 0.0))  # one device, one monotonic clock across runs
        self.telemetry_dt = telemetry_dt
        self._next_tel = clock.now()
        self.sent: list[bytes] = []
        self.extra_rx: list[bytes] = []  # datagrams delivered to the streamer before the next telemetry
        self.intercept: Callable[[bytes], bytes | None] | None = None
        self.silent = False  # device deaf and mute

    def send(self, frame: bytes) -> None:
        self.sent.append(frame)
        data = frame if self.intercept is None else self.intercept(frame)
        if data is not None and not self.silent:
            self.core.handle(data, self.clock.now())

    def inject(self, data: bytes) -> bool:
        """A datagram from someone else, handled by the device now."""
        return self.core.handle(data, self.clock.now())

    def receive(self) -> list[bytes]:
        now = self.clock.now()
        out, self.extra_rx = self.extra_rx, []
        if now >= self._next_tel:
            self._next_tel = max(self._next_tel + self.telemetry_dt, now)
            tel = None if self.silent else self.core.telemetry(now)
            if tel is not None:
                out.append(tel.encode())
        else:
            self.core.advance(now)
        return out
