"""The simulated device: first-order servo lag, CRC and sequence checks, its own limits, faults."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import (
    ESTOP,
    HOLD,
    MOVE,
    PING,
    STATUS_ESTOP,
    STATUS_HOLDING,
    STATUS_REFUSED,
    Frame,
    FrameError,
    Telemetry,
)
from crtraj.hardware.sim_device import Faults, SimDevice

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def acts(robot):
    return Actuators.from_robot(robot)


class Host:
    """A bare UDP peer speaking the protocol by hand (independent of the Streamer)."""

    def __init__(self, dev: SimDevice) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.5)
        self.addr = dev.address

    def send(self, kind: int, seq: int, values, stamp: float = 0.0) -> None:
        self.sock.sendto(Frame(kind, seq, stamp, np.asarray(values, dtype=float)).encode(), self.addr)

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


def test_servo_lag_is_first_order_with_the_given_time_constant(acts):
    tau = 0.2
    with SimDevice(acts, tau=tau, physics_dt=0.001) as dev:
        h = Host(dev)
        h.send(PING, 0, [])
        t0 = h.telemetry()
        np.testing.assert_array_equal(t0.positions, acts.zero_offset)
        target = np.array([0.5, -0.4, 0.3, 0.0, 0.2, -0.1, 10.0])
        h.send(MOVE, 1, target)
        samples = []
        end = time.monotonic() + 0.6
        while time.monotonic() < end:
            t = h.telemetry()
            if t.ack == 1:
                samples.append(t)
        applied = dev.applied[-1]
        h.close()
    assert applied.seq == 1 and applied.kind == MOVE
    assert len(samples) > 20
    # closed form of tau x' = u - x from x(t_a) = 0: x = u (1 - exp(-(t - t_a) / tau))
    for t in samples:
        frac = 1.0 - np.exp(-(t.stamp - applied.wall) / tau)
        # the physics steps quantise time to 1 ms and the target takes effect at the next step
        np.testing.assert_allclose(t.positions, target * frac, atol=0.02 * np.abs(target).max() + 1e-9)
    assert samples[-1].positions[-1] > 0.9 * target[-1]


def test_crc_sequence_limits_and_estop(acts):
    with SimDevice(acts, tau=0.01) as dev:
        h = Host(dev)
        h.send(PING, 0, [])
        h.telemetry()
        v1 = np.full(7, 0.1)
        good = Frame(MOVE, 1, 0.0, v1).encode()
        bad = bytearray(good)
        bad[20] ^= 0x10
        h.raw(bytes(bad))  # corrupted: never applied
        h.send(MOVE, 5, v1)  # seq gap of 4 (1..4 missing)
        h.send(MOVE, 3, np.full(7, 0.9))  # older than 5: stale
        h.send(MOVE, 6, np.array([2.5, 0, 0, 0, 0, 0, 0]))  # outside s1c1 limits: refused by the device
        t = h.wait_for(lambda t: t.refused == 1)
        assert (t.crc_errors, t.missed, t.stale, t.refused) == (1, 4, 1, 1)
        assert t.status & STATUS_REFUSED
        assert [a.seq for a in dev.applied] == [5]
        np.testing.assert_array_equal(dev.state()["target"], v1)
        h.send(HOLD, 7, v1)
        h.send(ESTOP, 8, v1)
        h.send(MOVE, 9, np.zeros(7))  # ignored: e-stop latches
        t = h.wait_for(lambda t: t.ack == 9)
        assert t.status & STATUS_ESTOP and t.status & STATUS_HOLDING
        assert [a.kind for a in dev.applied] == [MOVE, HOLD, ESTOP]
        h.close()


def test_ping_opens_a_new_session(acts):
    with SimDevice(acts) as dev:
        a, b = Host(dev), Host(dev)
        a.send(PING, 0, [])
        a.telemetry()
        a.send(MOVE, 1, np.zeros(7))
        a.send(MOVE, 2, np.zeros(7))
        a.wait_for(lambda t: t.ack == 2)
        b.send(PING, 0, [])  # a new streamer: sequence numbers restart at 1 and telemetry goes to b
        assert b.telemetry().ack == 0
        b.send(MOVE, 1, np.full(7, 0.01))
        assert b.wait_for(lambda t: t.ack == 1).stale == 0
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
    with pytest.raises(InputError, match="--tau: must be > 0"):
        SimDevice(a, tau=0.0)
