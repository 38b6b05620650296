"""`SimDynamixel`: a chain of simulated Dynamixel servos (`crtraj.hardware.dynamixel.ServoChain`) served on a
pseudo-terminal from a thread, so the host opens `path` like a USB serial port (see that module's doc)."""

from __future__ import annotations

import contextlib
import os
import select
import termios
import threading
import time
import tty
from collections.abc import Callable
from types import MappingProxyType

from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._sim_chain import ServoChain

_BAUD_TERMIOS = MappingProxyType(
    {b: getattr(termios, f"B{b}") for b in dxl.BAUD_CODES.values() if hasattr(termios, f"B{b}")}
)


class SimDynamixel:
    """A `ServoChain` served on a pseudo-terminal from a thread; `path` is the device to open.

    clock: the chain's device time (s; tests pass a virtual clock). wire_time:
    delay replies by their bytes' time on a real wire at the chain's baud rate
    and the servos' Return Delay Time. power_cycle_at: power-cycle every servo
    this long (clock s) after `serve` starts.
    """

    def __init__(
        self,
        chain: ServoChain,
        *,
        clock: Callable[[], float] = time.monotonic,
        wire_time: bool = True,
        power_cycle_at: float | None = None,
    ) -> None:
        self.chain = chain
        self.power_cycle_at = power_cycle_at  # s after `serve` starts (clock time): every servo power-cycles once
        self.clock = clock
        self.wire_time = wire_time
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reader = dxl.PacketReader()
        self._bus_free = 0.0
        self.wrong_baud = 0  # reads ignored because the host's rate was not the bus rate
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        attrs[4] = attrs[5] = _BAUD_TERMIOS.get(chain.baud, attrs[4])
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        self.path = os.ttyname(self._slave)

    @property
    def bad_packets(self) -> int:
        """Packets dropped for a bad CRC or length."""
        return self._reader.bad_crc + self._reader.bad_length

    def __enter__(self) -> SimDynamixel:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> SimDynamixel:
        self._thread = threading.Thread(target=self.serve, name="crtraj-sim-dynamixel", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    def locked(self) -> threading.Lock:
        """Hold it to change the chain's faults while it serves."""
        return self._lock

    def serve(self, duration: float | None = None) -> None:
        """Answer packets until `stop` (or for `duration` s of wall time)."""
        end = None if duration is None else time.monotonic() + duration
        cycle = None if self.power_cycle_at is None else self.clock() + self.power_cycle_at
        while not self._stop.is_set() and (end is None or time.monotonic() < end):
            cycle = self._power_cycle_due(cycle)
            try:
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(self._master, 4096)
            except OSError:
                return  # closed
            arrived = time.perf_counter()
            if termios.tcgetattr(self._master)[4] != _BAUD_TERMIOS.get(self.chain.baud):
                self.wrong_baud += 1  # a host at another rate: a real bus sees noise, nobody answers
                continue
            cycle = self._power_cycle_due(cycle)  # before the packet: it meets the servos as they are now
            for packet in self._reader.feed(data):
                with self._lock:
                    replies = self.chain.handle(packet, self.clock())
                self._send(packet.size, replies, arrived)

    def _power_cycle_due(self, cycle: float | None) -> float | None:
        """Power-cycle every servo once the clock reaches `cycle` (s); the time still pending (None: done)."""
        if cycle is None or self.clock() < cycle:
            return cycle
        with self._lock:
            self.chain.power_cycle(self.clock())
        return None

    def _send(self, request_size: int, replies: list[bytes], arrived: float) -> None:
        """Write the replies, after the wire time of the request and of each reply when modelled."""
        t = max(arrived, self._bus_free) + self.chain.reply_time(request_size, replies)
        self._bus_free = t
        if not replies:
            return
        if self.wire_time:  # one sleep to the end of the last reply (the host waits for all of them anyway)
            delay = t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        with contextlib.suppress(OSError):
            os.write(self._master, b"".join(replies))
