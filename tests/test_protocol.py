"""Wire protocol: frame layout, CRC, COBS byte-stream framing and the transports' framing."""

from __future__ import annotations

import contextlib
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.core.errors import InputError
from crtraj.hardware.protocol import (
    ESTOP,
    HOLD,
    MOVE,
    PING,
    Frame,
    FrameError,
    StreamDecoder,
    Telemetry,
    cobs_decode,
    cobs_encode,
    read_stream_file,
    seq_after,
    seq_distance,
    seq_next,
    stream_encode,
)
from crtraj.hardware.transport import Transport, TransportError, parse_hostport

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
values = st.lists(finite, min_size=0, max_size=16).map(np.array)


@given(st.sampled_from([MOVE, HOLD, ESTOP]), st.integers(0, 2**32 - 1), finite, values, st.integers(0, 2**32 - 1))
def test_frame_round_trip(kind, seq, stamp, v, session):
    f = Frame.decode(Frame(kind, seq, stamp, v, session).encode())
    assert isinstance(f, Frame)
    assert (f.kind, f.seq, f.stamp, f.session) == (kind, seq, stamp, session)
    np.testing.assert_array_equal(f.values, v)


def test_layout_matches_the_documented_bytes():
    v = np.array([0.5, -1.25, 3.0])
    data = Frame(MOVE, 7, 1.5, v, 0xA1B2C3D4).encode()
    assert len(data) == 22 + 8 * 3 + 4
    assert data[:2] == b"CR" and data[2] == 2 and data[3] == MOVE
    assert struct.unpack_from("<HIId", data, 4) == (3, 0xA1B2C3D4, 7, 1.5)
    assert struct.unpack_from("<3d", data, 22) == (0.5, -1.25, 3.0)
    assert struct.unpack_from("<I", data, len(data) - 4)[0] == zlib.crc32(data[:-4])
    tel = Telemetry(3, 0.5, 7, 16, np.array([1.0]), 1, 2, 3, 4, 5, 6, session=9).encode()
    assert len(tel) == 22 + 32 + 8 + 4
    assert struct.unpack_from("<IHHIIIIII", tel, 22) == (7, 16, 0, 1, 2, 3, 4, 5, 6)
    assert struct.unpack_from("<d", tel, 54) == (1.0,)


def test_serial_number_arithmetic_wraps_around():
    # RFC 1982 with 32 bits: 0 follows 0xFFFFFFFF, and "newer" means less than half the circle ahead
    assert seq_after(0, 0xFFFFFFFF) and seq_after(5, 0xFFFFFFF0) and not seq_after(0xFFFFFFFF, 0)
    assert not seq_after(7, 7)
    assert seq_after(2**31 - 1, 0) and not seq_after(2**31, 0) and not seq_after(2**31 + 1, 0)
    assert seq_next(0xFFFFFFFF) == 0 and seq_next(0xFFFFFFFE, 3) == 1
    assert seq_distance(1, 0xFFFFFFFF) == 2 and seq_distance(0xFFFFFFFF, 0) == 2**32 - 1


@given(
    st.integers(0, 2**32 - 1),
    st.integers(0, 2**32 - 1),
    st.integers(0, 0xFFFF),
    st.lists(st.integers(0, 2**32 - 1), min_size=6, max_size=6),
    values,
)
def test_telemetry_round_trip(seq, ack, status, counters, p):
    t = Telemetry(seq, 2.5, ack, status, p, *counters, session=seq ^ 0x5A5A5A5A)
    back = Frame.decode(t.encode())
    assert isinstance(back, Telemetry)
    assert (back.seq, back.ack, back.status, back.session) == (seq, ack, status, seq ^ 0x5A5A5A5A)
    assert list(back.counters().values()) == counters
    np.testing.assert_array_equal(back.positions, p)


@settings(max_examples=300)
@given(st.data())
def test_any_one_to_three_bit_flips_are_detected(data):
    v = data.draw(st.lists(finite, min_size=1, max_size=8).map(np.array))
    frame = bytearray(Frame(MOVE, data.draw(st.integers(1, 10**6)), 0.25, v).encode())
    bits = data.draw(st.sets(st.integers(0, len(frame) * 8 - 1), min_size=1, max_size=3))
    for b in bits:
        frame[b // 8] ^= 1 << (b % 8)
    with pytest.raises(FrameError):
        Frame.decode(bytes(frame))


def _reseal(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def test_malformed_frames_name_the_problem():
    good = Frame(MOVE, 1, 0.0, np.array([1.0, 2.0])).encode()
    with pytest.raises(FrameError, match="too short"):
        Frame.decode(good[:10])
    with pytest.raises(FrameError, match="CRC"):
        Frame.decode(good[:-5] + good[-4:])
    with pytest.raises(FrameError, match="magic"):
        Frame.decode(_reseal(b"XX" + good[2:-4]))
    with pytest.raises(FrameError, match="version 9"):
        Frame.decode(_reseal(good[:2] + b"\x09" + good[3:-4]))
    with pytest.raises(FrameError, match="kind 77"):
        Frame.decode(_reseal(good[:3] + b"\x4d" + good[4:-4]))
    with pytest.raises(FrameError, match="length mismatch"):
        Frame.decode(_reseal(good[:-4] + b"\x00" * 8))
    nan_body = bytearray(good[:-4])
    nan_body[22:30] = struct.pack("<d", float("nan"))
    with pytest.raises(FrameError, match="non-finite value"):
        Frame.decode(_reseal(bytes(nan_body)))
    with pytest.raises(FrameError, match="too many values"):
        Frame.decode(_reseal(good[:4] + struct.pack("<H", 1025) + good[6:-4]))
    with pytest.raises(FrameError, match="too long"):
        Frame.decode(bytes(70000))
    ping = Frame.decode(Frame.ping(77, 5, 0.01).encode())
    assert (ping.kind, ping.session, ping.seq, ping.values.tolist()) == (PING, 77, 5, [0.01])
    for bad_period in ([], [0.0], [11.0], [0.01, 0.01]):
        with pytest.raises(FrameError, match="PING must carry one period"):
            Frame.decode(Frame(PING, 0, 0.0, np.array(bad_period), 77).encode())


@pytest.mark.parametrize(
    ("raw", "encoded"),
    [
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"", b"\x01"),
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
        (b"\x00" + bytes(range(1, 255)), b"\x01\xff" + bytes(range(1, 255))),
        (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
        (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    ],
)
def test_cobs_known_vectors(raw, encoded):
    # vectors from Cheshire & Baker's COBS paper / the Wikipedia examples
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


@given(st.binary(max_size=1200))
def test_cobs_round_trip_has_no_zero(data):
    enc = cobs_encode(data)
    assert 0 not in enc
    assert cobs_decode(enc) == data
    assert len(enc) <= len(data) + len(data) // 254 + 1


def test_stream_decoder_resynchronises_and_handles_splits():
    frames = [Frame(MOVE, i, i * 0.01, np.array([i, -i], dtype=float)).encode() for i in range(1, 6)]
    stream = b"".join(stream_encode(f) for f in frames)
    damaged = stream_encode(frames[0])[:-1][:7] + b"\x00"  # a truncated frame, then the delimiter
    data = b"\x05garbage\x00" + damaged + stream
    dec = StreamDecoder()
    out = []
    for i in range(0, len(data), 7):  # arbitrary chunking, as a serial port delivers bytes
        out += dec.feed(data[i : i + 7])
    decoded = []
    for b in out:
        with contextlib.suppress(FrameError):
            decoded.append(Frame.decode(b))
    assert [f.seq for f in decoded] == [1, 2, 3, 4, 5]
    assert read_stream_file(stream)[4].seq == 5


def test_serial_transport_over_pyserial_loopback():
    with Transport.open("serial://loop://?baud=57600") as tr:
        assert tr.has_telemetry
        sent = [Frame(MOVE, i, 0.01 * i, np.full(7, 0.1 * i)).encode() for i in range(1, 30)]
        for f in sent:
            tr.send(f)
        got = tr.receive()
        assert got == sent


def test_file_transport_records_the_byte_stream(tmp_path):
    path = tmp_path / "frames.bin"
    tr = Transport.open(f"file://{path}")
    assert not tr.has_telemetry
    frames = [Frame(HOLD, i, 0.0, np.arange(3.0)) for i in range(1, 4)]
    for f in frames:
        tr.send(f.encode())
    assert tr.receive() == []
    tr.close()
    back = read_stream_file(path.read_bytes())
    assert [f.seq for f in back] == [1, 2, 3]
    with pytest.raises(TransportError):
        tr.send(frames[0].encode())


def test_transport_url_and_address_errors():
    with pytest.raises(InputError, match="unknown scheme"):
        Transport.open("tcp://127.0.0.1:5")
    with pytest.raises(InputError, match="--udp: expected HOST:PORT"):
        parse_hostport("localhost", "--udp")
    with pytest.raises(InputError, match="port must be an integer"):
        parse_hostport("127.0.0.1:abc", "--udp")
    with pytest.raises(InputError, match=r"port must be in 0\.\.65535"):
        parse_hostport("127.0.0.1:70000", "--udp")
    with pytest.raises(TransportError):
        Transport.open("serial:///dev/does-not-exist-crtraj")
