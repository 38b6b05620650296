"""The in-process simulator port (`SimPort`) behind the official SDK: real protocol bytes both ways, replies at
the clock's time, and a silent servo's read timing out after the SDK's own packet timeout in virtual time."""

from __future__ import annotations

import pytest
from conftest import require_module

from crtraj.core.clock import VirtualClock
from crtraj.hardware.dynamixel_protocol import X
from crtraj.hardware.sim_dynamixel import ServoChain
from crtraj.hardware.sim_dynamixel_port import SDK_LATENCY_MS, SimPort


@pytest.fixture
def sdk():
    return require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")


def test_the_sdk_reads_and_writes_the_chain_through_the_port(sdk):
    """Ping, a 4-byte read and a write go through the SDK's packet handler to the chain and back."""
    clock = VirtualClock()
    chain = ServoChain([1, 7], [1060, 1030], initial=[100, -30720])
    port, ph = SimPort(chain, clock), sdk.PacketHandler(2.0)
    assert port.openPort()
    model, result, error = ph.ping(port, 7)
    assert (model, result, error) == (1030, sdk.COMM_SUCCESS, 0)
    value, result, _ = ph.read4ByteTxRx(port, 7, X.PRESENT_POSITION)
    assert result == sdk.COMM_SUCCESS and value == (-30720) & 0xFFFFFFFF
    result, error = ph.write1ByteTxRx(port, 1, X.LED, 1)
    assert (result, error) == (sdk.COMM_SUCCESS, 0) and chain.register(1, X.LED, 1) == 1
    assert clock.now() == 0.0 and port.timeouts == 0  # no wire time asked for: the clock stood still


def test_wire_time_moves_the_clock_by_the_bytes_on_the_bus(sdk):
    """With wire_time, a ping takes its request's and reply's bytes at 10 bits each at the bus rate plus the
    servo's Return Delay Time (factory 250 x 2 us)."""
    clock = VirtualClock()
    chain = ServoChain([3], [1030], baud=57_600)
    port, ph = SimPort(chain, clock, wire_time=True), sdk.PacketHandler(2.0)
    port.setBaudRate(57_600)
    assert ph.ping(port, 3)[1] == sdk.COMM_SUCCESS
    ping, status = 10, 14  # bytes: PING instruction packet, status packet with model number and firmware
    assert clock.now() == pytest.approx((ping + status) * 10 / 57_600 + 250 * 2e-6, rel=1e-12)


def test_a_silent_servo_times_out_after_the_sdk_timeout_in_virtual_time(sdk):
    """A missing id gets no reply: the SDK's read times out at once in wall time, the clock moving on by the
    SDK's packet timeout (bytes' time + 2 x its latency timer + 2 ms); a host at another rate gets nothing."""
    clock = VirtualClock()
    chain = ServoChain([1, 2], [1060, 1060])
    chain.remove(2)
    port, ph = SimPort(chain, clock), sdk.PacketHandler(2.0)
    port.openPort()
    _, result, _ = ph.read4ByteTxRx(port, 2, X.PRESENT_POSITION)
    assert result == sdk.COMM_RX_TIMEOUT and port.timeouts == 1
    expected_ms = 2 * SDK_LATENCY_MS + 2.0
    assert expected_ms / 1000 < clock.now() < (expected_ms + 1.0) / 1000  # plus the reply's bytes at 1 Mbaud
    assert SDK_LATENCY_MS == sdk.port_handler.LATENCY_TIMER  # the SDK's own constant
    port.setBaudRate(57_600)
    assert ph.ping(port, 1)[1] == sdk.COMM_RX_TIMEOUT and port.wrong_baud == 1
