"""Drive Mode (register 10) declared per actuator in the robot file, through the official SDK against the
Protocol 2.0 simulator, which models the reverse bit as the ROBOTIS e-manual defines it (reverse mode counts
clockwise as positive: goal, present position and velocity all flip; the shaft does not move). Streamer and
servos share a virtual clock: no wall-clock timing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import require_module
from dxl_helpers import ROBOT, Z_HOMING, Clock, InProcessSim, homed_state, robot_text, serve_in_process, write

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.dynamixel._homing import Homer
from crtraj.hardware.dynamixel._homing_spec import read_homing
from crtraj.hardware.dynamixel._homing_state import HomingState
from crtraj.hardware.dynamixel._link import open_dynamixel
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import ServoChain
from crtraj.hardware.dynamixel._sim_robot import robot_chain
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.hardware.transport import TransportError
from crtraj.io.problem import load_robot
from crtraj.world.scene import Scene

S1C2 = "[robot.actuators.servo.s1c2]\nid = 2\n"


@pytest.fixture(autouse=True)
def _sdk(monkeypatch):
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    serve_in_process(monkeypatch)  # the simulators below answer in process, on their virtual clock


def _robot_file(tmp_path: Path, s1c2: str = "", z: str = "") -> Path:
    """cdsr2.toml with extra lines in s1c2's and z's tables, in tmp_path."""
    text = ROBOT.read_text().replace(S1C2, S1C2 + s1c2).replace("lead = 20.0", z + "lead = 20.0")
    p = tmp_path / "robot.toml"
    p.write_text(text)
    return p


def _motion(robot, acts):
    """A 4 s admitted motion among no obstacles, from the straight pose at z = -10 mm to a bent one."""
    x0, x1 = robot.straight(-10.0), np.array([0.3, 0.4, 0.1, 0.4, -10.0])
    s = np.linspace(0, 2, 11)
    X_ = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s / s[-1]))[:, None]
    record = MotionRecord("", "plan", "success", True, True, 0, 0, robot, Scene(), s, robot.cables(X_))
    return admit(record, acts, rate=100.0, time_scale=2.0)


def _connect(sim, acts, **kw):
    return open_dynamixel(f"dynamixel://{sim.path}", acts, warn=lambda m: None, max_misses=50, **kw)


def _refused(acts, chain) -> str:
    """The one-line refusal of connecting to `chain` (its servos homed where they stand)."""
    with InProcessSim(chain, clock=Clock(), wire_time=False) as sim, pytest.raises(TransportError) as e:
        _connect(sim, acts, homing=homed_state(chain, acts))
    assert "\n" not in str(e.value)
    return str(e.value)


def test_the_simulated_reverse_bit_flips_the_counting_not_the_shaft():
    """e-manual: reverse mode counts CW as positive. Setting the bit negates the reading (Homing Offset 0), the
    shaft stays; a goal of +500 then turns the shaft to -500 in normal counting."""
    chain = ServoChain([1], [1030], initial=[1000])
    write(chain, 1, X.DRIVE_MODE, X.DRIVE_REVERSE, 1)
    assert chain.register(1, X.PRESENT_POSITION, 4) == -1000
    assert chain.shaft(0.0).tolist() == [1000.0]
    write(chain, 1, X.OPERATING_MODE, X.EXTENDED_POSITION, 1)  # torque on in mode 3 would lose the turn count
    write(chain, 1, X.TORQUE_ENABLE, 1, 1)
    write(chain, 1, X.GOAL_POSITION, 500, 4)
    assert chain.positions(5.0)[0] == pytest.approx(500.0, abs=1e-6)
    assert chain.shaft(5.0)[0] == pytest.approx(-500.0, abs=1e-6)
    assert chain.register(1, X.PRESENT_VELOCITY, 4) == 0


def test_a_declared_reversed_servo_moves_the_robot_the_right_way(tmp_path):
    """s1c2's servo is mounted mirrored (its cable follows the shaft backwards) and declared reversed: connect
    sets the bit (it was clear), the spool is unwrapped afresh, and after streaming a motion the cable of every
    actuator, as the mechanism sees it through the shafts, is at the motion's final set-point. s1c2's shaft
    turned opposite to its commanded value: crtraj did not negate the values itself on top of the servo."""
    robot = load_robot(_robot_file(tmp_path, s1c2="drive_mode = { reverse = true }\n"))
    acts = Actuators.from_robot(robot)
    assert [m.reverse for m in acts.bus.drive_modes] == [False, True, False, False, False, False, False]
    motion = _motion(robot, acts)
    mount = np.ones(acts.n)
    mount[1] = -1.0  # mirrored: the cable's value is minus the shaft's (normal counting)
    clock = Clock()
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=mount * acts.bus.ticks(motion.values[0]))
    shaft0 = chain.shaft(0.0).copy()
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        link = _connect(sim, acts, homing=homed_state(chain, acts), stop_torque="off")
        assert chain.register(2, X.DRIVE_MODE, 1) == X.DRIVE_REVERSE  # the declared bit, set at connect
        rep = Streamer(link, acts, StreamOptions(rate=100.0, watchdog=10.0), None, clock=clock).run_path(motion)
        assert rep.status == "done", rep.message
        shaft = chain.shaft(clock.now())
    cable = acts.bus.values(np.rint(mount * shaft))
    tol = StreamOptions().settle_tolerance * (1 + 1e-9) + acts.bus.resolution
    assert np.all(np.abs(cable - motion.values[-1]) <= tol), cable - motion.values[-1]
    moved = motion.values[-1][1] - motion.values[0][1]
    assert abs(moved) > 0.1  # rad: the motion does turn s1c2
    assert np.sign(shaft[1] - shaft0[1]) == -np.sign(moved)  # the shaft turned against its commanded value


def test_an_undeclared_reverse_bit_is_refused_naming_the_servo_and_the_key(tmp_path):
    """A reverse bit the robot file does not declare: one line naming the servo and the key; nothing is set up
    (Return Delay Time still the factory 250, torque off, Drive Mode as found)."""
    acts = Actuators.from_robot(load_robot(ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models)
    write(chain, 5, X.DRIVE_MODE, X.DRIVE_REVERSE, 1)
    text = _refused(acts, chain)
    assert text.startswith(
        "servo id 5 (s2c2): Drive Mode 0x01 has the reverse bit set, which the robot file does not declare: "
        "add drive_mode = { reverse = true } to [robot.actuators.servo.s2c2]"
    ), text
    assert [chain.register(i, X.RETURN_DELAY, 1) for i in acts.bus.ids] == [X.RETURN_DELAY_DEFAULT] * 7
    assert not any(chain.torque(i) for i in acts.bus.ids)
    assert chain.register(5, X.DRIVE_MODE, 1) == X.DRIVE_REVERSE


def test_the_time_based_profile_is_refused_on_the_servo_and_in_the_robot_file(tmp_path):
    """Bit 2 found on a servo: one line saying crtraj does not support it and why; declared in the robot file:
    one line naming the key."""
    acts = Actuators.from_robot(load_robot(ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models)
    write(chain, 7, X.DRIVE_MODE, X.DRIVE_TIME_PROFILE, 1)
    text = _refused(acts, chain)
    assert text.startswith("servo id 7 (z): Drive Mode 0x04 has the time-based profile bit set")
    assert "crtraj does not support the time-based profile" in text and "clear bit 2 of register 10" in text
    with pytest.raises(InputError) as e2:
        load_robot(_robot_file(tmp_path, z="drive_mode = { time_based_profile = true }\n"))
    assert "\n" not in str(e2.value)
    assert str(e2.value).startswith(
        "robot.actuators.z.drive_mode.time_based_profile: crtraj does not support the time-based profile"
    ), str(e2.value)
    assert str(e2.value).endswith("remove this key from the robot file") and len(str(e2.value)) < 200
    with pytest.raises(InputError) as e3:
        load_robot(_robot_file(tmp_path, s1c2="drive_mode = { reverse = 1 }\n"))
    assert str(e3.value).startswith("robot.actuators.servo.s1c2.drive_mode.reverse: expected true or false")


def test_setting_a_declared_reverse_bit_on_the_stage_requires_homing_again(tmp_path):
    """The stage's reading flips with the bit: connect clears its homed marker, so the stream link refuses it
    (one line naming it) instead of using a reading mirrored about the offset."""
    acts = Actuators.from_robot(load_robot(_robot_file(tmp_path, z="drive_mode = { reverse = true }\n")))
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(np.r_[np.zeros(6), -150.0]))
    with InProcessSim(chain, clock=Clock(), wire_time=False) as sim:
        state = homed_state(chain, acts)
        with pytest.raises(InputError) as e:
            _connect(sim, acts, homing=state)
    assert str(e.value).startswith("servo id 7 (z): not homed since its last power-up or reboot")
    assert chain.register(7, X.DRIVE_MODE, 1) == X.DRIVE_REVERSE and chain.register(7, X.LED, 1) == 0
    assert not chain.torque(7)


# Every Drive Mode the robot file accepts (where it is declared, what it says) with the register as a servo may
# be found: clear, or already carrying the declared bit. (declaration, table it goes in, preset, reversed)
_DECLARED = [
    pytest.param("", "z", False, False, id="undeclared"),
    pytest.param("drive_mode = { reverse = false }\n", "z", False, False, id="normal"),
    pytest.param(
        "drive_mode = { reverse = false, time_based_profile = false }\n", "z", False, False, id="normal-velocity"
    ),
    pytest.param("drive_mode = { reverse = true }\n", "z", False, True, id="reverse-set-at-connect"),
    pytest.param("drive_mode = { reverse = true }\n", "z", True, True, id="reverse-preset"),
    pytest.param(
        "drive_mode = { reverse = true, time_based_profile = false }\n", "z", True, True, id="reverse-velocity"
    ),
    pytest.param("drive_mode = { reverse = true }\n", "shared", False, True, id="all-reverse-set-at-connect"),
    pytest.param("drive_mode = { reverse = true }\n", "shared", True, True, id="all-reverse-preset"),
]


@pytest.mark.parametrize("direction", [-1, 1], ids=["stop-below", "stop-above"])
@pytest.mark.parametrize(("declared", "where", "preset", "reversed_"), _DECLARED)
def test_the_stage_homes_against_its_stop_under_every_drive_mode(
    tmp_path, declared, where, preset, reversed_, direction
):
    """A power-cycled stage at -150 mm homes against the simulator's stop under every accepted Drive Mode, with
    the stop on either side. Ground truth is the simulator's mechanism: the shaft ends pressed on the stop (its
    physical position, normal counting), the servo then reads the reference, and after a move to z = v the shaft
    stands mount * (ticks(v) - ticks(reference)) from the stop, mount = -1 for a reversed servo (it counts the
    shaft backwards, ROBOTIS e-manual Drive Mode bit 0): the Homing Offset puts the reference on the stop and the
    values run the right way. The spools read their true values again (unwrapped, reversed or not)."""
    reference, v = (-200.0, -120.0) if direction < 0 else (100.0, 40.0)
    homing = Z_HOMING.replace("-200.0", f"{reference}").replace("direction = -1", f"direction = {direction}")
    text = robot_text(homing)
    if where == "shared":
        text = text.replace("[robot.actuators]\n", "[robot.actuators]\n" + declared, 1)
    else:
        text = text.replace("lead = 20.0", declared + "lead = 20.0")
    (robot_file := tmp_path / "robot.toml").write_text(text)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    assert acts.bus.drive_mode(6).reverse is reversed_
    values = acts.command(robot.cables(np.array([0.9, -0.6, 0.3, 0.5, -150.0])))
    clock = Clock()
    chain = robot_chain(robot, acts, values, preset=preset)
    stop = chain.stops[6][0] if np.isfinite(chain.stops[6][0]) else chain.stops[6][1]  # physical ticks
    chain.power_cycle(0.0)
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        link = _connect(sim, acts, power_up_check=False)
        try:
            homed = Homer(link, acts, dict(read_homing(robot, acts)), clock, lambda text: False).run()
        finally:
            link.close()
        assert chain.register(7, X.DRIVE_MODE, 1) == (X.DRIVE_REVERSE if reversed_ else 0)
        assert chain.shaft(clock.now())[6] == pytest.approx(stop, abs=1.0)  # pressed on the true stop
        z_ticks = [int(acts.bus.ticks(np.r_[np.zeros(6), z])[6]) for z in (reference, v)]
        assert chain.register(7, X.PRESENT_POSITION, 4) == z_ticks[0]
        got = acts.bus.values(np.array([chain.register(i, X.PRESENT_POSITION, 4) for i in acts.bus.ids]))
        np.testing.assert_allclose(got[:-1], values[:-1], atol=acts.bus.resolution[0])
        link = _connect(sim, acts, homing=HomingState(tuple(homed)))  # the stream's check accepts it
        try:
            link.write(7, X.GOAL_POSITION, int(z_ticks[1]) & 0xFFFFFFFF, 4, "goal position")
            for _ in range(600):  # 30 s, read every 50 ms: within the bus watchdog (a silent host stops the servos)
                clock.sleep(0.05)
                link.read(7, X.PRESENT_POSITION, 4)
            assert chain.register(7, X.PRESENT_POSITION, 4) == z_ticks[1]
        finally:
            link.close()
    mount = -1.0 if reversed_ else 1.0
    assert chain.shaft(clock.now())[6] == pytest.approx(stop + mount * (z_ticks[1] - z_ticks[0]), abs=1.0)
