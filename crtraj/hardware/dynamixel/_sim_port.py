"""The Dynamixel simulator as an in-process port: the official SDK's bytes reach a `ServoChain` without a
pseudo-terminal or a thread, on an injected clock.

`SimPort` has the methods the SDK's `PacketHandler` and `GroupSync*` call on a `PortHandler` (``writePort``,
``readPort``, the packet timeout, ``clearPort``, ...). Every packet the host writes is parsed by the
simulator's own reader (`crtraj.hardware.dynamixel._protocol.PacketReader`, written from the spec, not from the
SDK), handled by the chain at the clock's time, and its status packets are queued for the host's reads as
bytes: the real protocol bytes both ways. The whole transaction happens inside ``writePort``, so a reply that
is not queued when the host reads never comes: the SDK's packet timeout then expires at once, the clock moving
on by the rest of the timeout (what a host waits for a silent servo). With ``wire_time`` the clock also moves
on by the transaction's time on a real wire (`ServoChain.reply_time`). On a `crtraj.core.clock.VirtualClock`
shared with the streamer and the homing, a run is the same on any machine under any load.

Tests put a factory of these in `crtraj.hardware.dynamixel._link.port_factory` (the test seam, no flag reaches it), so
that `crtraj.cli.main([...])` drives the simulator end to end. Times in s.

Unplugging the adapter (`unplug_at`): from that clock time on, every call on the port raises what pyserial
raises on a USB-serial adapter (or a pseudo-terminal) that went away: `serial.SerialException` on a write or
a read, `OSError` (EIO) for the bytes waiting, `termios.error` (EIO) for a flush; closing still works.
"""

from __future__ import annotations

import errno
import termios

import serial

from crtraj.core.clock import Clock
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._sim_chain import ServoChain

SDK_LATENCY_MS = 16.0  # the SDK's LATENCY_TIMER (ms): its packet timeout is bytes' time + 2 x this + 2 ms


class SimPort:
    """A `ServoChain` behind the SDK's port interface, on `clock` (see the module doc).

    name: the device name it stands for. wire_time: the clock moves on by each transaction's bus time.
    """

    def __init__(self, chain: ServoChain, clock: Clock, *, name: str = "sim", wire_time: bool = False) -> None:
        self.chain, self.clock, self.wire_time = chain, clock, wire_time
        self.port_name = name
        self.baudrate = chain.baud
        self.is_open = False
        self.is_using = False  # the SDK's own busy flag
        self.ser = None  # no serial port behind it (`DynamixelTransport._set_baud` tunes a real one)
        self.tx_time_per_byte = 10_000.0 / self.baudrate  # ms
        self.packet_start_time = 0.0  # ms on the clock
        self.packet_timeout = 0.0  # ms
        self.wrong_baud = 0  # packets written at another rate than the bus's: nobody answered
        self.timeouts = 0  # reads that found no reply and timed out
        self.unplug_at: float | None = None  # clock time (s) the adapter is pulled out (None: never)
        self._rx = bytearray()
        self._reader = dxl.PacketReader()

    # ------------------------------------------------------------ port life
    def openPort(self) -> bool:  # noqa: N802 - the SDK's names
        return self.setBaudRate(self.baudrate)

    def closePort(self) -> None:  # noqa: N802
        self.is_open = False
        self._rx.clear()

    def unplugged(self) -> bool:
        """The adapter is out (`unplug_at` reached on the clock)."""
        return self.unplug_at is not None and self.clock.now() >= self.unplug_at

    def clearPort(self) -> None:  # noqa: N802
        if self.unplugged():
            raise termios.error(errno.EIO, "Input/output error")
        self._rx.clear()

    def setBaudRate(self, baudrate: int) -> bool:  # noqa: N802
        self.baudrate = int(baudrate)
        self.tx_time_per_byte = 10_000.0 / self.baudrate
        self.is_open = True
        self._rx.clear()
        return True

    def getBaudRate(self) -> int:  # noqa: N802
        return self.baudrate

    def getPortName(self) -> str:  # noqa: N802
        return self.port_name

    # ----------------------------------------------------------------- bytes
    def getBytesAvailable(self) -> int:  # noqa: N802
        if self.unplugged():
            raise OSError(errno.EIO, "Input/output error")
        return len(self._rx)

    def writePort(self, packet: list[int] | bytes) -> int:  # noqa: N802
        """The host sends `packet`: the chain handles every complete packet now; its replies are queued."""
        data = bytes(packet)
        if self.unplugged():
            raise serial.SerialException(f"write failed: {OSError(errno.EIO, 'Input/output error')}")
        if self.baudrate != self.chain.baud:
            self.wrong_baud += 1  # a host at another rate: the servos see noise, nobody answers
            return len(data)
        for p in self._reader.feed(data):
            replies = self.chain.handle(p, self.clock.now())
            if self.wire_time:
                self.clock.sleep(self.chain.reply_time(p.size, replies))
            for r in replies:
                self._rx += r
        return len(data)

    def readPort(self, length: int) -> bytes:  # noqa: N802
        if self.unplugged():
            raise serial.SerialException(
                "device reports readiness to read but returned no data (device disconnected or multiple access on "
                "port?)"
            )
        out = bytes(self._rx[:length])
        del self._rx[:length]
        return out

    # --------------------------------------------------------------- timeout
    def getCurrentTime(self) -> float:  # noqa: N802
        """The clock's time in ms (the SDK's unit)."""
        return self.clock.now() * 1000.0

    def setPacketTimeout(self, packet_length: int) -> None:  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * SDK_LATENCY_MS + 2.0

    def setPacketTimeoutMillis(self, msec: float) -> None:  # noqa: N802
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = msec

    def isPacketTimeout(self) -> bool:  # noqa: N802
        """Asked only when the reply is short: in process nothing more arrives, so the wait runs out now."""
        if self._rx:
            return False
        self.clock.sleep((self.packet_start_time + self.packet_timeout - self.getCurrentTime()) / 1000.0)  # ms -> s
        self.packet_timeout = 0.0
        self.timeouts += 1
        return True
