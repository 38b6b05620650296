"""Dynamixel servos (Protocol 2.0, X-series) as a streamer link, on the official `dynamixel_sdk`.

`DynamixelTransport` is a `Transport`: the `Streamer` stays the one place every
command passes through (limits gate, admission's verified frames, watchdog,
acknowledgement and following checks, e-stop), and this link only carries
its frames to the bus. Per frame:

- MOVE / HOLD: the values (rad, mm) become ticks (`crtraj.hardware.dynamixel._servo_bus`)
  and go out as one Group Sync Write of the goal positions of every servo (one
  bus transaction per set-point);
- ESTOP (after the streamer's planned stop, `crtraj.hardware.stream._braking`): with ``stop_torque="off"`` one Group
  Sync Write of torque enable = 0 (torque off); with "keep" (the default) the goals stay where the stop ended,
  torque on; either way latched: no goal is written after it;
- PING: opens the session (no bus traffic).

Every `receive` is one Group Sync Read of torque enable, hardware error
status, present velocity and present position (one transaction: the four
fields are mapped next to each other through the indirect addresses at
connect), turned into a telemetry frame (positions back in rad / mm, the last
written set-point acknowledged, e-stop status).
A hardware error bit, a servo whose torque went off without an e-stop (it
rebooted, e.g. after a brown-out: its indirect addresses are then reset too,
so the torque byte reads 0 either way), or a servo that misses `max_misses`
reads in a row, is a `TransportError` naming the servo: the link holds at
once (no goal is written after it) and the streamer stops and reports it.
`close` turns the torque off with ``stop_torque="off"`` and leaves it on with "keep".

Connecting checks, each failure one line: the port exists and opens, the
servos answer at this baud rate (if none does, the other common rates are
tried and the right one named), every id answers (a silent one is named),
each model number is the robot file's, no hardware error bit is set, and the
actuators' position limits fit the extended position range, and Drive Mode
carries no bit the robot file does not declare (`crtraj.hardware.dynamixel._checks.DriveModeCheck`:
no undeclared reverse bit, never the time-based profile). Then it sets torque
off and the declared reverse bits, and checks that every position is absolute
(`crtraj.hardware.dynamixel._homing_state.PowerUpCheck`: a multi-turn actuator homed since
its last power-up, matching the homing state file; a spool unwrapped into its
limits). That check is on by default: every caller that opens a link to move
the robot (``crtraj stream``, ``crtraj replan --stream``, a `Streamer.open`)
gets it; only ``crtraj home`` turns it off (``power_up_check=False``). Then it
sets Return Delay Time (0 by default: the factory 250 adds
500 us to every reply), Status Return Level 2, extended position control (operating mode 4: a spool turns more
than one revolution), the profile velocity and acceleration from the
actuator limits, the indirect addresses, the goal to the present position,
and torque on. On Linux
a USB-serial latency timer above 1 ms is a warning: it caps the rate.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import termios
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import numpy as np
import serial

from crtraj.core.clock import Clock, default_clock
from crtraj.core.errors import InputError
from crtraj.core.interrupt import shielded
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel._checks import (
    SYSFS_USB_SERIAL,
    DriveModeCheck,
    ServoCheck,
    check_baud,
    check_ranges,
    hardware_error_line,
    latency_warning,
)
from crtraj.hardware.dynamixel._homing_state import HomingState, PowerUpCheck, multi_turn, record_last
from crtraj.hardware.dynamixel._protocol import X, reply_sizes_checked
from crtraj.hardware.dynamixel._safety import BusWatchdog, ForceCaps, TripWatch, watchdog_units
from crtraj.hardware.protocol import ESTOP, PING, STATUS_ESTOP, Frame, Telemetry, seq_next
from crtraj.hardware.transport import LinkLostError, Transport, TransportError

log = logging.getLogger(__name__)

DEFAULT_BAUD = 1_000_000
CONNECT_ATTEMPTS = 3  # tries of each transaction while connecting
READ_BLOCK = 0.002  # s a port read may wait for its bytes (far below the SDK's 34 ms reply timeout)
# what one sync read returns, through the indirect addresses: (address, size) in this order
_STATE = (
    (X.TORQUE_ENABLE, 1),
    (X.HARDWARE_ERROR, 1),
    (X.PRESENT_VELOCITY, 4),
    (X.PRESENT_POSITION, 4),
    (X.BUS_WATCHDOG, 1),
    (X.PRESENT_CURRENT, 2),
    (X.PRESENT_VOLTAGE, 2),
    (X.PRESENT_TEMPERATURE, 1),
)
_STATE_SIZE = sum(n for _, n in _STATE)
_AT_TORQUE, _AT_ERROR = X.INDIRECT_DATA, X.INDIRECT_DATA + 1
_AT_VELOCITY, _AT_POSITION, _AT_WATCHDOG = X.INDIRECT_DATA + 2, X.INDIRECT_DATA + 6, X.INDIRECT_DATA + 10
_AT_CURRENT, _AT_VOLTAGE, _AT_TEMPERATURE = X.INDIRECT_DATA + 11, X.INDIRECT_DATA + 13, X.INDIRECT_DATA + 15
# what reaches the SDK's callers when the adapter goes away (USB-serial unplugged): pyserial raises
# SerialException on a write or read, OSError from the ioctl behind in_waiting, termios.error from the flush
# behind clearPort; the SDK catches none of them (and leaves its busy flag set)
LINK_ERRORS = (serial.SerialException, OSError, termios.error)
# a pseudo-terminal's reply allowance beyond the SDK's (ms), and Linux's device numbers of pseudo-terminal ends
PTY_LATENCY_MS = 500.0
_PTY_MAJORS = range(136, 144)
# indices into the SDK's packets (lists of bytes; header FF FF FD 00, then id)


def _sdk() -> Any:
    """The official SDK (the optional extra), or a one-line `InputError` saying how to install it."""
    try:
        import dynamixel_sdk
    except ImportError:
        raise InputError("--dynamixel: the Dynamixel SDK is not installed; pip install 'crtraj[dynamixel]'") from None
    return dynamixel_sdk


def sdk_port(sdk: Any, device: str) -> Any:
    """The SDK's `PortHandler` of `device`; `TransportError` (one line) when there is no such device. On a
    pseudo-terminal each reply may take `PTY_LATENCY_MS` longer: its other end is a program (`crtraj
    sim-dynamixel`, a socat bridge), which answers when the scheduler runs it, not within a bus's microseconds."""
    if not os.path.exists(device):
        raise TransportError(
            f"{device}: no such port (is the USB-serial adapter, e.g. a U2D2, plugged in? see ls /dev/ttyUSB*)"
        )
    port = sdk.PortHandler(device)
    try:
        pty = os.major(os.stat(device).st_rdev) in _PTY_MAJORS
    except OSError:
        pty = False
    if pty:
        timeout = port.setPacketTimeout

        def patient(packet_length: int) -> None:
            timeout(packet_length)
            port.packet_timeout += PTY_LATENCY_MS

        port.setPacketTimeout = patient
    return port


# Test seam, not a user-facing option: how a device name becomes a port object. Production opens the SDK's
# port; end-to-end tests set it (pytest's monkeypatch) to put the in-process simulator's port
# (`crtraj.hardware.dynamixel.SimPort`) behind one device name.
port_factory: Callable[[Any, str], Any] = sdk_port


def parse_url(url: str) -> tuple[str, int]:
    """(device, baud) of ``dynamixel:///dev/ttyUSB0[?baud=N]``; one-line `InputError` otherwise."""
    parts = urlsplit(url)
    device = parts.netloc + parts.path
    if parts.scheme != "dynamixel" or not device:
        raise InputError(f"stream target: expected dynamixel:///dev/PORT[?baud=N], got {url!r}")
    q = parse_qs(parts.query)
    text = q["baud"][0] if "baud" in q else str(DEFAULT_BAUD)
    if not (text.isascii() and text.isdecimal() and len(text) <= 10):  # int() takes other scripts' digits
        raise InputError(f"stream target: baud must be an integer, got {text[:40]!r}")
    return device, int(text)


def _signed32(v: int) -> int:
    return v - (1 << 32) if v >= 1 << 31 else v


class DynamixelTransport(Transport):
    """The servos of `actuators.bus` on `device` at `baud`, as a streamer link (see the module doc).

    warn: where connection warnings go (default: a warning of the ``crtraj`` logger). sysfs: the USB-serial
    sysfs folder (tests point it elsewhere). max_misses: failed reads in a row that end the stream.
    homing: the homing state (or the path of its file, `crtraj.hardware.dynamixel.state_path` of the robot
    file) that absolute positions are checked against (`crtraj.hardware.dynamixel._homing_state.PowerUpCheck`, before
    torque comes on); None: no state, so every multi-turn actuator is refused until homed.
    power_up_check: False skips that check (only `crtraj home`, which makes the positions absolute itself).
    return_delay: Return Delay Time written to every servo (2 us units, 0..254). home_command: named in refusals.
    stop_torque: ``[robot.stop] torque``: "keep" (an e-stop, after the streamer's planned stop, latches the
    goals with the torque on, and `close` leaves it on: the cables stay taut, a lead-screw stage cannot
    back-drive) or "off" (torque off at e-stop and close).
    clock: stamps the telemetry and times the drain after a failed read (default
    `crtraj.core.clock.default_clock()`, the wall clock; share the streamer's).
    """

    # Over 60 lines: the connection checks, each with its own one-line message, in the order a lab meets them.
    def __init__(  # long: connection checks in order
        self,
        device: str,
        baud: int,
        actuators: Actuators,
        *,
        warn: Callable[[str], None] | None = None,
        sysfs: Path = SYSFS_USB_SERIAL,
        max_misses: int = 5,
        homing: HomingState | str | Path | None = None,
        power_up_check: bool = True,
        return_delay: int = 0,
        home_command: str = "crtraj home",
        stop_torque: str = "keep",
        clock: Clock | None = None,
        bus_watchdog: float = 0.1,
    ) -> None:
        sdk = _sdk()
        self._clock = default_clock() if clock is None else clock
        if actuators.bus is None:
            raise InputError(
                "robot.actuators: no Dynamixel ids; add id, ticks_per_rev and model per servo (and lead for z), "
                "see README 'Run it on a real robot'"
            )
        self.bus = bus = actuators.bus
        check_ranges(actuators, bus)
        self.baud = check_baud(int(baud))
        self.device = device
        self.description = f"dynamixel://{device}?baud={self.baud}"
        self.warnings: list[str] = []
        self._warn = warn if warn is not None else log.warning
        self.max_misses = int(max_misses)
        if not 0 <= int(return_delay) <= 254:
            raise InputError(f"--return-delay: must be in 0..254 (2 us units), got {return_delay}")
        self.return_delay = int(return_delay)
        if stop_torque not in ("keep", "off"):
            raise InputError(f'robot.stop.torque: must be "keep" or "off", got {stop_torque!r}')
        self.stop_torque = stop_torque
        self.bus_watchdog = watchdog_units(bus_watchdog)
        self.caps = ForceCaps(actuators)  # a robot file without its tendons' caps is one line before the port opens
        why = self.caps.refusal()
        if why is not None:
            raise InputError(why)
        self.trips = TripWatch(self.caps)  # the first reading beyond a bound, and the last readings
        # a bad state file is one line before the port opens
        state = homing if isinstance(homing, HomingState) else HomingState.load(homing) if homing else HomingState()
        self._state, self._state_path = state, None if isinstance(homing, HomingState) or not homing else Path(homing)
        self._sdk = sdk
        self._ph = reply_sizes_checked(sdk.PacketHandler(2.0), sdk.COMM_RX_CORRUPT)
        self._port = None
        self._lost: str | None = None  # why the link is gone (`_bus`), or None
        port = port_factory(sdk, device)
        try:
            opened = port.openPort() and self._set_baud(port, self.baud)
        except Exception as exc:  # pyserial raises SerialException / OSError / ValueError
            why = f"{device}: cannot open ({exc}); on Linux, is your user in the dialout group?"
            raise TransportError(why) from None
        if not opened:
            raise TransportError(f"{device}: cannot open at {self.baud} baud")
        self._port = port
        try:
            w = latency_warning(device, sysfs)
            if w is not None:
                self.warnings.append(w)
                self._warn(w)
            ServoCheck(self).run()
            watchdog = BusWatchdog(self, bus, self.bus_watchdog)
            tripped = watchdog.start()
            drive = DriveModeCheck(self, bus)
            why = drive.refusal()  # before anything is written
            if why is not None:
                raise TransportError(why)
            self._torque_off(confirm=True)
            drive.apply()
            if power_up_check:
                watchdog.refuse_tripped(tripped, multi_turn(actuators), home_command)
                PowerUpCheck(self, actuators, state, home_command).run()
            self._setup(actuators)
        except BaseException:
            with contextlib.suppress(Exception):  # a setup that failed half-way must not leave torque on
                self._torque_off(confirm=False)
            with contextlib.suppress(*LINK_ERRORS):
                self._port.closePort()
            self._port = None
            raise
        self._write_goal = sdk.GroupSyncWrite(port, self._ph, X.GOAL_POSITION, 4)
        self._read_state = sdk.GroupSyncRead(port, self._ph, X.INDIRECT_DATA, _STATE_SIZE)
        for i in bus.ids:
            self._write_goal.addParam(i, [0, 0, 0, 0])
            self._read_state.addParam(i)
        self._session: int | None = None
        self._ack = 0
        self._seq = 0
        self._estopped = False
        self._armed = False  # the bus watchdog re-armed at the session's first frame
        self._held: str | None = None  # why the link holds (a servo failed mid-stream), or None
        self._misses = 0
        self.counts = {"timeouts": 0, "corrupt": 0, "writes": 0, "reads": 0}
        self.timings: deque[tuple[float, float]] = deque(maxlen=100_000)  # (write s, read s) per tick
        self._t_write = 0.0
        self._t0 = self._clock.now()
        self.velocities = np.zeros(len(bus.ids))  # last present velocities (rad/s, mm/s)

    @staticmethod
    def _set_baud(port: Any, baud: int) -> bool:
        """`PortHandler.setBaudRate`, then reads that block up to `READ_BLOCK` s for the bytes the SDK asks
        for: the SDK polls the port in a loop, and with pyserial's default (timeout 0) that loop spins a core
        while a reply is on the wire; blocking in select returns as soon as the bytes are there."""
        ok = port.setBaudRate(baud)
        if ok and port.ser is not None:
            port.ser.timeout = READ_BLOCK
        return ok

    # ------------------------------------------------------------ the bus
    def _bus(self, call: Callable[..., Any], *args: Any) -> Any:
        """`call(*args)`: the one place an SDK call (or a call on its port) is made. A serial or OS error (the
        adapter unplugged) becomes `LinkLostError`, the SDK's busy flag released (it stays set when the error
        escapes mid-packet), and every later call refuses at once without touching the port."""
        if self._lost is not None:
            raise LinkLostError(self._lost)
        try:
            # a Ctrl-C or SIGTERM waits for the packet's end: one cut mid-packet leaves the SDK's busy flag set
            # ("Port is in use!") and the bus mid-frame, so the stop that follows could not reach the servos
            with shielded():
                return call(*args)
        except LINK_ERRORS as exc:
            if self._port is not None:
                self._port.is_using = False
            self._lost = (
                f"{self.device}: the link to the servos is lost ({type(exc).__name__}: {exc}); is the USB-serial "
                "adapter unplugged? the servos keep their last goal until their bus watchdog stops them: plug it "
                "back in, check the robot, then stream again"
            )
            log.info("%s", self._lost)
            raise LinkLostError(self._lost) from None

    # --------------------------------------------------------------- checks
    def _ask(self, call: Callable[..., tuple[Any, ...]], *args: Any) -> tuple[Any, ...]:
        """One connect-time transaction (an SDK call returning ``(..., result, error)``), tried up to
        `CONNECT_ATTEMPTS` times: a reply lost to line noise (or a busy host) is not yet a missing servo. A try
        after a failed one drains late replies first (a reply of the wrong size is refused: `reply_sizes_checked`)."""
        out = self._bus(call, self._port, *args)
        for _ in range(CONNECT_ATTEMPTS - 1):
            if out[-2] == self._sdk.COMM_SUCCESS:
                break
            self._drain()
            out = self._bus(call, self._port, *args)
        return out

    def read(self, dxl_id: int, addr: int, size: int) -> int:
        """One register of servo `dxl_id` (signed for 2 and 4 bytes); `TransportError` naming it on no answer."""
        f = {1: self._ph.read1ByteTxRx, 2: self._ph.read2ByteTxRx, 4: self._ph.read4ByteTxRx}[size]
        value, result, _ = self._ask(f, dxl_id, addr)
        if result != self._sdk.COMM_SUCCESS:
            raise TransportError(f"servo {self.bus.name_of(dxl_id)}: cannot read register {addr}")
        if size == 4:
            return _signed32(value)
        return value - (1 << 16) if size == 2 and value >= 1 << 15 else value

    def write(self, dxl_id: int, addr: int, value: int, size: int, what: str) -> None:
        """Write one register (value as unsigned bytes); `TransportError` naming `what` when refused."""
        self._write1(dxl_id, addr, value, size, what)

    def _write1(self, dxl_id: int, addr: int, value: int, size: int, what: str) -> None:
        f = {1: self._ph.write1ByteTxRx, 2: self._ph.write2ByteTxRx, 4: self._ph.write4ByteTxRx}[size]
        result, error = self._ask(f, dxl_id, addr, value)
        if result != self._sdk.COMM_SUCCESS or error & 0x7F:
            raise TransportError(
                f"servo {self.bus.name_of(dxl_id)}: setting {what} failed "
                f"({self._ph.getTxRxResult(result) if result else self._ph.getRxPacketError(error)})"
            )

    def _setup(self, actuators: Actuators) -> None:
        """Torque off, the force caps (`crtraj.hardware.dynamixel._safety`), profiles, goal = present, torque on."""
        bus = self.bus
        for i in bus.ids:
            self._write1(i, X.TORQUE_ENABLE, 0, 1, "torque off")
        self.caps.apply(self)  # shutdown conditions, operating mode 5 with the Goal Current of each cap (or 4)
        for k, i in enumerate(bus.ids):
            self._write1(i, X.RETURN_DELAY, self.return_delay, 1, "return delay time")
            self._write1(i, X.STATUS_RETURN, 2, 1, "status return level")
            # profile limits at or just above the actuator limits: the set-points already obey them, the
            # servo's own profile only smooths what the gate let through
            rev = bus.per_rev[k]
            vel = math.ceil(actuators.vmax[k] / rev * 60.0 / X.VELOCITY_UNIT)
            acc = math.ceil(actuators.amax[k] / rev * 3600.0 / X.ACCELERATION_UNIT)
            self._write1(i, X.PROFILE_VELOCITY, vel, 4, "profile velocity")
            self._write1(i, X.PROFILE_ACCELERATION, acc, 4, "profile acceleration")
            mirror = [a + j for a, n in _STATE for j in range(n)]
            data = [b for a in mirror for b in (a & 0xFF, a >> 8)]
            result, error = self._ask(self._ph.writeTxRx, i, X.INDIRECT_ADDRESS, len(data), data)
            if result != self._sdk.COMM_SUCCESS or error & 0x7F:
                raise TransportError(f"servo {bus.name_of(i)}: setting its indirect addresses failed")
            present, result, _ = self._ask(self._ph.read4ByteTxRx, i, X.PRESENT_POSITION)
            if result != self._sdk.COMM_SUCCESS:
                raise TransportError(f"servo {bus.name_of(i)}: cannot read its present position")
            # the goal is where it is, so torque on does not move it
            self._write1(i, X.GOAL_POSITION, present & 0xFFFFFFFF, 4, "goal position")
        for i in bus.ids:
            self._write1(i, X.TORQUE_ENABLE, 1, 1, "torque on")

    # -------------------------------------------------------------- frames
    def send(self, frame: bytes) -> None:
        """Carry one streamer frame (already through the limits gate) to the bus."""
        if self._port is None:
            raise TransportError(f"{self.description}: closed")
        msg = Frame.decode(frame)
        if msg.kind == PING:
            self._session, self._ack = msg.session, msg.seq
            return
        t = time.perf_counter()
        if msg.kind == ESTOP:
            if self.stop_torque == "off":
                self._torque_off(confirm=not self._estopped)  # the repeats of a latched e-stop: sync write only
            self._estopped = True  # "keep": the goals stay where the stop ended, torque on
        elif self._held is not None:  # a servo failed mid-stream: nothing moves the servos again
            raise TransportError(self._held)
        elif not self._estopped:  # after an e-stop nothing moves the servos again
            if not self._armed:
                self._arm_watchdog()
            ticks = self.bus.ticks(msg.values)
            if np.any(np.abs(ticks) > X.EXTENDED_LIMIT):
                k = int(np.argmax(np.abs(ticks)))
                raise TransportError(
                    f"servo {self.bus.name_of(self.bus.ids[k])}: goal {ticks[k]} ticks outside the extended "
                    f"position range +-{X.EXTENDED_LIMIT}"
                )
            for i, v in zip(self.bus.ids, ticks, strict=True):
                u = int(v) & 0xFFFFFFFF
                self._write_goal.changeParam(i, [u & 0xFF, (u >> 8) & 0xFF, (u >> 16) & 0xFF, u >> 24])
            result = self._bus(self._write_goal.txPacket)
            if result != self._sdk.COMM_SUCCESS:
                raise TransportError(f"{self.description}: sync write failed ({self._ph.getTxRxResult(result)})")
            self.counts["writes"] += 1
        self._ack = msg.seq
        self._t_write = time.perf_counter() - t

    def _sync1(self, addr: int, value: int) -> None:
        """One sync write of the 1-byte register `addr` = `value` to every servo (no replies)."""
        w = self._sdk.GroupSyncWrite(self._port, self._ph, addr, 1)
        for i in self.bus.ids:
            w.addParam(i, [value])
        self._bus(w.txPacket)

    def _arm_watchdog(self) -> None:
        """At the session's first frame: clear (0) and set the bus watchdog again; a trip counts from then on.
        Between connect and the first frame (an approach being planned) the host may be silent longer than the
        watchdog with the servos at rest: a trip then stopped nothing, and would leave the goals read-only."""
        self._sync1(X.BUS_WATCHDOG, 0)
        self._sync1(X.BUS_WATCHDOG, self.bus_watchdog)
        self._armed = True

    def _torque_off(self, confirm: bool = True) -> list[int]:
        """Torque off: one sync write to every servo at once, then (confirm) a write with a reply to each,
        so it has surely happened when this returns; the ids that did not confirm it."""
        self._sync1(X.TORQUE_ENABLE, 0)
        if not confirm:
            return []
        silent = []
        for i in self.bus.ids:
            result, _ = self._bus(self._ph.write1ByteTxRx, self._port, i, X.TORQUE_ENABLE, 0)
            if result != self._sdk.COMM_SUCCESS:
                silent.append(i)
        return silent

    def receive(self) -> list[bytes]:
        """One telemetry frame from a sync read of every servo (none before the session's PING, or on a miss)."""
        if self._session is None or self._port is None:
            return []
        t = time.perf_counter()
        group = self._read_state
        result = self._bus(group.txRxPacket)
        if result != self._sdk.COMM_SUCCESS:
            self._miss(result)
            return []
        self._misses = 0
        self.counts["reads"] += 1
        self.timings.append((self._t_write, time.perf_counter() - t))
        bus = self.bus
        ticks, vel = [], []
        for k, i in enumerate(bus.ids):
            self._check_state(i)
            ticks.append(_signed32(group.getData(i, _AT_POSITION, 4)))
            vel.append(_signed32(group.getData(i, _AT_VELOCITY, 4)))
            if not self._estopped:
                at = (_AT_CURRENT, 2), (_AT_VOLTAGE, 2), (_AT_TEMPERATURE, 1)
                self.trips.see(k, *(group.getData(i, a, n) for a, n in at))
        # present velocity in 0.229 rev/min units -> revolutions per second -> rad/s or mm/s
        self.velocities = np.asarray(vel) * X.VELOCITY_UNIT / 60.0 * np.asarray(bus.per_rev)
        self._seq = seq_next(self._seq)
        tel = Telemetry(
            seq=self._seq,
            stamp=self._clock.now() - self._t0,
            ack=self._ack,
            status=STATUS_ESTOP if self._estopped else 0,
            positions=bus.values(ticks),
            crc_errors=self.counts["corrupt"],
            missed=self.counts["timeouts"],
            session=self._session,
        )
        return [tel.encode()]

    def _check_state(self, dxl_id: int) -> None:
        """Hold at once when servo `dxl_id`'s last sync read shows a hardware error or its torque off
        without an e-stop (a reboot): no goal is written after it; `TransportError` naming the servo."""
        bits = self._read_state.getData(dxl_id, _AT_ERROR, 1)
        why = None
        if bits:
            why = hardware_error_line(self.bus, dxl_id, bits)
        elif self._armed and self._read_state.getData(dxl_id, _AT_WATCHDOG, 1) == X.WATCHDOG_TRIPPED:
            why = (
                f"servo {self.bus.name_of(dxl_id)}: its bus watchdog stopped it (no instruction for "
                f"{self.bus_watchdog * X.WATCHDOG_UNIT * 1000:.0f} ms); holding: check the host's load, then stream "
                "again"
            )
        elif not self._estopped and self._read_state.getData(dxl_id, _AT_TORQUE, 1) != 1:
            why = (
                f"servo {self.bus.name_of(dxl_id)}: torque off mid-stream (it rebooted or lost power); holding: "
                "check its power supply, then stream again"
            )
        if why is not None:
            self._held = why
            raise TransportError(why)

    def trip(self) -> tuple[str, str] | None:
        """(status, one line) of the first reading beyond a bound since connect (`crtraj.hardware.dynamixel._safety`:
        over-tension, slack, over-temperature, under-/over-voltage; read while the torque should be on), or None."""
        return self.trips.first

    def _miss(self, result: int) -> None:
        """Count a failed read; `max_misses` in a row end the stream, naming the first silent servo."""
        self.counts["corrupt" if result == self._sdk.COMM_RX_CORRUPT else "timeouts"] += 1
        self._misses += 1
        group = self._read_state
        self._drain()
        if self._misses < self.max_misses:
            return
        # the SDK reads the replies in id order and stops at the first bad one: its entry is the short one
        bad = next((i for i in self.bus.ids if len(group.data_dict.get(i, [])) != group.data_length), None)
        who = f"servo {self.bus.name_of(bad)}" if bad is not None else self.description
        what = "a corrupted reply" if result == self._sdk.COMM_RX_CORRUPT else "no answer"
        raise TransportError(
            f"{who}: {what} to {self._misses} sync reads in a row ({self._ph.getTxRxResult(result)}); "
            "check its cable and power"
        )

    def _drain(self, quiet: float = 0.005, most: float = 0.1) -> None:
        """After a failed read, let late replies arrive and drop them (until `quiet` s of silence, at
        most `most` s), so the next read does not take a stale reply for its own."""
        clock = self._clock
        end = clock.now() + most
        last = clock.now()
        while clock.now() < end and clock.now() - last < quiet:
            if self._bus(self._port.getBytesAvailable):
                self._bus(self._port.clearPort)
                last = clock.now()
            clock.sleep(0.0005)
        self._bus(self._port.clearPort)

    def close(self) -> None:
        """Torque off (with ``stop_torque="off"``), then close the port (idempotent; never raises for a lost
        link: the servos cannot be reached, a warning says so)."""
        if self._port is None:
            return
        try:
            if self._lost is None:
                record_last(self, self.bus.ids, self._state, self._state_path, self._warn)
            if self.stop_torque == "keep":
                log.info("%s: torque kept on (robot.stop.torque = keep)", self.description)
                if self._lost is None:  # a clean end: the servos hold; the watchdog is for a host that dies
                    self._sync1(X.BUS_WATCHDOG, 0)
                return
            silent = self._torque_off() if self._lost is None else []
            if silent:
                who = ", ".join(self.bus.name_of(i) for i in silent)
                self._warn(f"warning: torque off not confirmed by servo {who}: check it before approaching the robot")
        except LinkLostError:
            pass  # the report's one line already says the link is lost and the servos keep their last goal
        finally:
            with contextlib.suppress(*LINK_ERRORS):
                self._port.closePort()
            self._port = None


def open_dynamixel(url: str, actuators: Actuators, **kw: Any) -> DynamixelTransport:
    """`DynamixelTransport` of ``dynamixel:///dev/PORT[?baud=N]`` for `actuators` (bound to the robot)."""
    device, baud = parse_url(url)
    return DynamixelTransport(device, baud, actuators, **kw)
