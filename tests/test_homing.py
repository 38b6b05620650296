"""Absolute position after a power-up, through the official SDK against the Protocol 2.0 simulator: the
simulator's power-up (multi-turn count lost), the refusal of an unhomed z stage, hard-stop homing, the
spools' unwrap, the homing section's bad inputs, and the servo setup at connect (return delay, status
return level, drive mode). Streamer, homer and servos share a virtual clock: no wall-clock timing."""

from __future__ import annotations

import io
import json
import math
import os
import select
import sys
import termios
from pathlib import Path

import dxl_helpers
import numpy as np
import pytest
from conftest import require_module
from dxl_helpers import ROBOT, Z_HOMING, Clock, InProcessSim, in_process, robot_text, serve_in_process

from crtraj.app.devices import admit_result, plan_approach
from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._homing import Homer, HomingError
from crtraj.hardware.dynamixel._homing_spec import read_homing
from crtraj.hardware.dynamixel._homing_state import HomedServo, HomingState, PowerUpCheck, state_path, unwrap
from crtraj.hardware.dynamixel._link import open_dynamixel
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import TICKS_PER_REV, ServoChain
from crtraj.hardware.dynamixel._sim_pty import SimDynamixel
from crtraj.hardware.dynamixel._sim_robot import ChainIO, stops
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.hardware.transport import TransportError
from crtraj.io.problem import load_robot
from crtraj.world.scene import Scene

sim1_plan = dxl_helpers.sim1_plan  # the fixture, shared


@pytest.fixture(autouse=True)
def _sdk(monkeypatch):
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    serve_in_process(monkeypatch)  # the simulators below answer in process (all but the pseudo-terminal's test)
    old = sys.getswitchinterval()  # that one's thread answers the test's own reads
    sys.setswitchinterval(1e-4)
    yield
    sys.setswitchinterval(old)


def _robot_file(tmp_path: Path, extra: str = Z_HOMING) -> Path:
    """cdsr2.toml with `extra` in place of its own [robot.homing.z], in tmp_path."""
    p = tmp_path / "robot.toml"
    p.write_text(robot_text(extra))
    return p


def _chain(robot, acts, values, **kw) -> ServoChain:
    """Servos at actuator `values` (rad, mm), homed as far as the shafts go (absolute readings), with the
    mechanical stops of the robot's hard_stop specs."""
    return ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(values), stops=stops(robot, acts), **kw)


def _write(chain: ServoChain, dxl_id: int, addr: int, value: int, size: int) -> None:
    """A WRITE instruction to the chain, as another program on the bus would send it."""
    params = addr.to_bytes(2, "little") + value.to_bytes(size, "little", signed=value < 0)
    chain.handle(dxl.Packet(dxl_id, dxl.WRITE, params), 0.0)


def _start(acts) -> np.ndarray:
    """A bent pose with the stage switched off at z = -150 mm (actuator values, rad and mm)."""
    robot = load_robot(ROBOT)
    v = acts.command(robot.cables(np.array([0.9, -0.6, 0.3, 0.5, -150.0])))
    assert np.all(acts.lower <= v) and np.all(v <= acts.upper) and np.any(v[:-1] < 0)  # some spools wrap at power-up
    return v


def _reading(chain: ServoChain, acts, clock) -> np.ndarray:
    return acts.bus.values(np.rint(chain.positions(clock.now())))


def _motion(robot, acts, start: np.ndarray):
    """A short admitted motion (no obstacles) from the actuator values `start` to a nearby pose."""
    x0 = robot.config(acts.actuation(start))
    x1 = x0 + np.array([0.05, -0.05, 0.02, 0.0, 5.0])
    s = np.linspace(0, 1, 11)
    X_ = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    record = MotionRecord("", "plan", "success", True, True, 0, 0, robot, Scene(), s, robot.cables(X_))
    return admit(record, acts, rate=100.0)


# ------------------------------------------------------------- the simulator's power-up
def test_power_cycle_reads_within_one_turn_plus_the_homing_offset_and_resets_ram():
    """After a power cycle each reading is the old one modulo a turn (plus the homing offset); LED reads 0."""
    chain = ServoChain([1, 2], [1030, 1030], initial=[-30720, 5000])
    _write(chain, 1, X.LED, 1, 1)
    _write(chain, 2, X.HOMING_OFFSET, -100, 4)
    assert chain.positions(0.0).tolist() == [-30720, 4900]  # the offset moves the reading at once
    chain.power_cycle(1.0)
    assert chain.positions(1.0).tolist() == [-30720 % 4096, (4900 + 100) % 4096 - 100]
    assert chain.register(1, X.LED, 1) == 0  # RAM at its power-up default: the homed marker is gone
    assert chain.register(2, X.HOMING_OFFSET, 4) == -100  # EEPROM kept
    chain.handle(dxl.Packet(1, dxl.REBOOT, b""), 2.0)
    assert chain.positions(2.0)[0] == -30720 % 4096


def test_return_delay_and_status_return_level_as_the_e_manual_defines_them():
    """Reply time = the bytes at 10 bits each + 2 us per unit of Return Delay Time (factory 250 = 500 us);
    Status Return Level 1 answers reads but not writes, 0 only pings."""
    chain = ServoChain([1], [1030], baud=1_000_000)
    read = dxl.Packet(1, dxl.READ, bytes([X.PRESENT_POSITION, 0, 4, 0]))
    replies = chain.handle(read, 0.0)
    assert len(replies) == 1
    assert chain.reply_time(14, replies) == pytest.approx((14 + len(replies[0])) * 10 / 1e6 + 250 * 2e-6)
    assert chain.handle(dxl.Packet(1, dxl.WRITE, bytes([X.STATUS_RETURN, 0, 1])), 0.0)  # answered (level 2)
    assert chain.handle(dxl.Packet(1, dxl.WRITE, bytes([X.LED, 0, 1])), 0.0) == []
    assert len(chain.handle(read, 0.0)) == 1
    chain.handle(dxl.Packet(1, dxl.WRITE, bytes([X.STATUS_RETURN, 0, 0])), 0.0)
    assert chain.handle(read, 0.0) == []
    assert len(chain.handle(dxl.Packet(1, dxl.PING, b""), 0.0)) == 1


def test_connect_sets_return_delay_and_status_return_and_refuses_a_reverse_bit():
    """Connect writes Return Delay Time 0 and Status Return Level 2; a reverse Drive Mode bit is one line."""
    acts = Actuators.from_robot(load_robot(ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models)
    clock = Clock()
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        open_dynamixel(
            f"dynamixel://{sim.path}", acts, warn=lambda m: None, stop_torque="off", power_up_check=False
        ).close()
        assert [chain.register(i, X.RETURN_DELAY, 1) for i in acts.bus.ids] == [0] * 7
        assert [chain.register(i, X.STATUS_RETURN, 1) for i in acts.bus.ids] == [2] * 7
        _write(chain, 3, X.DRIVE_MODE, X.DRIVE_REVERSE, 1)  # as a servo tool would (torque is off after close)
        with pytest.raises(TransportError) as e:
            open_dynamixel(f"dynamixel://{sim.path}", acts, warn=lambda m: None)
        assert "servo id 3 (s1c3): Drive Mode 0x01 has the reverse bit set" in str(e.value)


# ------------------------------------------------------------- unwrap
@pytest.mark.parametrize("true_value", [-2.0, -1.5, -0.3, 0.0, 0.7, 1.99])
@pytest.mark.parametrize("turns", [-3, -1, 0, 1, 2])
def test_unwrap_returns_the_value_within_the_limits_whatever_the_turn(true_value, turns):
    """A spool within its limits whose reading is off by whole turns is unwrapped exactly."""
    n, lo, hi = 4096, -1304, 1304  # +-2 rad
    truth = round(true_value / (2 * math.pi) * n)
    shift = unwrap(truth + turns * n, lo, hi, n)
    assert shift == -turns * n


def test_unwrap_refuses_a_reading_in_no_turn_of_the_window():
    assert unwrap(2500, -1304, 1304, 4096) is None  # 3.8 rad: between the window's end and the next turn's start


# ------------------------------------------------------------- end to end
def _connect(sim, acts, **kw):
    """A link; without a homing state it is `crtraj home`'s (no power-up check), with one a streaming link's."""
    kw.setdefault("power_up_check", "homing" in kw)
    return open_dynamixel(f"dynamixel://{sim.path}", acts, warn=lambda m: None, max_misses=50, **kw)


def test_power_cycled_stage_is_refused_then_homed_then_streams(tmp_path):
    """z switched off at -150 mm reads within one turn after power-up: the stream refuses naming it; after
    homing against the stop at -200 mm it reads -200 mm, the state file is written, and a stream from there
    completes with the servos at the final set-point."""
    robot_file = _robot_file(tmp_path)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    clock = Clock()
    chain = _chain(robot, acts, _start(acts))
    chain.power_cycle(0.0)
    z_read = _reading(chain, acts, clock)[-1]
    assert 0.0 <= z_read < 20.0 and abs(z_read - (-150.0)) > 100  # a lead-screw stage lost 7.5 turns
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        with pytest.raises(InputError) as e:
            _connect(sim, acts, homing=HomingState.load(state_path(robot_file)))
        assert "\n" not in str(e.value)
        assert str(e.value).startswith("servo id 7 (z): not homed since its last power-up")
        assert not chain.torque(7) and _reading(chain, acts, clock)[-1] == pytest.approx(z_read)  # no motion
        link = _connect(sim, acts)
        try:
            homed = Homer(link, acts, dict(read_homing(robot, acts)), clock, lambda text: False).run()
        finally:
            link.close()
        HomingState().merged(homed).save(state_path(robot_file))
        now = _reading(chain, acts, clock)
        assert now[-1] == pytest.approx(-200.0, abs=acts.bus.resolution[-1])
        # the spools were unwrapped to where they are (their shafts did not move)
        np.testing.assert_allclose(now[:-1], _start(acts)[:-1], atol=acts.bus.resolution[0])
        saved = json.loads(state_path(robot_file).read_text())
        assert [(s["id"], s["name"], s["model"], s["method"]) for s in saved["servos"]] == [(7, "z", 1030, "hard_stop")]
        motion = _motion(robot, acts, now)
        link = _connect(sim, acts, homing=HomingState.load(state_path(robot_file)))
        rep = Streamer(link, acts, StreamOptions(rate=100.0, watchdog=10.0), None, clock=clock).run_path(motion)
        assert rep.status == "done", rep.message
        final = _reading(chain, acts, clock)
        assert np.max(np.abs(final - motion.values[-1])) <= StreamOptions().settle_tolerance * (1 + 1e-9)


def test_a_spool_turned_while_unpowered_is_unwrapped_or_refused():
    """A spool whose reading is a turn off after power-up is unwrapped to its true value; one outside every
    turn of its window is refused, naming it; neither is ever used 2 pi off."""
    acts = Actuators.from_robot(load_robot(ROBOT))
    clock = Clock()
    values = _start(acts)
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(values))
    chain.turn_by_hand(2, TICKS_PER_REV)  # s1c2 turned a whole revolution while unpowered
    chain.power_cycle(0.0)
    _write(chain, 7, X.LED, 1, 1)  # the stage counts as homed here: this test is about the spools
    here = chain.register(7, X.PRESENT_POSITION, 4)  # where it was let go
    stage = HomingState((HomedServo(7, "z", 1030, 0, "index", "2026-01-01T00:00:00+00:00", 0, 46, here),))
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        assert np.any(np.abs(_reading(chain, acts, clock)[:-1] - values[:-1]) > 6.0)  # read a turn off
        link = _connect(sim, acts)
        try:
            for i in acts.bus.ids:
                link.write(i, X.TORQUE_ENABLE, 0, 1, "torque off")
            PowerUpCheck(link, acts, stage).run()
        finally:
            link.close()
        got = _reading(chain, acts, clock)[:-1]
        np.testing.assert_allclose(got, values[:-1], atol=acts.bus.resolution[0])
        chain.power_cycle(clock.now())
        _write(chain, 7, X.LED, 1, 1)
        chain.turn_by_hand(3, 2500 - chain.register(3, X.PRESENT_POSITION, 4))  # s1c3 to 3.8 rad, past its 2 rad
        link = _connect(sim, acts)
        try:
            with pytest.raises(InputError) as e:
                PowerUpCheck(link, acts, stage).run()
        finally:
            link.close()
        assert str(e.value).startswith("servo id 3 (s1c3): after a power-up it reads 2500 ticks")


# ------------------------------------------------------------- bad input
def test_a_stop_outside_the_limits_is_one_line_and_nothing_is_written(tmp_path, capsys):
    robot_file = _robot_file(tmp_path, Z_HOMING.replace("-200.0", "-250.0"))
    assert main(["home", "--dynamixel", str(tmp_path / "ttyUSB9"), "--robot", str(robot_file)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["crtraj: error: robot.homing.z.reference: -250 mm is outside the position limits [-200, 100] mm"], (
        err
    )
    assert not state_path(robot_file).exists()


def test_a_servo_that_never_stalls_is_one_line_and_nothing_is_written(tmp_path):
    robot_file = _robot_file(tmp_path, Z_HOMING + "travel = 40.0\n")
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    clock = Clock()
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(_start(acts)))  # no stops
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        link = _connect(sim, acts)
        try:
            with pytest.raises(HomingError) as e:
                Homer(link, acts, dict(read_homing(robot, acts)), clock, lambda t: True, poll=0.02).run()
        finally:
            link.close()
    assert str(e.value).startswith("servo id 7 (z): no stall within 40 mm of travel")
    assert chain.register(7, X.HOMING_OFFSET, 4) == 0  # no offset written
    assert not state_path(robot_file).exists()


def test_a_mark_never_confirmed_is_one_line_no_motion_and_nothing_written(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))  # nobody at the keyboard: standard input is closed
    robot_file = _robot_file(tmp_path, Z_HOMING.replace('"hard_stop"', '"index"'))
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(_start(acts)))
    sim = in_process(monkeypatch, chain, Clock())
    before = chain.positions(sim.clock.now()).copy()
    code = main(["home", "--dynamixel", sim.path, "--robot", str(robot_file)])
    after = chain.positions(sim.clock.now())
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err == [
        "crtraj: error: servo id 7 (z): its index mark was never confirmed (robot.homing.z); nothing written"
    ], err
    np.testing.assert_array_equal(before, after)
    assert not state_path(robot_file).exists()


def test_stream_approach_refuses_an_unhomed_stage_then_runs_after_homing(sim1_plan, tmp_path, capsys):
    """`crtraj stream PLAN --dynamixel DEV --approach` after a power cycle with z at -150 mm: one line naming
    z, nothing moves; after homing, the same run (approach planned and verified) completes."""
    robot_file = _robot_file(tmp_path)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    clock = Clock()
    chain = _chain(robot, acts, _start(acts))
    chain.power_cycle(0.0)
    capsys.readouterr()
    with InProcessSim(chain, clock=clock, wire_time=False) as sim:
        before = chain.positions(clock.now()).copy()
        goals = [chain.register(i, X.GOAL_POSITION, 4) for i in acts.bus.ids]
        argv = ["stream", str(sim1_plan), "--dynamixel", sim.path, "--approach", "--robot", str(robot_file)]
        assert main([*argv, "--log", str(tmp_path / "refused.jsonl")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("crtraj: error: servo id 7 (z): not homed since its last power-up")
        assert f"crtraj home --dynamixel {sim.path} --robot {robot_file}" in err[0]
        np.testing.assert_array_equal(chain.positions(clock.now()), before)
        assert [chain.register(i, X.GOAL_POSITION, 4) for i in acts.bus.ids] == goals  # no goal went out
        assert not any(chain.torque(i) for i in acts.bus.ids)
        link = _connect(sim, acts)
        try:
            homed = Homer(link, acts, dict(read_homing(robot, acts)), clock, lambda text: False).run()
        finally:
            link.close()
        HomingState().merged(homed).save(state_path(robot_file))
        motion = admit_result(sim1_plan, robot_file, rate=100.0)
        link = _connect(sim, acts, homing=HomingState.load(state_path(robot_file)))
        st = Streamer(link, acts, StreamOptions(rate=100.0, watchdog=10.0), None, clock=clock)
        rep = st.run_path(motion, approach=True, plan_approach=plan_approach)
        assert rep.status == "done", rep.message
        assert not any(e[1] == "refused" for e in rep.events)
        final = _reading(chain, acts, clock)
        assert np.max(np.abs(final - motion.values[-1])) <= StreamOptions().settle_tolerance * (1 + 1e-9)


def test_power_cycle_at_a_time_of_the_simulators_clock():
    """`SimDynamixel(power_cycle_at=T)` power-cycles every servo once its clock passes T: the next packet
    already meets the reading within one turn and the homed marker gone."""
    clock = Clock()
    chain = ServoChain([7], [1030], initial=[-30720])
    _write(chain, 7, X.LED, 1, 1)
    with SimDynamixel(chain, clock=clock, wire_time=False, power_cycle_at=0.5) as sim:
        assert chain.register(7, X.PRESENT_POSITION, 4) == -30720
        clock.advance(1.0)
        fd = os.open(sim.path, os.O_RDWR | os.O_NOCTTY)
        try:
            attrs = termios.tcgetattr(fd)
            attrs[4] = attrs[5] = termios.B1000000  # the bus rate (the simulator ignores other rates)
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
            os.write(fd, dxl.encode(7, dxl.READ, bytes([X.LED, 0, 1, 0])))
            assert select.select([fd], [], [], 5.0)[0]
            reply = dxl.PacketReader().feed(os.read(fd, 64))
        finally:
            os.close(fd)
    assert [p.params for p in reply] == [b"\x00\x00"]  # no error, LED 0: the marker is gone
    assert chain.register(7, X.PRESENT_POSITION, 4) == -30720 % 4096


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ('[robot.homing.q9]\nmethod = "index"\nreference = 0.0\n', "robot.homing.q9: not an actuator"),
        ('[robot.homing.z]\nmethod = "magic"\nreference = 0.0\n', "robot.homing.z.method: must be one of"),
        ('[robot.homing.z]\nmethod = "index"\n', "robot.homing.z.reference: missing"),
        ('[robot.homing.z]\nmethod = "index"\nreference = 0.0\ndirection = 0\n', "robot.homing.z.direction"),
        ('[robot.stop]\ntorque = "loose"\n', "robot.stop.torque: must be one of"),
    ],
)
def test_bad_homing_and_stop_sections_are_one_line(tmp_path, section, message):
    with pytest.raises(InputError) as e:
        load_robot(_robot_file(tmp_path, section))
    assert "\n" not in str(e.value) and str(e.value).startswith(message), str(e.value)


def test_sim_dynamixel_power_cycle_at_must_be_a_time(capsys):
    assert main(["sim-dynamixel", "--pty", "--power-cycle-at", "-1", "--duration", "0"]) == 2
    assert capsys.readouterr().err.strip() == "crtraj: error: --power-cycle-at: must be in 0..1000000 s, got -1.0"


def test_a_state_file_without_the_servo_identity_is_refused_until_homed_again(tmp_path):
    """A state file written before the identity was recorded (no model information, no firmware) matches no
    servo: the marked stage is refused in one line naming it, with the command that homes it."""
    acts = Actuators.from_robot(load_robot(ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(_start(acts)))
    _write(chain, 7, X.OPERATING_MODE, X.EXTENDED_POSITION, 1)  # as homing leaves it: the marker counts in mode 4
    _write(chain, 7, X.LED, 1, 1)
    old = {"kind": "crtraj-homing", "servos": [{"id": 7, "name": "z", "model": 1030, "offset": 0, "method": "index",
                                                "time": "2026-11-30T00:00:00+00:00"}]}  # fmt: skip
    path = tmp_path / "robot.homing.json"
    path.write_text(json.dumps(old))
    state = HomingState.load(path)
    assert state.get(7).identity() == (1030, -1, -1)
    with pytest.raises(InputError) as e:
        PowerUpCheck(ChainIO(chain, Clock()), acts, state, "crtraj home --dynamixel D").run()
    assert str(e.value) == (
        "servo id 7 (z): model 1030, model information 0, firmware 46 is not the servo the homing state file "
        "recorded (model 1030, model information -1, firmware -1): another servo on this id; run crtraj home "
        "--dynamixel D"
    )
