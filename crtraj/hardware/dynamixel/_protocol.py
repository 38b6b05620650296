"""Dynamixel Protocol 2.0 packets, written from the public protocol description (not from the SDK).

An instruction or status packet is::

    FF FF FD 00 | id | length (u16 LE) | instruction | params ... | crc (u16 LE)

``length`` counts the bytes after it: instruction, params (after byte stuffing)
and the two CRC bytes. A status packet's instruction is 0x55 and its first
parameter is the error byte. The CRC is CRC-16 with polynomial 0x8005,
initial value 0, no reflection, no final XOR (CRC-16/BUYPASS), over every
byte before it. Byte stuffing: inside instruction and params, every
``FF FF FD`` is followed by an extra ``FD``, so the header never appears in a
packet body.

The crtraj side talks to servos through the official SDK
(`crtraj.hardware.dynamixel._link`); this module serves the servo simulator
(`crtraj.hardware.dynamixel._sim_chain`) and the tests, and holds the X-series
control table addresses both use. Every incoming byte is hostile:
`PacketReader` bounds the buffer and the packet length, drops packets with a
bad CRC and resynchronises at the next header.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from types import MappingProxyType

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 252

# Instructions.
PING, READ, WRITE, REBOOT, STATUS, SYNC_READ, SYNC_WRITE = 0x01, 0x02, 0x03, 0x08, 0x55, 0x82, 0x83
CLEAR = 0x10  # with CLEAR_MULTI_TURN: the present position back within one turn (torque off only)
CLEAR_MULTI_TURN = bytes([0x01, 0x44, 0x58, 0x4C, 0x22])  # 0x01 then "DXL\"" (Protocol 2.0, Clear instruction)

# Status packet error byte: bit 7 = alert (a hardware error is set), bits 0..6 = the error number.
ERR_ALERT = 0x80
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = range(1, 8)

# Hardware error status (address 70) bits, X-series.
HW_INPUT_VOLTAGE, HW_OVERHEATING, HW_ENCODER, HW_SHOCK, HW_OVERLOAD = 0x01, 0x04, 0x08, 0x10, 0x20
HW_ERROR_NAMES = (
    (HW_INPUT_VOLTAGE, "input voltage"),
    (HW_OVERHEATING, "overheating"),
    (HW_ENCODER, "motor encoder"),
    (HW_SHOCK, "electrical shock"),
    (HW_OVERLOAD, "overload"),
)


class X:
    """X-series control table addresses (bytes) and sizes, from the XM430 e-manual."""

    MODEL_NUMBER = 0  # 2, read-only
    MODEL_INFORMATION = 2  # 4, read-only (the X-series has no serial-number register)
    FIRMWARE = 6  # 1
    ID = 7  # 1
    BAUD_RATE = 8  # 1
    RETURN_DELAY = 9  # 1, 2 us units (factory default 250: 500 us before every reply)
    DRIVE_MODE = 10  # 1: bit 0 reverse direction, bit 2 time-based profile, bit 3 torque on by goal update
    OPERATING_MODE = 11  # 1: 3 position, 4 extended position, 5 current-based position
    HOMING_OFFSET = 20  # 4, signed ticks added to the present position (EEPROM)
    HOMING_OFFSET_LIMIT = 1_044_479  # ticks, +- (the register's range)
    CURRENT_LIMIT = 38  # 2, 2.69 mA units (EEPROM)
    TORQUE_ENABLE = 64  # 1; EEPROM (< 64) is writable only with torque off
    LED = 65  # 1, RAM (power-up default 0): crtraj's "homed since power-up" marker
    STATUS_RETURN = 68  # 1, RAM: 0 answer PING only, 1 PING and READ, 2 every instruction
    BUS_WATCHDOG = 98  # 1, RAM: 0 off (clears the error), 1..127 on (20 ms units, torque on only), -1 (0xFF) tripped
    HARDWARE_ERROR = 70  # 1, read-only
    GOAL_PWM = 100  # 2: the first goal value (read-only after a Bus Watchdog stop)
    GOAL_CURRENT = 102  # 2, 2.69 mA units (current-based position mode)
    PROFILE_ACCELERATION = 108  # 4, 214.577 rev/min^2 units
    PROFILE_VELOCITY = 112  # 4, 0.229 rev/min units
    GOAL_POSITION = 116  # 4, ticks
    MOVING = 122  # 1
    PRESENT_CURRENT = 126  # 2, signed, 2.69 mA units
    PRESENT_VELOCITY = 128  # 4, signed, 0.229 rev/min units
    PRESENT_POSITION = 132  # 4, signed, ticks
    PRESENT_VOLTAGE = 144  # 2, 0.1 V
    PRESENT_TEMPERATURE = 146  # 1, deg C
    INDIRECT_ADDRESS = 168  # 28 x 2: the address each indirect data byte mirrors (writable with torque off)
    INDIRECT_DATA = 224  # 28 x 1: the bytes the indirect addresses name, so one read gets scattered fields
    INDIRECT_COUNT = 28
    SIZE = 252  # bytes of control table the simulator keeps

    POSITION = 3  # position control (single turn: switching to it, or torque on in it, loses the turn count)
    EXTENDED_POSITION = 4
    CURRENT_POSITION = 5  # current-based position control (multi-turn, current limited by the goal current)
    DRIVE_REVERSE, DRIVE_TIME_PROFILE, DRIVE_TORQUE_ON_GOAL = 0x01, 0x04, 0x08
    RETURN_DELAY_DEFAULT = 250  # factory default (x 2 us)
    CURRENT_UNIT = 2.69  # mA per unit of goal / present current
    CURRENT_LIMIT_DEFAULT = 1193  # units (3.2 A), XM430
    # extended position control: goal position range, ticks (+-256 revolutions)
    EXTENDED_LIMIT = 1_048_575
    WATCHDOG_UNIT = 0.020  # s per unit of Bus Watchdog
    WATCHDOG_TRIPPED = 0xFF  # Bus Watchdog reads -1 after it stopped the servo
    VELOCITY_UNIT = 0.229  # rev/min per unit of profile / present velocity
    ACCELERATION_UNIT = 214.577  # rev/min^2 per unit of profile acceleration


# Dynamixel baud rate register (address 8) values.
BAUD_CODES = MappingProxyType({0: 9600, 1: 57600, 2: 115200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000})

# Largest packet the reader accepts (bytes, header to CRC): a sync write to every id of 4 bytes each is
# 4 + 3 + 1 + 4 + 253 * 5 + 2 = 1279 bytes before stuffing.
MAX_PACKET = 2048


def _crc_byte(i: int) -> int:
    """CRC-16 (polynomial 0x8005, MSB first) of the byte `i` alone: one entry of the lookup table."""
    crc = i << 8
    for _ in range(8):
        crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
    return crc & 0xFFFF


_CRC_TABLE = tuple(_crc_byte(i) for i in range(256))


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0: polynomial 0x8005, initial 0, MSB first, no final XOR (table driven)."""
    table = _CRC_TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ b]
    return crc


def stuff(body: bytes) -> bytes:
    """Insert 0xFD after every FF FF FD in `body` (instruction and params). The inserted FD cannot start
    a new FF FF FD, so replacing every occurrence at once is the byte-by-byte rule."""
    return bytes(body).replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    """Remove the 0xFD inserted after every FF FF FD (the inverse of `stuff`)."""
    return bytes(body).replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def encode(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One packet (instruction or status) with stuffing and CRC."""
    if not 0 <= dxl_id <= 0xFE:
        raise ValueError(f"id must be in 0..254, got {dxl_id}")
    body = stuff(bytes([instruction]) + bytes(params))
    head = HEADER + struct.pack("<BH", dxl_id, len(body) + 2)
    packet = head + body
    return packet + struct.pack("<H", crc16(packet))


def status(dxl_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A status packet: instruction 0x55, then the error byte and the params."""
    return encode(dxl_id, STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    """A decoded packet: id, instruction and unstuffed params (a status packet's params start with its error)."""

    id: int
    instruction: int
    params: bytes
    size: int = 0  # bytes on the wire, header to CRC


class PacketReader:
    """Collects bytes from a hostile stream and yields the packets with a valid CRC.

    Bytes before a header are discarded; a length over `MAX_PACKET` or below
    3, or a bad CRC, drops that header and resynchronises at the next one.
    The buffer never holds more than `MAX_PACKET` bytes of one incomplete packet.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.bad_crc = 0
        self.bad_length = 0
        self.discarded = 0

    def feed(self, data: bytes) -> list[Packet]:
        self._buf.extend(data)
        out: list[Packet] = []
        while True:
            i = self._buf.find(HEADER)
            if i < 0:
                keep = 3  # a header may straddle two reads
                self.discarded += max(0, len(self._buf) - keep)
                del self._buf[: max(0, len(self._buf) - keep)]
                return out
            if i:
                self.discarded += i
                del self._buf[:i]
            if len(self._buf) < 7:
                return out
            dxl_id, length = struct.unpack_from("<BH", self._buf, 4)
            if length < 3 or 7 + length > MAX_PACKET:
                self.bad_length += 1
                del self._buf[:1]
                continue
            if len(self._buf) < 7 + length:
                return out
            packet = bytes(self._buf[: 7 + length])
            (crc,) = struct.unpack_from("<H", packet, len(packet) - 2)
            if crc16(packet[:-2]) != crc:
                self.bad_crc += 1
                del self._buf[:1]
                continue
            del self._buf[: len(packet)]
            body = unstuff(packet[7:-2])
            out.append(Packet(dxl_id, body[0], body[1:], len(packet)))


def hardware_error_text(bits: int) -> str:
    """The hardware error status bits by name (``overload, overheating``), or the raw value."""
    names = [name for bit, name in HW_ERROR_NAMES if bits & bit]
    return ", ".join(names) if names else f"0x{bits:02x}"
