"""Tendon force caps and the stream's trips (issue 38): current-based position mode with the Goal Current of each
tendon's max_tension, and the stop on over-tension, slack, over-temperature and under-voltage, injected into the
Dynamixel simulator mid-stream (in process, on one virtual clock: every run is the same on any machine)."""

from __future__ import annotations

import copy
import math

import dxl_helpers
import numpy as np
import pytest
from conftest import require_module
from dxl_helpers import Z_HOMING, Clock, robot_text

from crtraj.app.devices import admit_result
from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import HomingState, ServoChain, SimPort, X, open_dynamixel, state_path
from crtraj.hardware.dynamixel import _link as dynamixel
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._safety import AT_CAP, ForceCaps
from crtraj.hardware.dynamixel._sim_shaft import STALL_CURRENT
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.io.problem import load_robot

sim1_plan = dxl_helpers.sim1_plan  # the fixture, shared
PRETENSION = 20  # units (53.8 mA, 7.0 N on a 10 mm spool of the XM430-W210) each simulated tendon holds
MIN_TENSION = "min_tension = 2.0                  # N\n"


@pytest.fixture(autouse=True)
def _sdk():
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")


def _write(chain: ServoChain, dxl_id: int, addr: int, value: int, size: int, now: float = 0.0) -> int:
    """A WRITE to the chain as another program would send it; the status packet's error number."""
    params = addr.to_bytes(2, "little") + value.to_bytes(size, "little", signed=value < 0)
    reply = chain.handle(dxl.Packet(dxl_id, dxl.WRITE, params), now)
    return dxl.PacketReader().feed(b"".join(reply))[0].params[0] & 0x7F


@pytest.mark.parametrize("mode", [X.EXTENDED_POSITION, X.CURRENT_POSITION])
def test_the_simulator_caps_a_jammed_servo_as_its_mode_does(mode):
    """A jammed shaft whose goal runs on: in extended position mode (4) nothing but PWM Limit caps the current, so
    it climbs to the stall current (855 units, 2.3 A; half of it at PWM Limit 442.5 of 885); in current-based
    position mode (5) it stops at Goal Current (57 units). Goal Current above Current Limit is refused (data limit
    error), as the e-manual says. The position loop's rise is K_P (ref - pos) with K_P = 800 / 128 per tick."""
    chain = ServoChain([1], [1030], tau=0.0)
    assert _write(chain, 1, X.OPERATING_MODE, mode, 1) == 0
    assert _write(chain, 1, X.GOAL_CURRENT, X.CURRENT_LIMIT_DEFAULT + 1, 2) == dxl.ERR_DATA_LIMIT
    assert _write(chain, 1, X.GOAL_CURRENT, 57, 2) == 0
    assert _write(chain, 1, X.TORQUE_ENABLE, 1, 1, 0.0) == 0
    chain.jam(1, 0.0)
    assert _write(chain, 1, X.GOAL_POSITION, 400, 4, 0.0) == 0  # unlimited profile: the reference is there at once
    assert chain.current(1, 0.01) == (57 if mode == X.CURRENT_POSITION else STALL_CURRENT)
    assert chain.positions(0.01)[0] == 0.0  # jammed
    assert _write(chain, 1, X.GOAL_POSITION, 5, 4, 0.02) == 0
    assert chain.current(1, 0.03) == round(800 / 128 * 5)  # below either cap: the loop's output
    if mode == X.EXTENDED_POSITION:
        assert _write(chain, 1, X.TORQUE_ENABLE, 0, 1, 0.04) == 0
        assert _write(chain, 1, X.PWM_LIMIT, 442, 2, 0.04) == 0
        assert _write(chain, 1, X.TORQUE_ENABLE, 1, 1, 0.04) == 0
        assert _write(chain, 1, X.GOAL_POSITION, 400, 4, 0.05) == 0
        assert chain.current(1, 0.06) == int(STALL_CURRENT * 442 / 885)


def test_the_cap_converts_tension_through_spool_and_torque_constant_and_a_missing_one_is_refused(tmp_path):
    """Goal Current = floor(F r / k_t / 2.69 mA): 20 N on a 10 mm spool of an XM430-W210 (3.0 N*m / 2.3 A) is
    57 units; a declared torque_constant replaces the model's; a cable servo without max_tension, or a model crtraj
    does not know without torque_constant, is one line naming the field, before any port is opened."""
    robot = load_robot(dxl_helpers.ROBOT)
    caps = ForceCaps(Actuators.from_robot(robot))
    assert caps.refusal() is None
    assert list(caps.goal[:6]) == [math.floor(20.0 * 0.01 / (3.0 / 2.3) * 1000 / 2.69)] * 6 and caps.goal[6] == 0
    assert caps.tension(0, 57) == pytest.approx(57 * 2.69e-3 * (3.0 / 2.3) / 0.01)
    text = robot_text(Z_HOMING)
    cases = {
        "missing": (text.replace("max_tension = 20.0", "# no cap"), r"robot\.actuators\.servo\.s1c1\.max_tension"),
        "model": (
            text.replace("model = 1030 ", "model = 1060 "),
            r"robot\.actuators\.servo\.s1c1\.torque_constant: missing: model 1060",
        ),
    }
    for name, (body, pattern) in cases.items():
        f = tmp_path / f"{name}.toml"
        f.write_text(body)
        acts = Actuators.from_robot(load_robot(f))
        with pytest.raises(InputError, match=pattern) as exc:
            open_dynamixel("dynamixel:///dev/no-such-port", acts)
        assert "\n" not in str(exc.value)
    f = tmp_path / "kt.toml"
    f.write_text(text.replace("max_tension = 20.0", "max_tension = 20.0\ntorque_constant = 2.0"))
    assert list(ForceCaps(Actuators.from_robot(load_robot(f))).goal[:6]) == [math.floor(0.2 / 2.0 / 2.69e-3)] * 6


# ------------------------------------------------------------------- trips mid-stream
@pytest.fixture(scope="module")
def taut(sim1_plan, tmp_path_factory):
    """The robot file with min_tension 2 N (its homing state beside it), and servos homed at sim 1's start whose
    tendons each hold `PRETENSION`: (robot file, chain, device time reached)."""
    text = robot_text(Z_HOMING).replace(
        "max_tension = 20.0                 # N\n", "max_tension = 20.0\n" + MIN_TENSION
    )
    assert MIN_TENSION in text
    robot_file, chain, reached = dxl_helpers.homed_at(sim1_plan, tmp_path_factory.mktemp("robot") / "robot.toml", text)
    for i in chain.ids[:6]:
        chain.set_load(i, PRETENSION)
    return robot_file, chain, reached


class FaultPort(SimPort):
    """The simulator's port; `fault(chain, at)` happens at clock time `at` (s), and every packet records the
    device's true current of servo `watch` before it is handled: (clock time, units)."""

    def __init__(self, chain, clock, at: float, fault, watch: int) -> None:
        super().__init__(chain, clock, name="/dev/sim")
        self.at, self.fault, self.watch, self.done = at, fault, watch, False
        self.currents: list[tuple[float, int]] = []

    def writePort(self, packet) -> int:  # noqa: N802 - the SDK's name
        now = self.clock.now()
        if not self.done and now >= self.at:
            self.done = True
            self.fault(self.chain, self.at)
        self.currents.append((now, abs(self.chain.current(self.watch, now))))
        return super().writePort(packet)


def _faulted_stream(plan, taut, at: float, fault, watch: int = 1):
    """Sim 1 streamed to the taut servos with `fault` at `at` s after the start: (report, streamer, port, acts)."""
    robot_file, chain0, reached = taut
    motion = admit_result(str(plan), str(robot_file), rate=100.0)
    clock = Clock(reached)
    port = FaultPort(copy.deepcopy(chain0), clock, reached + at, fault, watch)
    old = dynamixel.port_factory
    dynamixel.port_factory = lambda sdk, name: port
    try:
        state = HomingState.load(state_path(robot_file))
        tr = open_dynamixel("dynamixel:///dev/sim", motion.actuators, homing=state, clock=clock, warn=lambda m: None)
        st = Streamer(tr, motion.actuators, StreamOptions(rate=motion.rate), None, clock=clock)
        rep = st.run_path(motion)
    finally:
        dynamixel.port_factory = old
    return rep, st, port, motion.actuators


def _event(rep, name: str) -> float:
    return next(t for t, n, _ in rep.events if n == name)


def test_a_jammed_spool_trips_within_two_periods_and_never_pulls_past_its_cap(sim1_plan, taut):
    """A spool jammed at 8 random (seeded) times of a sim-1 stream: the stream stops with status over-tension,
    naming the servo; the trip comes within 2 periods of the servo's true current (read from the simulator at
    every packet, not through the link) first reaching 95 % of its Goal Current; that current never exceeds the
    Goal Current (20 N of tension); the stop braked within the limits and the tendon stays at most at its cap."""
    duration = admit_result(str(sim1_plan), str(taut[0]), rate=100.0).stamps[-1]
    rng = np.random.default_rng(3840)
    worst, delays = [], []
    for at in rng.uniform(0.5, duration - 0.5, 8):
        rep, st, port, acts = _faulted_stream(sim1_plan, taut, float(at), lambda c, t: c.jam(1, t))
        caps = ForceCaps(acts)
        goal = int(caps.goal[0])
        assert rep.status == "over-tension", rep
        assert rep.message.startswith("servo id 1 (s1c1): pulls ") and "at its cap of 20 N" in rep.message
        t = np.array([x for x, _ in port.currents])
        i = np.array([c for _, c in port.currents])
        first = t[np.argmax(i >= AT_CAP * goal)]
        tripped = st._machine.t_start + _event(rep, "over-tension")
        delays.append((tripped - first) * 100.0)
        assert 0.0 <= tripped - first <= 2 * 0.01 + 1e-9, (at, tripped - first)
        assert i.max() <= goal  # mode 5: never past the cap
        worst.append(caps.tension(0, i.max()))
        assert rep.brakes == 1 and rep.latched == 0
    print(f"jam: worst tension {max(worst):.2f} N (cap 20 N); trip after the crossing: {max(delays):.2f} periods")


def test_a_cut_tendon_trips_slack(sim1_plan, taut):
    """A tendon cut mid-stream: its current collapses below min_tension's (2 N: 6 units) and the stream stops with
    status slack, naming the servo; before the cut the pretensioned tendons never tripped."""
    rep, st, port, _ = _faulted_stream(sim1_plan, taut, 1.5, lambda c, t: c.cut(3, t), watch=3)
    assert rep.status == "slack", rep
    assert rep.message.startswith("servo id 3 (s1c3): its tendon pulls 0.0 N, below min_tension 2 N")
    assert st._machine.t_start + _event(rep, "slack") - (port.at) <= 0.02 + 1e-9
    assert rep.brakes == 1 and rep.latched == 0


@pytest.mark.parametrize(
    ("fault", "status", "text"),
    [
        (lambda c, t: c.heat(5, 76, t), "over-temperature", "servo id 5 (s2c2): 76 deg C, within 5 of its"),
        (lambda c, t: c.supply(9.9, t), "under-voltage", "servo id 1 (s1c1): input 9.9 V, within 0.5 V of its"),
    ],
)
def test_heat_and_a_sagging_supply_trip_before_the_servo_shuts_down(sim1_plan, taut, fault, status, text):
    """Present Temperature 76 deg C (5 below the Temperature Limit 80), and a supply at 9.9 V (0.4 above the Min
    Voltage Limit 9.5 V): the stream stops with its status and the reading before the servo's own shutdown (the
    torque stays on: no hardware error bit is set)."""
    rep, _st, port, acts = _faulted_stream(sim1_plan, taut, 1.0, fault)
    assert rep.status == status and rep.message.startswith(text), rep
    assert all(port.chain.torque(i) for i in acts.bus.ids)
    assert not any(port.chain.register(i, X.HARDWARE_ERROR, 1) for i in acts.bus.ids)


class UnplugAfter(SimPort):
    """The simulator's port with the adapter pulled out at its `after`-th write (a packet of the connect)."""

    def __init__(self, chain, clock, name: str, after: int) -> None:
        super().__init__(chain, clock, name=name)
        self.after, self.writes = after, 0

    def writePort(self, packet) -> int:  # noqa: N802 - the SDK's name
        self.writes += 1
        if self.writes == self.after:
            self.unplug_at = self.clock.now()
        return super().writePort(packet)


def test_an_adapter_pulled_out_at_any_packet_of_the_connect_is_one_line(sim1_plan, taut, monkeypatch, capsys):
    """The adapter pulled out at 12 packets spread over the whole connect (pings, model checks, the watchdog, the
    drive mode, the power-up check, the force caps, the profiles, torque on): every time `crtraj stream` exits 1
    with one stderr line saying the link is lost, no traceback, and the SDK's busy flag released."""
    robot_file, chain0, reached = taut
    clock = Clock(reached)
    port = UnplugAfter(copy.deepcopy(chain0), clock, "/dev/sim", 0)
    monkeypatch.setattr(dynamixel, "port_factory", lambda sdk, name: port)
    acts = Actuators.from_robot(load_robot(robot_file))
    open_dynamixel("dynamixel:///dev/sim", acts, homing=state_path(robot_file), clock=clock, warn=lambda m: None)
    connect = port.writes  # the packets of one whole connect
    assert connect > 50
    for after in np.linspace(1, connect, 12).astype(int):
        sim = dxl_helpers.in_process(monkeypatch, copy.deepcopy(chain0), clock)
        sim.open = lambda after=after, sim=sim: UnplugAfter(sim.chain, clock, sim.path, int(after))
        sim.ports = []
        made = sim.open
        sim.open = lambda made=made, sim=sim: sim.ports.append(made()) or sim.ports[-1]
        code = main(["stream", str(sim1_plan), "--dynamixel", sim.path, "--robot", str(robot_file)])
        out = capsys.readouterr()
        err = out.err.strip().splitlines()
        assert code == 1, (after, out)
        assert len(err) == 1 and "the link to the servos is lost" in err[0], (after, err)
        assert "Traceback" not in out.out + out.err
        assert not sim.ports[-1].is_using


# ------------------------------------------------------------------- the safety registers at connect
def test_connect_sets_pwm_current_limit_and_shutdown_and_reads_back_the_limits(monkeypatch, tmp_path):
    """Servos left by another tool with PWM Limit 300 (a slowed servo), Current Limit 1000, Shutdown 0x34 (the
    factory's: no input voltage), Temperature Limit 70 and Min Voltage 10.5 V: after connect PWM Limit reads 885,
    each capped spool's Current Limit equals its Goal Current (57: 20 N), the uncapped stage keeps its Current
    Limit, Shutdown reads 0x35, and the limits the trips use are the ones read back (a 66 deg C reading trips, 64
    does not). A second connect writes none of these EEPROM registers again; a cap above the model's largest
    Current Limit (the simulator refuses it, data limit) is one line naming max_tension."""
    from dxl_helpers import homed_state, write

    from crtraj.hardware.dynamixel._safety import Reading

    acts = Actuators.from_robot(load_robot(dxl_helpers.ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models)
    for i in acts.bus.ids:
        for addr, value, size in ((X.PWM_LIMIT, 300, 2), (X.CURRENT_LIMIT, 1000, 2), (X.TEMPERATURE_LIMIT, 70, 1)):
            write(chain, i, addr, value, size)
        write(chain, i, X.MIN_VOLTAGE, 105, 2)
    state = homed_state(chain, acts)
    clock = Clock()
    eeprom = []
    handle = chain.handle

    def watch(packet, now):
        if packet.instruction == dxl.WRITE and int.from_bytes(packet.params[:2], "little") in (36, 38, 63):
            eeprom.append(int.from_bytes(packet.params[:2], "little"))
        return handle(packet, now)

    chain.handle = watch
    monkeypatch.setattr(dynamixel, "port_factory", lambda sdk, name: SimPort(chain, clock, name=name))
    tr = open_dynamixel("dynamixel:///dev/sim", acts, homing=state, clock=clock, warn=lambda m: None)
    assert [chain.register(i, X.PWM_LIMIT, 2) for i in acts.bus.ids] == [885] * 7
    assert [chain.register(i, X.CURRENT_LIMIT, 2) for i in acts.bus.ids] == [57] * 6 + [1000]
    assert [chain.register(i, X.GOAL_CURRENT, 2) for i in acts.bus.ids[:6]] == [57] * 6
    assert [chain.register(i, X.SHUTDOWN, 1) for i in acts.bus.ids] == [0x35] * 7
    assert sorted(set(eeprom)) == [36, 38, 63] and len(eeprom) == 7 + 6 + 7
    assert tr.caps.limits[1] == (70, 105, 160)
    assert tr.caps.trip(0, Reading(30, 120, 66))[0] == "over-temperature"
    assert tr.caps.trip(0, Reading(30, 120, 64)) is None
    assert tr.caps.trip(0, Reading(30, 109, 40))[0] == "under-voltage"  # within 0.5 V of the 10.5 V read back
    tr.close()
    eeprom.clear()
    for i in acts.bus.ids:
        write(chain, i, X.TORQUE_ENABLE, 0, 1, clock.now())
    open_dynamixel("dynamixel:///dev/sim", acts, homing=state, clock=clock, warn=lambda m: None).close()
    assert eeprom == []
    text = dxl_helpers.ROBOT.read_text().replace("max_tension = 20.0", "max_tension = 500.0")
    (path := tmp_path / "strong.toml").write_text(text)
    strong = Actuators.from_robot(load_robot(path))
    for i in acts.bus.ids:
        write(chain, i, X.TORQUE_ENABLE, 0, 1, clock.now())
    with pytest.raises(dynamixel.TransportError) as exc:
        open_dynamixel("dynamixel:///dev/sim", strong, homing=state, clock=clock, warn=lambda m: None)
    assert str(exc.value) == (
        "servo id 1 (s1c1): max tension 500 N needs 3833 mA, above the largest Current Limit its model takes: "
        "lower it in the robot file"
    )
