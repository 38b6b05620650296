"""Wire protocol between the streamer and a device (docs/protocol.md is the reference).

Every frame is little-endian::

    magic "CR" | version u8 = 2 | kind u8 | n u16 | session u32 | seq u32 | stamp f64 | body | crc u32

``body`` of a set-point frame (MOVE, HOLD, ESTOP) is ``n`` f64 actuator values
(rad for servos, mm for the z stage); a PING carries one value, the host's
frame period (s). A TELEMETRY frame (device -> host) carries ``ack u32 |
status u16 | reserved u16 | crc_errors u32 | missed u32 | stale u32 |
refused u32 | foreign u32 | limited u32`` then ``n`` f64 measured positions.
``crc`` is CRC-32 (zlib/IEEE 802.3) of every byte before it.

``session`` is a random non-zero number the host draws per run and opens
with a PING; a device acts only on frames of its current session.
Sequence numbers are compared with serial-number arithmetic (RFC 1982,
32 bits), so they wrap around, and a frame more than `SEQ_WINDOW` ahead of
the last applied one is rejected, so no single frame can lock a session out.

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
VERSION = 2

MOVE = 1  # follow these set-points
HOLD = 2  # hold these positions (the last commanded ones): braking command
ESTOP = 3  # emergency stop: the device freezes and latches until restarted
PING = 4  # one value, the host's frame period (s): opens a session
TELEMETRY = 16  # device -> host

KIND_NAMES = MappingProxyType({MOVE: "move", HOLD: "hold", ESTOP: "estop", PING: "ping", TELEMETRY: "telemetry"})

# Device status bits in telemetry frames.
STATUS_HOLDING = 1  # last applied command was HOLD (or no command yet)
STATUS_ESTOP = 2  # e-stop latched
STATUS_LINK_LOST = 4  # no valid set-point within the device's own timeout
STATUS_REFUSED = 8  # the device refused an out-of-limit set-point (it then holds)
STATUS_LIMITED = 16  # a set-point needed more than a velocity/acceleration limit (the servo limited it)

_HEAD = struct.Struct("<2sBBHIId")  # 22 bytes
_TEL = struct.Struct("<IHHIIIIII")  # 32 bytes
_CRC = struct.Struct("<I")
HEADER_SIZE = _HEAD.size
MAX_VALUES = 1024
MAX_FRAME = _HEAD.size + _TEL.size + 8 * MAX_VALUES + _CRC.size

SEQ_MOD = 1 << 32
# Largest forward jump of a sequence number a device accepts (frames lost in a row):
# 65536 frames are 11 min at 100 Hz. Anything further ahead is treated as stale.
SEQ_WINDOW = 1 << 16
# PING period bounds (s): 0.1 ms .. 10 s.
PERIOD_MIN, PERIOD_MAX = 1e-4, 10.0


def seq_distance(a: int, b: int) -> int:
    """How far `a` is ahead of `b` modulo 2**32 (0 .. 2**32 - 1)."""
    return (a - b) % SEQ_MOD


def seq_after(a: int, b: int) -> bool:
    """RFC 1982 serial-number order: True when `a` is newer than `b` (a wrapped 0 follows 0xFFFFFFFF)."""
    return 0 < seq_distance(a, b) < SEQ_MOD // 2


def seq_next(a: int, step: int = 1) -> int:
    """The sequence number `step` frames after `a`, wrapping at 2**32."""
    return (a + step) % SEQ_MOD


class FrameError(ValueError):
    """A frame that failed to decode: bad CRC, magic, version, kind or length."""


def _values_bytes(values: np.ndarray) -> bytes:
    return np.ascontiguousarray(values, dtype="<f8").tobytes()


def _seal(body: bytes) -> bytes:
    return body + _CRC.pack(zlib.crc32(body) & 0xFFFFFFFF)


def _open(data: bytes) -> tuple[int, int, int, int, float, memoryview]:
    """Check length, CRC, magic and version; return (kind, n, session, seq, stamp, payload)."""
    if len(data) < _HEAD.size + _CRC.size:
        raise FrameError(f"frame too short ({len(data)} bytes)")
    if len(data) > MAX_FRAME:
        raise FrameError(f"frame too long ({len(data)} bytes, at most {MAX_FRAME})")
    body, crc = data[:-4], _CRC.unpack_from(data, len(data) - 4)[0]
    if zlib.crc32(body) & 0xFFFFFFFF != crc:
        raise FrameError("CRC mismatch")
    magic, version, kind, n, session, seq, stamp = _HEAD.unpack_from(body, 0)
    if magic != MAGIC:
        raise FrameError(f"bad magic {magic!r}")
    if version != VERSION:
        raise FrameError(f"unsupported protocol version {version}")
    if kind not in KIND_NAMES:
        raise FrameError(f"unknown frame kind {kind}")
    if n > MAX_VALUES:
        raise FrameError(f"too many values ({n}, at most {MAX_VALUES})")
    if not math.isfinite(stamp):
        raise FrameError("non-finite time stamp")
    return kind, n, session, seq, stamp, memoryview(body)[_HEAD.size :]


def _read_values(payload: memoryview, n: int) -> np.ndarray:
    if len(payload) != 8 * n:
        raise FrameError(f"length mismatch: {n} values need {8 * n} bytes, got {len(payload)}")
    v = np.frombuffer(payload, dtype="<f8").astype(float)
    if not np.all(np.isfinite(v)):
        raise FrameError("non-finite value")
    return v


@dataclass(frozen=True)
class Telemetry:
    """Device -> host: measured positions and counters. stamp: device time (s).
    session: the device's current session (0: none)."""

    seq: int
    stamp: float
    ack: int  # seq of the last applied set-point frame (the PING's seq: none yet)
    status: int
    positions: np.ndarray
    crc_errors: int = 0  # frames rejected for a bad CRC/format
    missed: int = 0  # sequence gaps (frames lost on the way)
    stale: int = 0  # frames not newer than the last applied one, or too far ahead
    refused: int = 0  # frames refused by the device's own position-limit check
    foreign: int = 0  # frames of another session (not acted on)
    limited: int = 0  # set-points that needed more than a velocity/acceleration limit
    session: int = 0

    def encode(self) -> bytes:
        p = np.asarray(self.positions, dtype=float)
        head = _HEAD.pack(
            MAGIC, VERSION, TELEMETRY, p.size, self.session % SEQ_MOD, self.seq % SEQ_MOD, float(self.stamp)
        )
        counts = (self.crc_errors, self.missed, self.stale, self.refused, self.foreign, self.limited)
        tel = _TEL.pack(self.ack % SEQ_MOD, self.status & 0xFFFF, 0, *(c % SEQ_MOD for c in counts))
        return _seal(head + tel + _values_bytes(p))

    def counters(self) -> dict[str, int]:
        return {
            "crc_errors": self.crc_errors,
            "missed": self.missed,
            "stale": self.stale,
            "refused": self.refused,
            "foreign": self.foreign,
            "limited": self.limited,
        }


@dataclass(frozen=True)
class Frame:
    """Host -> device frame. kind: MOVE, HOLD, ESTOP (set-points) or PING (one value: the host's
    frame period, s); stamp: trajectory time (s); values: actuator values (rad for servos, mm
    for the stage); session: the host's session number (non-zero)."""

    kind: int
    seq: int
    stamp: float
    values: np.ndarray = field(repr=False)
    session: int = 0

    @property
    def kind_name(self) -> str:
        return KIND_NAMES[self.kind]

    def encode(self) -> bytes:
        v = np.asarray(self.values, dtype=float)
        if self.kind not in (MOVE, HOLD, ESTOP, PING):
            raise ValueError(f"not a set-point kind: {self.kind}")
        if v.ndim != 1 or v.size > MAX_VALUES:
            raise ValueError(f"values must be a vector of at most {MAX_VALUES} numbers")
        head = _HEAD.pack(
            MAGIC, VERSION, self.kind, v.size, self.session % SEQ_MOD, self.seq % SEQ_MOD, float(self.stamp)
        )
        return _seal(head + _values_bytes(v))

    @staticmethod
    def ping(session: int, seq: int, period: float) -> Frame:
        """The PING that opens `session`: set-points follow from seq + 1, one every `period` s."""
        return Frame(PING, seq, 0.0, np.array([float(period)]), session)

    @staticmethod
    def decode(data: bytes) -> Frame | Telemetry:
        """Decode one frame of either direction; `FrameError` when it is damaged or malformed."""
        kind, n, session, seq, stamp, payload = _open(bytes(data))
        if kind == TELEMETRY:
            if len(payload) < _TEL.size:
                raise FrameError("telemetry frame too short")
            ack, status, _, *counts = _TEL.unpack_from(payload, 0)
            pos = _read_values(payload[_TEL.size :], n)
            return Telemetry(seq, stamp, ack, status, pos, *counts, session=session)
        values = _read_values(payload, n)
        if kind == PING and not (n == 1 and PERIOD_MIN <= values[0] <= PERIOD_MAX):
            raise FrameError(f"PING must carry one period in [{PERIOD_MIN:g}, {PERIOD_MAX:g}] s")
        return Frame(kind, seq, stamp, values, session)


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
