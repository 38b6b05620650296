"""Wire protocol between the streamer and a device (docs/protocol.md is the reference).

Every frame is little-endian::

    magic "CR" | version u8 = 1 | kind u8 | n u16 | seq u32 | stamp f64 | body | crc u32

``body`` of a set-point frame (MOVE, HOLD, ESTOP) is ``n`` f64 actuator values
(rad for servos, mm for the z stage). A TELEMETRY frame (device -> host)
carries ``ack u32 | status u16 | reserved u16 | crc_errors u32 | missed u32 |
stale u32 | refused u32`` then ``n`` f64 measured positions. ``crc`` is
CRC-32 (zlib/IEEE 802.3) of every byte before it.

Over UDP one datagram holds one frame. Over a byte stream (serial, dry-run
file) each frame is COBS-encoded and followed by one 0x00 delimiter, so a
receiver resynchronises at the next zero after any corruption.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

MAGIC = b"CR"
VERSION = 1

MOVE = 1  # follow these set-points
HOLD = 2  # hold these positions (the last commanded ones): braking command
ESTOP = 3  # emergency stop: the device freezes and latches until restarted
PING = 4  # no values: opens a session (telemetry goes to the sender; sequence numbers restart)
TELEMETRY = 16  # device -> host

KIND_NAMES = MappingProxyType({MOVE: "move", HOLD: "hold", ESTOP: "estop", PING: "ping", TELEMETRY: "telemetry"})

# Device status bits in telemetry frames.
STATUS_HOLDING = 1  # last applied command was HOLD (or no command yet)
STATUS_ESTOP = 2  # e-stop latched
STATUS_LINK_LOST = 4  # no valid set-point within the device's own timeout
STATUS_REFUSED = 8  # the device refused an out-of-limit set-point (it then holds)

_HEAD = struct.Struct("<2sBBHId")  # 18 bytes
_TEL = struct.Struct("<IHHIIII")  # 24 bytes
_CRC = struct.Struct("<I")
MAX_VALUES = 1024


class FrameError(ValueError):
    """A frame that failed to decode: bad CRC, magic, version, kind or length."""


def _values_bytes(values: np.ndarray) -> bytes:
    return np.ascontiguousarray(values, dtype="<f8").tobytes()


def _seal(body: bytes) -> bytes:
    return body + _CRC.pack(zlib.crc32(body) & 0xFFFFFFFF)


def _open(data: bytes) -> tuple[int, int, int, float, memoryview]:
    """Check length, CRC, magic and version; return (kind, n, seq, stamp, payload)."""
    if len(data) < _HEAD.size + _CRC.size:
        raise FrameError(f"frame too short ({len(data)} bytes)")
    body, crc = data[:-4], _CRC.unpack_from(data, len(data) - 4)[0]
    if zlib.crc32(body) & 0xFFFFFFFF != crc:
        raise FrameError("CRC mismatch")
    magic, version, kind, n, seq, stamp = _HEAD.unpack_from(body, 0)
    if magic != MAGIC:
        raise FrameError(f"bad magic {magic!r}")
    if version != VERSION:
        raise FrameError(f"unsupported protocol version {version}")
    if kind not in KIND_NAMES:
        raise FrameError(f"unknown frame kind {kind}")
    if not math.isfinite(stamp):
        raise FrameError("non-finite time stamp")
    return kind, n, seq, stamp, memoryview(body)[_HEAD.size :]


def _read_values(payload: memoryview, n: int) -> np.ndarray:
    if len(payload) != 8 * n:
        raise FrameError(f"length mismatch: {n} values need {8 * n} bytes, got {len(payload)}")
    v = np.frombuffer(payload, dtype="<f8").astype(float)
    if not np.all(np.isfinite(v)):
        raise FrameError("non-finite value")
    return v


@dataclass(frozen=True)
class Telemetry:
    """Device -> host: measured positions and counters. stamp: device time (s)."""

    seq: int
    stamp: float
    ack: int  # seq of the last applied set-point frame (0: none yet)
    status: int
    positions: np.ndarray
    crc_errors: int = 0  # frames rejected for a bad CRC/format
    missed: int = 0  # sequence gaps (frames lost on the way)
    stale: int = 0  # frames older than one already applied (reordered/duplicated)
    refused: int = 0  # frames refused by the device's own limit check

    def encode(self) -> bytes:
        p = np.asarray(self.positions, dtype=float)
        head = _HEAD.pack(MAGIC, VERSION, TELEMETRY, p.size, self.seq & 0xFFFFFFFF, float(self.stamp))
        tel = _TEL.pack(
            self.ack & 0xFFFFFFFF,
            self.status & 0xFFFF,
            0,
            self.crc_errors & 0xFFFFFFFF,
            self.missed & 0xFFFFFFFF,
            self.stale & 0xFFFFFFFF,
            self.refused & 0xFFFFFFFF,
        )
        return _seal(head + tel + _values_bytes(p))

    def counters(self) -> dict[str, int]:
        return {"crc_errors": self.crc_errors, "missed": self.missed, "stale": self.stale, "refused": self.refused}


@dataclass(frozen=True)
class Frame:
    """Host -> device frame. kind: MOVE, HOLD, ESTOP (set-points) or PING (no values);
    stamp: trajectory time (s); values: actuator values (rad for servos, mm for the stage)."""

    kind: int
    seq: int
    stamp: float
    values: np.ndarray = field(repr=False)

    @property
    def kind_name(self) -> str:
        return KIND_NAMES[self.kind]

    def encode(self) -> bytes:
        v = np.asarray(self.values, dtype=float)
        if self.kind not in (MOVE, HOLD, ESTOP, PING):
            raise ValueError(f"not a set-point kind: {self.kind}")
        if v.ndim != 1 or v.size > MAX_VALUES:
            raise ValueError(f"values must be a vector of at most {MAX_VALUES} numbers")
        head = _HEAD.pack(MAGIC, VERSION, self.kind, v.size, self.seq & 0xFFFFFFFF, float(self.stamp))
        return _seal(head + _values_bytes(v))

    @staticmethod
    def decode(data: bytes) -> Frame | Telemetry:
        """Decode one frame of either direction; `FrameError` when it is damaged or malformed."""
        kind, n, seq, stamp, payload = _open(bytes(data))
        if kind == TELEMETRY:
            if len(payload) < _TEL.size:
                raise FrameError("telemetry frame too short")
            ack, status, _, crc_e, missed, stale, refused = _TEL.unpack_from(payload, 0)
            pos = _read_values(payload[_TEL.size :], n)
            return Telemetry(seq, stamp, ack, status, pos, crc_e, missed, stale, refused)
        return Frame(kind, seq, stamp, _read_values(payload, n))


# ------------------------------------------------------------ byte streams
def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result has no zero byte (delimiter not included)."""
    out = bytearray()
    chunks = bytes(data).split(b"\x00")
    for j, chunk in enumerate(chunks):
        # a run of non-zero bytes becomes blocks of at most 254 bytes with code = len + 1;
        # a full block (0xFF) implies no zero after it
        full = False
        while len(chunk) >= 254:
            out.append(0xFF)
            out += chunk[:254]
            chunk = chunk[254:]
            full = True
        if full and not chunk and j == len(chunks) - 1:
            break  # canonical COBS: no empty block after a final full block
        out.append(len(chunk) + 1)
        out += chunk
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of `cobs_encode`; `FrameError` on malformed input."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise FrameError("COBS: zero byte inside a frame")
        end = i + code
        if end > n:
            raise FrameError("COBS: truncated block")
        block = data[i + 1 : end]
        if 0 in block:
            raise FrameError("COBS: zero byte inside a frame")
        out += block
        i = end
        if code < 0xFF and i < n:
            out.append(0)
    return bytes(out)


def stream_encode(frame_bytes: bytes) -> bytes:
    """One frame as it goes over a byte stream: COBS + 0x00 delimiter."""
    return cobs_encode(frame_bytes) + b"\x00"


class StreamDecoder:
    """Split a byte stream into frames at 0x00 delimiters (COBS), resynchronising after damage."""

    def __init__(self, max_frame: int = 64 * 1024) -> None:
        self._buf = bytearray()
        self._max = max_frame
        self.errors = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the complete decoded frame payloads (damaged ones are counted and skipped)."""
        self._buf += data
        out: list[bytes] = []
        while True:
            j = self._buf.find(0)
            if j < 0:
                if len(self._buf) > self._max:  # never a frame: drop until the next delimiter
                    self._buf.clear()
                    self.errors += 1
                return out
            chunk = bytes(self._buf[:j])
            del self._buf[: j + 1]
            if not chunk:
                continue
            try:
                out.append(cobs_decode(chunk))
            except FrameError:
                self.errors += 1


def read_stream_file(data: bytes) -> list[Frame | Telemetry]:
    """Decode every frame of a recorded byte stream (e.g. a dry-run file)."""
    dec = StreamDecoder(max_frame=len(data) + 1)
    return [Frame.decode(b) for b in dec.feed(data)]
