"""The simulated device: rate/acceleration-limited servos, sessions and sequence numbers, hostile input, faults.

Most tests drive `DeviceCore` directly on a virtual clock (device time in s); a few go over UDP."""

from __future__ import annotations

import socket
import struct
import time
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import (
    ESTOP,
    HOLD,
    MOVE,
    PING,
    SEQ_WINDOW,
    STATUS_ESTOP,
    STATUS_LIMITED,
    STATUS_LINK_LOST,
    STATUS_REFUSED,
    Frame,
    FrameError,
    Telemetry,
)
from crtraj.hardware.sim._device import Faults, SimDevice
from crtraj.hardware.sim._device_core import DeviceCore

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def acts(robot):
    return Actuators.from_robot(robot)


class Host:
    """A bare UDP peer speaking the protocol by hand (independent of the Streamer)."""

    def __init__(self, dev: SimDevice, session: int = 1) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.5)
        self.addr = dev.address
        self.session = session

    def send(self, kind: int, seq: int, values, stamp: float = 0.0) -> None:
        f = Frame.ping(self.session, seq, 0.01) if kind == PING else Frame(kind, seq, stamp, values, self.session)
        self.sock.sendto(f.encode(), self.addr)

    def raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.addr)

    def telemetry(self, timeout: float = 1.0) -> Telemetry:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            try:
                msg = Frame.decode(data)
            except FrameError:
                continue
            if isinstance(msg, Telemetry):
                return msg
        raise AssertionError("no telemetry")

    def wait_for(self, pred, timeout: float = 2.0) -> Telemetry:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            t = self.telemetry()
            if pred(t):
                return t
        raise AssertionError("condition not reached")

    def close(self) -> None:
        self.sock.close()


def trapezoid(D: float, vmax: float, amax: float, t: np.ndarray) -> np.ndarray:
    """Independent closed form: distance covered at time t by a rest-to-rest move of length D >= 0."""
    if D * amax >= vmax * vmax:  # reaches full speed: accelerate, cruise, brake
        ta, T = vmax / amax, D / vmax + vmax / amax
        return np.where(
            t < ta,
            0.5 * amax * t**2,
            np.where(t < T - ta, 0.5 * vmax * ta + vmax * (t - ta), D - 0.5 * amax * np.clip(T - t, 0, None) ** 2),
        )
    ta = np.sqrt(D / amax)  # triangular
    return np.where(t < ta, 0.5 * amax * t**2, D - 0.5 * amax * np.clip(2 * ta - t, 0, None) ** 2)


def open_session(core: DeviceCore, session: int = 7, seq: int = 0, now: float = 0.0, period: float = 0.01) -> None:
    assert core.handle(Frame.ping(session, seq, period).encode(), now)


def sample(core: DeviceCore, times: np.ndarray) -> np.ndarray:
    out = []
    for t in times:
        core.advance(t)
        out.append(core.state()["positions"])
    return np.array(out)


def test_step_command_moves_on_the_trapezoidal_profile_and_is_flagged(acts):
    """A 0 -> 95 mm z jump (and servo jumps) is not applied at once: each axis follows the time-optimal
    profile at its velocity and acceleration limits, and the step is reported as a limit violation."""
    core = DeviceCore(acts, tau=0.0)
    open_session(core)
    target = acts.zero_offset.copy()
    target[0] += 0.3  # triangular (never reaches 5 rad/s)
    target[1] -= 2.0  # trapezoidal, backwards
    target[-1] += 95.0  # the z jump: 4.95 s at 20 mm/s, 100 mm/s^2
    assert core.handle(Frame(MOVE, 1, 0.0, target, 7).encode(), 0.0)
    times = np.linspace(0.0, 5.2, 2601)
    X = sample(core, times)
    for i in (0, 1, 6):
        D = abs(target[i] - acts.zero_offset[i])
        expect = acts.zero_offset[i] + np.sign(target[i] - acts.zero_offset[i]) * trapezoid(
            D, acts.vmax[i], acts.amax[i], times
        )
        np.testing.assert_allclose(X[:, i], expect, atol=1e-9, err_msg=acts.names[i])
    # arrival time of z: 95 / 20 + 20 / 100 = 4.95 s
    z = X[:, -1]
    assert z[times <= 4.94].max() < 95.0 - 1e-4 and np.all(z[times >= 4.95] == 95.0)
    # finite differences of the measured motion stay within the limits
    dt = times[1] - times[0]
    V = np.diff(X, axis=0) / dt
    A = np.diff(V, axis=0) / dt
    assert np.all(np.abs(V) <= acts.vmax * (1 + 1e-9))
    assert np.all(np.abs(A) <= acts.amax * (1 + 1e-6) + 1e-6)
    # reported: counter, sticky status bit, and the violation itself (95 mm in one 10 ms period)
    tel = core.telemetry(5.2)
    assert tel.limited == 1 and tel.status & STATUS_LIMITED
    v = core.violations[0]
    assert (v.seq, v.quantity) == (1, "velocity") and v.actuator in ("s1c1", "s1c2", "z")
    assert core.state()["applied"] == 1


def test_retargeting_while_moving_never_exceeds_the_limits_and_arrives(acts):
    """Random new targets at random times (a seeded generator): the motion stays within velocity and
    acceleration limits (finite differences) and ends exactly at the last target, no later than a
    rest-to-rest move from the farthest point would take plus the time to brake first."""
    rng = np.random.default_rng(3)
    core = DeviceCore(acts, tau=0.0)
    open_session(core)
    t, dt = 0.0, 0.001
    X = [core.state()["positions"]]
    for seq in range(1, 26):
        target = rng.uniform(acts.lower, acts.upper)
        core.handle(Frame(MOVE, seq, t, target, 7).encode(), t)
        for _ in range(int(rng.integers(5, 200))):
            t += dt
            core.advance(t)
            X.append(core.state()["positions"])
    X = np.array(X)
    V = np.diff(X, axis=0) / dt
    A = np.diff(V, axis=0) / dt
    assert np.all(np.abs(V) <= acts.vmax * (1 + 1e-9))
    assert np.all(np.abs(A) <= acts.amax * (1 + 1e-6) + 1e-6)
    st_ = core.state()
    span = acts.upper - acts.lower
    t_brake = acts.vmax / acts.amax
    bound = float(np.max(span / acts.vmax + acts.vmax / acts.amax + 2 * t_brake))
    core.advance(t + bound)
    np.testing.assert_array_equal(core.state()["positions"], st_["target"])
    assert core.counts["limited"] >= 20  # random jumps across the whole range need more than the limits


def test_motor_lag_follows_a_ramp_tau_v_behind(acts):
    """With a motor time constant tau, the measured position trails the (ramp) reference by tau * v
    once the transient has decayed (the steady state of tau x' = r - x for r = v t)."""
    tau = 0.05
    core = DeviceCore(acts, tau=tau)
    open_session(core)
    target = acts.zero_offset.copy()
    target[-1] += 60.0
    core.handle(Frame(MOVE, 1, 0.0, target, 7).encode(), 0.0)
    for t in np.arange(0.8, 2.5, 0.1):  # cruise at 20 mm/s from 0.2 s to 3.0 s; e^(-0.6/0.05) ~ 6e-6
        core.advance(t)
        s = core.state()
        assert s["velocity"][-1] == pytest.approx(20.0)
        assert s["reference"][-1] - s["positions"][-1] == pytest.approx(tau * 20.0, abs=1e-4)


def test_estop_brakes_at_the_acceleration_limit(acts):
    core = DeviceCore(acts, tau=0.0)
    open_session(core)
    target = acts.zero_offset.copy()
    target[-1] += 90.0
    core.handle(Frame(MOVE, 1, 0.0, target, 7).encode(), 0.0)
    core.advance(1.0)  # cruising at 20 mm/s, at 20 * 1.0 - 2 = 18 mm
    assert core.state()["positions"][-1] == pytest.approx(18.0)
    core.handle(Frame(ESTOP, 2, 0.0, target, 7).encode(), 1.0)
    core.handle(Frame(MOVE, 3, 0.0, acts.zero_offset, 7).encode(), 1.05)  # ignored: latched
    core.advance(3.0)
    s = core.state()
    assert s["positions"][-1] == pytest.approx(18.0 + 20.0**2 / (2 * 100.0))  # braking distance v^2 / 2a
    assert s["status"] & STATUS_ESTOP and [a.seq for a in core.applied] == [1, 2]


def test_crc_sequence_limits_and_link_lost(acts):
    core = DeviceCore(acts, tau=0.01, link_timeout=0.25)
    open_session(core)
    v1 = np.full(7, 0.1)
    good = Frame(MOVE, 1, 0.0, v1, 7).encode()
    bad = bytearray(good)
    bad[20] ^= 0x10
    assert not core.handle(bytes(bad), 0.0)  # corrupted: never applied
    core.handle(Frame(MOVE, 5, 0.0, v1, 7).encode(), 0.01)  # seq gap of 4 (1..4 missing)
    core.handle(Frame(MOVE, 3, 0.0, np.full(7, 0.9), 7).encode(), 0.02)  # older than 5: stale
    core.handle(Frame(MOVE, 6, 0.0, np.array([2.5, 0, 0, 0, 0, 0, 0]), 7).encode(), 0.03)  # refused
    t = core.telemetry(0.04)
    assert (t.crc_errors, t.missed, t.stale, t.refused, t.ack) == (1, 4, 1, 1, 6)
    assert t.status & STATUS_REFUSED and t.session == 7
    assert [a.seq for a in core.applied] == [5]
    np.testing.assert_array_equal(core.state()["target"], v1)
    assert not core.telemetry(0.2).status & STATUS_LINK_LOST
    assert core.telemetry(0.03 + 0.26).status & STATUS_LINK_LOST  # no valid set-point for 0.25 s
    core.handle(Frame(HOLD, 7, 0.0, v1, 7).encode(), 0.3)
    assert not core.telemetry(0.3).status & STATUS_LINK_LOST


def test_sessions_wrap_around_and_no_frame_locks_a_session_out(acts):
    """Sequence numbers wrap (RFC 1982); a forged or stale frame with any sequence number or session
    is not applied and does not block the next legitimate frame; a new session restarts tracking."""
    core = DeviceCore(acts, tau=0.0)
    base = 0xFFFFFFF0
    open_session(core, session=11, seq=base)
    seqs = [(base + k) % 2**32 for k in range(1, 21)]  # ..., 0xFFFFFFFF, 0, 1, ...
    for k, q in enumerate(seqs):
        core.handle(Frame(MOVE, q, 0.01 * k, acts.zero_offset, 11).encode(), 0.01 * k)
    assert [a.seq for a in core.applied] == seqs and core.counts["missed"] == 0
    last = seqs[-1]
    hostile = [
        Frame(MOVE, 0xFFFFFFFF, 0.0, acts.upper, 11),  # the frame: now far behind, stale
        Frame(MOVE, (last + 2**31) % 2**32, 0.0, acts.upper, 11),  # half the circle away
        Frame(MOVE, (last + SEQ_WINDOW + 1) % 2**32, 0.0, acts.upper, 11),  # beyond the window
        Frame(MOVE, last, 0.0, acts.upper, 11),  # duplicate
        Frame(MOVE, (last + 1) % 2**32, 0.0, acts.upper, 12),  # another session
        Frame(MOVE, (last + 1) % 2**32, 0.0, acts.upper, 0),  # no session
    ]
    for f in hostile:
        core.handle(f.encode(), 0.5)
    assert (core.counts["stale"], core.counts["foreign"]) == (4, 2)
    assert [a.seq for a in core.applied] == seqs
    core.handle(Frame(MOVE, (last + 1) % 2**32, 0.5, acts.zero_offset, 11).encode(), 0.5)
    assert core.applied[-1].seq == (last + 1) % 2**32
    # a repeated PING of the same session does not reset tracking (no replay of old frames) ...
    open_session(core, session=11, seq=base, now=0.6)
    core.handle(Frame(MOVE, seqs[0], 0.0, acts.upper, 11).encode(), 0.6)
    assert core.applied[-1].seq == (last + 1) % 2**32
    # ... a new session (a restarted streamer) starts over at its own PING's seq
    open_session(core, session=99, seq=0, now=0.7)
    core.handle(Frame(MOVE, 1, 0.0, acts.zero_offset, 99).encode(), 0.7)
    assert core.applied[-1].seq == 1 and core.telemetry(0.7).ack == 1


def _reseal(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body))


def hostile_datagrams(acts) -> st.SearchStrategy[bytes]:
    """Empty, huge, random, truncated, bit-flipped and re-sealed (valid CRC) frames with wrong fields."""
    good = Frame(MOVE, 3, 0.1, acts.zero_offset, 7).encode()
    header = st.tuples(
        st.sampled_from([b"CR", b"XX"]),
        st.integers(0, 255),
        st.integers(0, 255),
        st.integers(0, 0xFFFF),
        st.sampled_from([0, 7, 8, 0xFFFFFFFF]),
        st.sampled_from([0, 1, 4, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF]),
        st.floats(allow_nan=True, allow_infinity=True),
    ).map(lambda h: struct.pack("<2sBBHIId", *h))
    return st.one_of(
        st.just(b""),
        st.just(b"\x00" * 65536),
        st.binary(max_size=300),
        st.integers(0, len(good) - 1).map(lambda k: good[:k]),
        st.integers(0, len(good) * 8 - 1).map(
            lambda b: bytes(x ^ (1 << b % 8) * (i == b // 8) for i, x in enumerate(good))
        ),
        st.tuples(header, st.binary(max_size=120)).map(lambda hb: _reseal(hb[0] + hb[1])),
        st.tuples(header, st.lists(st.floats(), max_size=9)).map(
            lambda hv: _reseal(hv[0] + struct.pack(f"<{len(hv[1])}d", *hv[1]))
        ),
    )


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_hostile_datagrams_never_crash_or_stop_the_device(acts, data):
    core = DeviceCore(acts, tau=0.02)
    open_session(core)
    dgrams = data.draw(st.lists(hostile_datagrams(acts), min_size=1, max_size=20))
    for k, d in enumerate(dgrams):
        core.handle(d, 0.001 * k)  # must not raise
        tel = core.telemetry(0.001 * k)
        assert tel is None or np.all(np.isfinite(tel.positions))
    s = core.state()
    assert np.all(np.isfinite(s["positions"])) and np.all(acts.position_violation(s["target"]) <= 1e-9)
    # and it still serves: a new session's set-point is applied and acknowledged
    open_session(core, session=12345, now=1.0)
    target = acts.zero_offset + 0.001
    core.handle(Frame(MOVE, 1, 0.0, target, 12345).encode(), 1.0)
    assert core.telemetry(1.0).ack == 1
    core.advance(3.0)
    np.testing.assert_allclose(core.state()["positions"], target, atol=1e-9)


def test_corrupt_fault_survives_empty_and_tiny_datagrams(acts):
    """`sim-device --corrupt` crashed on one empty datagram (`ValueError: high <= 0`)."""
    dev = SimDevice(acts, faults=Faults(corrupt=0.99), seed=2)
    try:
        for d in (b"", b"\x00", b"CR", bytes(65536)):
            for _ in range(20):
                dev.ingest(d, ("127.0.0.1", 9), 0.0)
        st_ = dev.state()
        assert st_["internal_errors"] == 0 and st_["received"] == 80 and st_["crc_errors"] == 80
        assert st_["corrupted_in"] > 60
    finally:
        dev.stop()


def test_ping_opens_a_new_session_over_udp(acts):
    with SimDevice(acts) as dev:
        a, b = Host(dev, session=1), Host(dev, session=2)
        a.send(PING, 0, [])
        a.telemetry()
        a.send(MOVE, 1, np.zeros(7))
        a.send(MOVE, 2, np.zeros(7))
        a.wait_for(lambda t: t.ack == 2)
        b.send(PING, 0, [])  # a new streamer: sequence numbers restart at 1 and telemetry goes to b
        assert b.wait_for(lambda t: t.session == 2).ack == 0
        a.send(MOVE, 3, np.zeros(7))  # the old session's frames are not acted on any more
        b.send(MOVE, 1, np.full(7, 0.01))
        t = b.wait_for(lambda t: t.ack == 1 and t.foreign == 1)
        assert t.stale == 0 and [x.seq for x in dev.applied] == [1, 2, 1]
        a.close()
        b.close()


def test_drop_corrupt_and_disconnect_faults(acts):
    faults = Faults(drop=0.3, corrupt=0.3, disconnect_after=0.6, disconnect_for=0.4)
    with SimDevice(acts, faults=faults, seed=1) as dev:
        h = Host(dev)
        h.sock.settimeout(0.02)
        seq = 0
        got = []
        t_start = time.monotonic()
        while time.monotonic() - t_start < 1.2:
            seq += 1
            h.send(PING if seq == 1 else MOVE, seq, [] if seq == 1 else np.zeros(7))
            try:
                data = h.sock.recv(65536)
                got.append((time.monotonic() - t_start, data))
            except TimeoutError:
                pass
        st = dev.state()
        h.close()
    assert st["dropped_in"] > 0 and st["corrupted_in"] > 0 and st["crc_errors"] > 0
    assert st["dropped_out"] > 0 and st["corrupted_out"] > 0
    # silent while disconnected (0.6 .. 1.0 s after start, with slack for scheduling)
    assert not [t for t, _ in got if 0.65 < t < 0.95]
    assert [t for t, _ in got if t > 1.05]
    # every applied frame was intact
    assert all(np.all(a.values == 0.0) for a in dev.applied)


def test_bad_device_options():
    from crtraj.io.problem import load_robot

    r = load_robot("problems/robots/cdsr2.toml")
    a = Actuators.from_robot(r)
    with pytest.raises(InputError, match=r"binds 127\.0\.0\.1 only"):
        SimDevice(a, host="0.0.0.0")
    with pytest.raises(InputError, match="--drop: must be in"):
        Faults(drop=1.5)
    with pytest.raises(InputError, match="--tau: must be >= 0"):
        SimDevice(a, tau=-1.0)
    with pytest.raises(InputError, match="--telemetry-rate: must be > 0"):
        SimDevice(a, telemetry_rate=0.0)
