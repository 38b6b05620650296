"""Hard-stop homing that is safe for the tendons and tells a jam from the stop (issue 38): the stall current
within the force cap, the offset read while the stop is still pressed (no spring-back in it), a jam refused by
the turn's phase, and a spool homed against a stop only when the robot file allows it. Through crtraj's own
homing (`Homer`) on the simulator's READ and WRITE packets, on a virtual clock."""

from __future__ import annotations

import numpy as np
import pytest
from dxl_helpers import Z_HOMING, robot_text

from crtraj.core.clock import VirtualClock
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import Homer, HomingState, X, read_homing, robot_chain
from crtraj.hardware.dynamixel._homing import HomingError
from crtraj.hardware.dynamixel._sim_robot import ChainIO
from crtraj.io.problem import load_robot

COMPLIANCE = 0.5  # ticks per current unit the simulated stage's stop yields


def _robot(tmp_path, text: str = Z_HOMING, extra: str = ""):
    f = tmp_path / "robot.toml"
    f.write_text(robot_text(text).replace("lead = 20.0 ", extra + "lead = 20.0 "))
    robot = load_robot(f)
    return robot, Actuators.from_robot(robot)


def _powered_up(robot, acts, z: float):
    """The robot's servos with the stage's shaft at `z` (mm), just powered up, its stop yielding `COMPLIANCE`."""
    values = acts.command(robot.cables(np.array([0.0, 0.0, 0.0, 0.0, z])))
    chain = robot_chain(robot, acts, values)
    chain.power_cycle(0.0)
    chain.loads.compliance[6] = COMPLIANCE
    return chain, VirtualClock()


def _home(robot, acts, chain, clock, previous=None):
    homer = Homer(ChainIO(chain, clock), acts, dict(read_homing(robot, acts)), clock, lambda t: True, previous=previous)
    return homer.run()


def _press(chain, clock, goal_units: int, z_goal_ticks: int) -> int:
    """The stage pressed against its stop again at `goal_units` of Goal Current: its reading (ticks)."""
    io = ChainIO(chain, clock)
    io.write(7, X.OPERATING_MODE, X.CURRENT_POSITION, 1, "mode")
    io.write(7, X.GOAL_CURRENT, goal_units, 2, "goal current")
    io.write(7, X.TORQUE_ENABLE, 1, 1, "torque on")
    io.write(7, X.GOAL_POSITION, z_goal_ticks, 4, "goal")
    clock.sleep(20.0)
    return io.read(7, X.PRESENT_POSITION, 4)


def test_the_offset_is_read_while_the_stop_is_pressed(tmp_path):
    """The stop yields 0.5 tick per current unit, 55.5 ticks at the homing's 300 mA (111 units), and springs back
    when the torque goes off. The homed stage reads its reference (-200 mm) when it presses the stop again at the
    homing current, to within a tick; after the torque-off it reads the spring-back above it (an offset read after
    the torque-off would put the reference at the released shaft: 55 ticks, 0.27 mm, off under load)."""
    robot, acts = _robot(tmp_path)
    chain, clock = _powered_up(robot, acts, -150.0)
    _home(robot, acts, chain, clock)
    res = float(acts.bus.resolution[6])
    want = round(-200.0 / res)
    clock.sleep(0.1)  # the shaft springs back once the torque is off
    released = ChainIO(chain, clock).read(7, X.PRESENT_POSITION, 4)
    give = COMPLIANCE * round(300.0 / 2.69)
    assert abs(released - (want + give)) <= 1.0, (released, want, give)
    assert abs(_press(chain, clock, round(300.0 / 2.69), want - 5000) - want) <= 1


def test_a_jam_is_told_from_the_stop_by_the_turns_phase(tmp_path):
    """Homed once against the stop; then, after a power-up, the stage jams at -143 mm (2.85 lead-screw turns above
    the stop): the stall there would make -143 mm read -200 mm. With the last homing in the state file the new
    offset differs from the old one by 3 mm less the stop's yield under the homing current (0.27 mm) modulo a
    turn, beyond stall_travel (0.6 mm): refused,
    naming the servo, nothing written. The true stop, homed again from elsewhere, passes the same check."""
    robot, acts = _robot(tmp_path)
    chain, clock = _powered_up(robot, acts, -150.0)
    first = HomingState(tuple(_home(robot, acts, chain, clock)))
    chain, clock = _powered_up(robot, acts, -143.0)
    chain.jam(7, 0.0)
    with pytest.raises(HomingError, match=r"^servo id 7 \(z\): stalled \+2\.7\d mm \(modulo one turn\) from where its"):
        _home(robot, acts, chain, clock, previous=first)
    assert chain.register(7, X.HOMING_OFFSET, 4) == 0  # nothing written
    chain, clock = _powered_up(robot, acts, -57.0)
    (again,) = _home(robot, acts, chain, clock, previous=first)
    assert abs(again.offset - first.servos[0].offset) % 4096 in (0, 1, 4095)


def test_the_stall_current_stays_within_the_force_cap(tmp_path):
    """With max_force = 50 N on the stage (20 mm lead: 50 N x 3.18 mm / 1.304 N*m/A = 122 mA, 45 units), a homing
    current of 300 mA would press with 111 units: refused naming robot.homing.z.current before anything moves;
    at 100 mA (37 units) it homes, and the stage streams in current-based position mode at the cap."""
    robot, acts = _robot(tmp_path, extra="max_force = 50.0\n")
    chain, clock = _powered_up(robot, acts, -150.0)
    with pytest.raises(HomingError, match=r"^robot\.homing\.z\.current: 300 mA presses with 1\d\d\.\d N, above its"):
        _home(robot, acts, chain, clock)
    assert not chain.torque(7) and chain.register(7, X.HOMING_OFFSET, 4) == 0
    robot, acts = _robot(tmp_path, Z_HOMING.replace("300.0", "100.0"), extra="max_force = 50.0\n")
    chain, clock = _powered_up(robot, acts, -150.0)
    (homed,) = _home(robot, acts, chain, clock)
    assert homed.name == "z"


def test_a_spool_is_homed_against_a_stop_only_when_allowed(tmp_path):
    """``method = "hard_stop"`` on a spool is one line naming robot.homing.s1c1.method (pressing a stop pulls its
    tendon); with allow_hard_stop = true the section is accepted."""
    spool = '\n[robot.homing.s1c1]\nmethod = "hard_stop"\nreference = -1.0\n'
    with pytest.raises(InputError, match=r"^robot\.homing\.s1c1\.method: \"hard_stop\" presses a spool") as e:
        _robot(tmp_path, Z_HOMING + spool)  # the robot file is read with its homing sections checked
    assert "\n" not in str(e.value)
    robot, acts = _robot(tmp_path, Z_HOMING + spool + "allow_hard_stop = true\n")
    assert read_homing(robot, acts)["s1c1"].method == "hard_stop"


class _PausingClock(VirtualClock):
    """A virtual clock whose `pause_at`-th sleep lasts `pause` s longer: the host stalls once (a loaded machine)."""

    def __init__(self, pause_at: int, pause: float) -> None:
        super().__init__()
        self.sleeps, self.pause_at, self.pause = 0, pause_at, pause

    def sleep(self, seconds: float) -> None:
        self.sleeps += 1
        super().sleep(seconds + (self.pause if self.sleeps == self.pause_at else 0.0))


@pytest.mark.parametrize("pause", [0.05, 0.3])
def test_a_host_silent_past_the_bus_watchdog_while_homing_is_named_at_once(tmp_path, pause):
    """The stage's Bus Watchdog (100 ms) runs while it homes. A host that pauses 0.3 s mid-move lets it stop the
    stage short of its stop: homing says so as soon as the shaft stands still, rather than waiting out the move's
    deadline and blaming a missing stop. A 0.05 s pause is within the watchdog: the stage homes."""
    robot, acts = _robot(tmp_path)
    chain, _ = _powered_up(robot, acts, -150.0)
    clock = _PausingClock(pause_at=200, pause=pause)  # 2 s into the move at 10 ms polls, 50 mm from the stop
    io = ChainIO(chain, clock)
    for dxl_id in acts.bus.ids:
        io.write(dxl_id, X.BUS_WATCHDOG, 5, 1, "bus watchdog")  # 5 x 20 ms
    homer = Homer(io, acts, dict(read_homing(robot, acts)), clock, lambda t: True)
    if pause < 0.1:
        (homed,) = homer.run()
        assert homed.method == "hard_stop"
        return
    with pytest.raises(HomingError, match=r"servo .*z.*: its bus watchdog stopped it while homing"):
        homer.run()
    spec = dict(read_homing(robot, acts))["z"]
    assert clock.now() < 2.0 * spec.travel / spec.speed  # named once the shaft stood still, not at the deadline
