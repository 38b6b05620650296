"""The in-process simulator port (`SimPort`) behind the official SDK: real protocol bytes both ways, replies at
the clock's time, and a silent servo's read timing out after the SDK's own packet timeout in virtual time; and
the robot's servos started homed at a pose (`sim-dynamixel --at`)."""

from __future__ import annotations

import re

import dxl_helpers
import numpy as np
import pytest
from conftest import require_module
from dxl_helpers import Z_HOMING, robot_text

from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel._homing_state import HomingState, PowerUpCheck, state_path
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import ServoChain
from crtraj.hardware.dynamixel._sim_port import SDK_LATENCY_MS, SimPort
from crtraj.hardware.dynamixel._sim_robot import ChainIO, home_in_place, robot_chain
from crtraj.io.problem import load_robot

sim1_plan = dxl_helpers.sim1_plan  # the fixture, shared


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


# ------------------------------------------------------- --at: the servos start homed
@pytest.mark.parametrize("reverse", [False, True], ids=["normal", "reversed"])
def test_servos_started_at_a_pose_are_homed_as_crtraj_home_leaves_them(tmp_path, reverse):
    """`home_in_place` powers the servos up, runs crtraj's homing against them and moves them back: each reads
    its start value, every homed marker (LED) is lit by the homing's own writes, the stage's Homing Offset puts
    its reference on the simulator's true stop (the shaft stands mount * (ticks(z) - ticks(-200 mm)) from it,
    mount -1 reversed), and the stream's power-up check accepts the servos with the entries returned, and
    refuses them again after another power cycle (the marker is RAM, nothing faked)."""
    text = robot_text(Z_HOMING)
    if reverse:
        text = text.replace("lead = 20.0", "drive_mode = { reverse = true }\nlead = 20.0")
    (path := tmp_path / "robot.toml").write_text(text)
    robot = load_robot(path)
    acts = Actuators.from_robot(robot)
    values = acts.command(robot.cables(np.array([0.9, -0.6, 0.3, 0.5, -150.0])))
    chain = robot_chain(robot, acts, values)
    stop, mount = next(s for s in chain.stops[6] if np.isfinite(s)), (-1.0 if reverse else 1.0)  # physical ticks
    homed, reached = home_in_place(robot, acts, chain, values)
    assert [(h.id, h.method) for h in homed] == [(7, "hard_stop")]
    assert reached > 50.0 / 20.0  # s: the stage went to its stop (50 mm at 20 mm/s) and back
    reading = np.array([chain.register(i, X.PRESENT_POSITION, 4) for i in acts.bus.ids])
    np.testing.assert_array_equal(reading, acts.bus.ticks(values))
    assert [chain.register(i, X.LED, 1) for i in acts.bus.ids] == [1] * 7
    ref = acts.bus.ticks(np.r_[np.zeros(6), -200.0])[6]
    assert chain.shaft(reached)[6] == pytest.approx(stop + mount * (reading[6] - ref), abs=1.0)
    assert chain.register(7, X.HOMING_OFFSET, 4) == homed[0].offset != 0
    io = ChainIO(chain, VirtualClock(reached))
    PowerUpCheck(io, acts, HomingState(tuple(homed))).run()
    chain.power_cycle(reached)
    with pytest.raises(InputError, match="servo id 7 \\(z\\): not homed since its last power-up"):
        PowerUpCheck(io, acts, HomingState(tuple(homed))).run()


def test_cli_sim_dynamixel_at_writes_the_homing_state_beside_the_robot(tmp_path, capsys, sim1_plan):
    """`crtraj sim-dynamixel --at RESULT --robot R` homes before it serves and writes R's homing state (as
    `crtraj home` would); the stream's check reads that file."""
    (robot := tmp_path / "robot.toml").write_text(robot_text(Z_HOMING))
    assert main(["sim-dynamixel", "--pty", "--robot", str(robot), "--at", str(sim1_plan), "--duration", "0"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert re.fullmatch(r"homed z \(id 7\) by hard_stop: homing offset -?\d+ ticks; homing state: .*", out[0]), out
    state = HomingState.load(state_path(robot))
    assert [(s.id, s.name, s.method) for s in state.servos] == [(7, "z", "hard_stop")]
    assert out[0].endswith(str(state_path(robot))) and out[1].startswith("sim-dynamixel on /dev/pts/")


def test_a_stage_without_a_homing_section_starts_homed_at_an_index_where_it_stands(tmp_path):
    """No [robot.homing.z]: `home_in_place` homes the stage as at an index mark where it stands (crtraj's index
    homing, the operator's confirmation given), so it reads its start value and the stream's check accepts it."""
    (path := tmp_path / "robot.toml").write_text(robot_text(""))
    robot = load_robot(path)
    acts = Actuators.from_robot(robot)
    values = acts.command(robot.cables(np.array([0.2, 0.1, 0.3, 0.5, -150.0])))
    chain = robot_chain(robot, acts, values)
    homed, reached = home_in_place(robot, acts, chain, values)
    assert [(h.id, h.method) for h in homed] == [(7, "index")]
    reading = np.array([chain.register(i, X.PRESENT_POSITION, 4) for i in acts.bus.ids])
    np.testing.assert_array_equal(reading, acts.bus.ticks(values))
    assert chain.shaft(reached)[6] == pytest.approx(acts.bus.ticks(values)[6], abs=1.0)  # it never moved
    PowerUpCheck(ChainIO(chain, VirtualClock(reached)), acts, HomingState(tuple(homed))).run()


def test_cli_sim_dynamixel_state_without_at_is_one_line(capsys, tmp_path):
    assert main(["sim-dynamixel", "--pty", "--state", str(tmp_path / "s.json"), "--duration", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["crtraj: error: --state: only with --at (the homing state of the servos it starts homed)"], err
