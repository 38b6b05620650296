"""Faults on a real robot's bus, injected into the Dynamixel simulator behind the command line (in process, on
one virtual clock shared by the streamer, the SDK's timeouts and the simulated servos: every run is the same
on any machine): the USB-serial adapter pulled out mid-stream (issue 38)."""

from __future__ import annotations

import copy
import json
import os
import termios
import tty

import dxl_helpers
import numpy as np
import pytest
import serial
from conftest import require_module
from dxl_helpers import Z_HOMING, Clock, in_process, robot_text

from crtraj.app.devices import admit_result
from crtraj.cli import main
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import HomingState, ServoChain, SimPort, home_in_place, robot_chain, state_path
from crtraj.io.problem import load_robot

sim1_plan = dxl_helpers.sim1_plan  # the fixture, shared
UNPLUGS = 50  # random unplug times, as the issue asks


@pytest.fixture(autouse=True)
def _sdk():
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")


@pytest.fixture(scope="module")
def homed_at_start(sim1_plan, tmp_path_factory):
    """The robot file (its homing state beside it), and servos homed standing at sim 1's start with the
    device time reached: what `crtraj sim-dynamixel --at` serves."""
    robot_file = tmp_path_factory.mktemp("robot") / "robot.toml"
    robot_file.write_text(robot_text(Z_HOMING))
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    start = admit_result(str(sim1_plan), str(robot_file), rate=100.0).values[0]
    chain = robot_chain(robot, acts, start)
    homed, reached = home_in_place(robot, acts, chain, start)
    HomingState(tuple(homed)).save(state_path(robot_file))
    return robot_file, chain, reached


def _fresh(robot_file, where):
    """A copy of the robot file and its homing state file in the folder `where` (a stream records where it let
    the servos go in the state file: each run starts from the fixture's)."""
    where.mkdir(parents=True, exist_ok=True)
    copy_file = where / robot_file.name
    copy_file.write_text(robot_file.read_text())
    state_path(copy_file).write_text(state_path(robot_file).read_text())
    return copy_file


class Unplugged:
    """Opens the ports of an in-process simulator with the adapter pulled out at clock time `at` (s)."""

    def __init__(self, sim, at: float | None) -> None:
        self.sim, self.at, self._open = sim, at, sim.open
        sim.open = self.open

    def open(self) -> SimPort:
        port = self._open()
        port.unplug_at = self.at
        return port


def _stream(monkeypatch, tmp_path, plan, homed, at: float | None):
    """`crtraj stream` of `plan` to servos homed at its start, the adapter pulled out at clock time `at` (None:
    never): (exit code, the log's records, the SimPort, the clock's start and end)."""
    robot_file, chain, reached = homed
    robot_file = _fresh(robot_file, tmp_path / f"robot-{at}")
    clock = Clock(reached)
    sim = in_process(monkeypatch, copy.deepcopy(chain), clock)
    Unplugged(sim, at)
    log = tmp_path / f"stream-{at}.jsonl"
    argv = ["stream", str(plan), "--dynamixel", sim.path, "--robot", str(robot_file), "--log", str(log)]
    code = main(argv)
    records = [json.loads(x) for x in log.read_text().splitlines()]
    return code, records, sim.ports[-1], reached, clock.now()


def test_closing_a_pseudo_terminal_raises_what_the_simulated_unplug_raises():
    """The unplug model is pyserial's behaviour: a port whose pseudo-terminal was closed (the adapter gone)
    raises SerialException on a write and a read, OSError for the bytes waiting, termios.error for a flush;
    `SimPort` raises the same types and messages."""
    master, slave = os.openpty()
    tty.setraw(master)
    name = os.ttyname(slave)
    os.close(slave)
    ser = serial.Serial(name, 1_000_000, timeout=0)
    os.close(master)
    calls = {"write": lambda: ser.write(b"x"), "read": lambda: ser.read(4)}
    calls |= {"in_waiting": lambda: ser.in_waiting, "flush": ser.reset_input_buffer}
    real = {}
    for what, call in calls.items():
        with pytest.raises((serial.SerialException, OSError, termios.error)) as exc:
            call()
        real[what] = (type(exc.value), str(exc.value))
    ser.close()
    port = SimPort(_chain(), Clock())
    port.unplug_at = 0.0
    sim_calls = {"write": lambda: port.writePort(b"x"), "read": lambda: port.readPort(4)}
    sim_calls |= {"in_waiting": port.getBytesAvailable, "flush": port.clearPort}
    for what, call in sim_calls.items():
        with pytest.raises(real[what][0]) as exc:
            call()
        assert (type(exc.value), str(exc.value)) == real[what], what


def _chain():
    from crtraj.hardware.dynamixel import ServoChain

    return ServoChain([1], [1020])


def test_unplugging_the_adapter_at_random_times_always_ends_link_lost_with_a_report(
    sim1_plan, homed_at_start, tmp_path, monkeypatch, capsys
):
    """The adapter pulled out at 50 random (seeded) times during a sim-1 stream: every time the command exits 1
    with one stderr line (status link_lost, naming the port), no traceback, the log ends with the report
    (status link_lost), and the SDK's busy flag is released."""
    code, records, _, t0, t1 = _stream(monkeypatch, tmp_path, sim1_plan, homed_at_start, None)
    assert code == 0 and records[-1]["status"] == "done"
    capsys.readouterr()
    rng = np.random.default_rng(38)
    moves = []
    for at in np.sort(rng.uniform(t0, t1, UNPLUGS)):
        code, records, port, _, _ = _stream(monkeypatch, tmp_path, sim1_plan, homed_at_start, float(at))
        out = capsys.readouterr()
        err = out.err.strip().splitlines()
        assert code == 1, (at, out)
        assert len(err) == 1 and err[0].startswith("crtraj: stream failed: link_lost: transport error: "), err
        assert "the link to the servos is lost" in err[0] and "Traceback" not in out.out + out.err
        report = records[-1]
        assert report["type"] == "report" and report["status"] == "link_lost", report
        assert port.unplugged() and not port.is_using
        moves.append(report["moves"])
    assert min(moves) < max(moves)  # the unplugs fell at different points of the stream
    print(f"unplugged at {UNPLUGS} times: moves before the unplug {min(moves)}..{max(moves)}")


class OneFailingCall(SimPort):
    """A `SimPort` unplugged for one of its calls only (`failing`): the others go on as before, so each error
    type pyserial raises reaches the link by itself."""

    failing = ""

    def unplugged(self) -> bool:
        return super().unplugged() and _caller() == self.failing


def _caller() -> str:
    import inspect

    return inspect.stack()[2].function


@pytest.mark.parametrize("failing", ["writePort", "readPort", "clearPort"])
def test_each_serial_error_becomes_the_links_error_and_releases_the_sdks_busy_flag(failing, monkeypatch):
    """Whichever port call fails first (a SerialException from a write or read, a termios.error from a flush),
    the link raises its `LinkLostError` naming the port, the SDK's busy flag is released, every later send
    refuses at once without touching the port, and close does not raise."""
    from dxl_helpers import homed_state

    from crtraj.hardware.dynamixel import _link as dynamixel
    from crtraj.hardware.transport import LinkLostError
    from crtraj.io.problem import load_robot as load

    acts = Actuators.from_robot(load(dxl_helpers.ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(acts.lower * 0.0))
    clock = Clock()
    state = homed_state(chain, acts)
    made = []

    def factory(sdk, name):
        made.append(OneFailingCall(chain, clock, name=name))
        made[-1].failing = failing
        return made[-1]

    monkeypatch.setattr(dynamixel, "port_factory", factory)
    tr = dynamixel.open_dynamixel("dynamixel:///dev/sim", acts, homing=state, clock=clock, warn=lambda m: None)
    tr.send(_ping())
    assert tr.receive()
    made[0].unplug_at = clock.now()
    with pytest.raises(LinkLostError, match=r"^/dev/sim: the link to the servos is lost \((SerialException|error): "):
        tr.receive()
    assert not made[0].is_using
    writes = chain.counts["packets"]
    with pytest.raises(LinkLostError):
        tr.send(_ping(kind="move", values=acts.bus.values(acts.bus.ticks(acts.lower * 0.0))))
    assert chain.counts["packets"] == writes
    tr.close()


def _ping(kind: str = "ping", values=None) -> bytes:
    from crtraj.hardware.protocol import MOVE, PING, Frame

    if kind == "ping":
        return Frame(PING, 1, 0.0, np.array([0.01]), session=1).encode()
    return Frame(MOVE, 2, 0.0, np.asarray(values), session=1).encode()


# ------------------------------------------------------------ the host dies: the Bus Watchdog stops the servos
KILLS = 20  # random kill times


class HostKilled(BaseException):
    """The host process is gone (SIGKILL): nothing after it runs, nothing more reaches the bus."""


class KillingClock(Clock):
    """The shared virtual clock; the host dies when it first sleeps past `at` (s)."""

    def __init__(self, start: float, at: float) -> None:
        super().__init__(start)
        self.at = at

    def sleep(self, s: float) -> None:
        super().sleep(s)
        if self.now() >= self.at:
            raise HostKilled


class MortalPort(SimPort):
    """The host's port on a `KillingClock`: once the host is dead nothing it would still send reaches the bus
    (a SIGKILL runs no `finally`; here the raised `HostKilled` does, so its writes are dropped)."""

    def writePort(self, packet) -> int:  # noqa: N802 - the SDK's name
        if self.clock.now() >= self.clock.at:
            return len(bytes(packet))
        return super().writePort(packet)


def _killed_stream(sim1_plan, homed, at: float):
    """Sim 1 streamed through the link to servos homed at its start; the host killed at clock time `at`.
    (chain, actuators, robot file, homing state, the kill time)."""
    from crtraj.hardware.dynamixel import open_dynamixel
    from crtraj.hardware.stream import Streamer, StreamOptions

    robot_file, chain0, reached = homed
    chain = copy.deepcopy(chain0)
    motion = admit_result(str(sim1_plan), str(robot_file), rate=100.0)
    acts = motion.actuators
    clock = KillingClock(reached, reached + at)
    state = HomingState.load(state_path(robot_file))
    from crtraj.hardware.dynamixel import _link as dynamixel

    port = MortalPort(chain, clock, name="/dev/sim")
    dynamixel.port_factory = lambda sdk, name: port
    tr = open_dynamixel("dynamixel:///dev/sim", acts, homing=state, clock=clock, warn=lambda m: None, max_misses=50)
    st = Streamer(tr, acts, StreamOptions(rate=motion.rate, watchdog=10.0), None, clock=clock)
    with pytest.raises(HostKilled):
        st.run_path(motion)
    return chain, acts, robot_file, state, clock.now()


def test_a_killed_host_is_stopped_by_the_bus_watchdog_within_the_acceleration_limits(
    sim1_plan, homed_at_start, monkeypatch
):
    """The host killed at 20 random (seeded) times of a sim-1 stream: the Bus Watchdog (100 ms) stops every
    servo; an independent dense check of the simulated shafts (1 ms finite differences) after the kill stays
    within each actuator's acceleration limit (plus one unit of the profile register, which rounds up), every
    servo comes to rest, and the next stream refuses the stage until it is homed again."""
    from crtraj.hardware.dynamixel import X, open_dynamixel
    from crtraj.hardware.dynamixel import _link as dynamixel

    monkeypatch.setattr(dynamixel, "port_factory", dynamixel.port_factory)
    duration = admit_result(str(sim1_plan), str(homed_at_start[0]), rate=100.0).stamps[-1]
    rng = np.random.default_rng(3838)
    worst = []
    for at in rng.uniform(0.5, duration, KILLS):
        chain, acts, _, state, killed = _killed_stream(sim1_plan, homed_at_start, float(at))
        dt = 1e-3
        t = killed + dt * np.arange(3001)
        shafts = np.array([chain.shaft(x) for x in t])
        acc = np.abs(np.diff(shafts, 2, axis=0)) / dt**2  # ticks/s^2
        ticks_per = np.asarray(acts.bus.ticks_per_rev) / np.asarray(acts.bus.per_rev)
        bound = acts.amax * ticks_per + X.ACCELERATION_UNIT / 3600.0 * np.asarray(acts.bus.ticks_per_rev)
        worst.append(float(np.max(acc / bound)))
        assert worst[-1] <= 1.0 + 1e-6, (at, worst[-1])
        assert np.max(np.abs(shafts[-1] - shafts[-101])) < 0.5  # at rest (ticks over the last 0.1 s)
        assert [chain.register(i, X.BUS_WATCHDOG, 1) for i in acts.bus.ids] == [X.WATCHDOG_TRIPPED] * 7
    clock = Clock(t[-1])
    port = SimPort(chain, clock, name="/dev/sim")
    dynamixel.port_factory = lambda sdk, name: port
    for _ in range(2):  # refused, and still refused the next time (the error was cleared, the marker too)
        with pytest.raises(Exception, match=r"servo id 7 \(z\): (its bus watchdog stopped it|not homed)") as exc:
            open_dynamixel("dynamixel:///dev/sim", acts, homing=state, clock=clock, warn=lambda m: None)
        assert "\n" not in str(exc.value)
    assert [chain.register(i, X.BUS_WATCHDOG, 1) for i in acts.bus.ids] == [5] * 7  # set again: 100 ms
    print(f"worst acceleration after a kill / limit: {max(worst):.3f} (median {np.median(worst):.3f})")


def test_a_host_killed_while_homing_leaves_the_stage_stopped_by_its_watchdog(tmp_path, monkeypatch, capsys):
    """`crtraj home` killed at 10 random (seeded) times while the stage travels toward its stop (current-based
    position mode, the goal 1.1 x its range away): without a watchdog it would go on pressing toward that goal.
    The Bus Watchdog stops it: after the kill the shaft travels at most the closed form v (T_wd + tau) +
    v^2 / (2 a) (homing speed v, profile acceleration a, watchdog T_wd, motor lag tau), its dense 1 ms
    accelerations stay within a, it comes to rest, and the register reads -1."""
    from crtraj.hardware.dynamixel import X, read_homing, stops

    robot_file = tmp_path / "robot.toml"
    robot_file.write_text(robot_text(Z_HOMING))
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    spec = read_homing(robot, acts)["z"]
    lead, tpr = float(acts.bus.per_rev[6]), int(acts.bus.ticks_per_rev[6])
    v = spec.speed * tpr / lead  # ticks/s (the profile velocity register rounds it down)
    a = (np.ceil(float(acts.amax[6]) / lead * 3600 / X.ACCELERATION_UNIT) * X.ACCELERATION_UNIT / 3600) * tpr
    tau = 0.03
    bound = v * (0.1 + tau) + v * v / (2 * a)
    rng = np.random.default_rng(3839)
    travelled = []
    for at in rng.uniform(0.3, 2.3, 10):
        x = np.array([0.0, 0.0, 0.0, 0.0, -150.0])
        chain = ServoChain(
            acts.bus.ids,
            acts.bus.models,
            initial=acts.bus.ticks(acts.command(robot.cables(x))),
            stops=stops(robot, acts),
            tau=tau,
        )
        chain.power_cycle(0.0)
        clock = KillingClock(0.0, float(at))
        sim = in_process(monkeypatch, chain, clock)
        sim.open = lambda sim=sim, clock=clock: MortalPort(sim.chain, clock, name=sim.path)
        with pytest.raises(HostKilled):
            main(["home", "--dynamixel", sim.path, "--robot", str(robot_file)])
        killed = clock.now()
        t = killed + 1e-3 * np.arange(2001)
        z = np.array([chain.shaft(x)[6] for x in t])
        travelled.append(float(np.max(np.abs(z - z[0]))))
        assert travelled[-1] <= bound, (at, travelled[-1], bound)
        assert np.max(np.abs(np.diff(z, 2))) / 1e-6 <= a * (1 + 1e-9)
        assert abs(z[-1] - z[-101]) < 0.5 and chain.register(7, X.BUS_WATCHDOG, 1) == X.WATCHDOG_TRIPPED
        assert not os.path.exists(state_path(robot_file))  # nothing written by the killed homing
    capsys.readouterr()
    mm = lead / tpr
    print(f"travel after a kill while homing: max {max(travelled) * mm:.3f} mm (bound {bound * mm:.3f})")


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", 0.1),
        ("bus_watchdog = 0.5", 0.5),
        ("bus_watchdog = 3.0", "robot.stop.bus_watchdog"),
        ("bus_watchdog = 0", ""),
    ],
)
def test_the_bus_watchdog_is_read_from_the_robot_file_within_its_range(tmp_path, text, expected):
    """``[robot.stop] bus_watchdog`` (s): default 0.1; outside 0.02..2.54 one line naming the key; the link writes
    it in 20 ms units (0.5 s -> 25)."""
    from crtraj.core.errors import InputError
    from crtraj.hardware.dynamixel import read_stop, watchdog_units

    (path := tmp_path / "robot.toml").write_text(robot_text(Z_HOMING) + f"\n[robot.stop]\n{text}\n")
    if isinstance(expected, float):
        seconds = read_stop(load_robot(path)).bus_watchdog
        assert seconds == expected and watchdog_units(seconds) == round(expected / 0.02)
        return
    with pytest.raises(InputError) as exc:
        read_stop(load_robot(path))
    assert "robot.stop.bus_watchdog" in str(exc.value) and "\n" not in str(exc.value), str(exc.value)


# ------------------------------------------------------------ a lost turn count behind the homed marker's back
def _connect(chain, reached, robot_file):
    """Open the link to `chain` with the robot file's homing state file (the stream's check), at `reached`."""
    from crtraj.hardware.dynamixel import _link as dynamixel

    acts = Actuators.from_robot(load_robot(robot_file))
    clock = Clock(reached)
    port = SimPort(chain, clock, name="/dev/sim")
    dynamixel.port_factory = lambda sdk, name: port
    return dynamixel.open_dynamixel(
        "dynamixel:///dev/sim", acts, homing=state_path(robot_file), clock=clock, warn=lambda m: None
    )


def _move_stage(chain, now: float, robot_file) -> float:
    """Through the link (the stream's check passes), move the stage 2.5 turns within its limits and let it go:
    its turn count is then not the one of its power-up, and the state file records where it was let go. The
    device time reached."""
    from crtraj.hardware.dynamixel import X, windows

    link = _connect(chain, now, robot_file)
    lo, hi = windows(Actuators.from_robot(load_robot(robot_file)))[6]
    here = chain.register(7, X.PRESENT_POSITION, 4)
    goal = here - 10_240 if here - 10_240 > lo else here + 10_240
    assert lo < goal < hi
    link.write(7, X.GOAL_POSITION, goal & 0xFFFFFFFF, 4, "goal position")
    for _ in range(200):  # 10 s of device time, read every 50 ms (within the bus watchdog)
        link._clock.sleep(0.05)
        if link.read(7, X.PRESENT_POSITION, 4) == goal:
            break
    assert chain.register(7, X.PRESENT_POSITION, 4) == goal
    link.close()
    assert HomingState.load(state_path(robot_file)).get(7).last == goal
    return link._clock.now()


def _clear(chain, dxl_id: int, now: float) -> None:
    from crtraj.hardware.dynamixel import _protocol as dxl

    (reply,) = chain.handle(dxl.Packet(dxl_id, dxl.CLEAR, dxl.CLEAR_MULTI_TURN), now)
    assert dxl.PacketReader().feed(reply)[0].params[0] == 0  # done (torque off)


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("none", None),
        ("mode 3", r"servo id 7 \(z\): Operating Mode reads 3, not 4 or 5 \(multi-turn\)"),
        ("mode 3 and back to 4", r"servo id 7 \(z\): reads -?\d+ ticks, [+-]\d+\.\d\d turns from where crtraj left it"),
        ("clear", r"servo id 7 \(z\): reads -?\d+ ticks, [+-]\d+\.\d\d turns from where crtraj left it"),
    ],
)
def test_a_lost_turn_count_behind_a_lit_marker_is_refused(homed_at_start, tmp_path, monkeypatch, fault, message):
    """The homed marker (LED) stays lit through three documented losses of the turn count: Operating Mode 3 (the
    simulator models it), mode 3 and back, and the Clear instruction. The first is refused by the mode read back,
    the others by the reading whole turns from where crtraj let the stage go; an untouched chain connects."""
    from dxl_helpers import write

    from crtraj.core.errors import InputError
    from crtraj.hardware.dynamixel import X
    from crtraj.hardware.dynamixel import _link as dynamixel

    monkeypatch.setattr(dynamixel, "port_factory", dynamixel.port_factory)
    robot_file, chain0, reached = homed_at_start
    robot_file, chain = _fresh(robot_file, tmp_path), copy.deepcopy(chain0)
    reached = _move_stage(chain, reached, robot_file)
    before = chain.register(7, X.PRESENT_POSITION, 4)
    write(chain, 7, X.TORQUE_ENABLE, 0, 1, reached)  # another program (a servo tool) takes over the stage
    if fault.startswith("mode 3"):
        write(chain, 7, X.OPERATING_MODE, X.POSITION, 1, reached)
    if fault == "mode 3 and back to 4":
        write(chain, 7, X.OPERATING_MODE, X.EXTENDED_POSITION, 1, reached)
    if fault == "clear":
        _clear(chain, 7, reached)
    after = chain.register(7, X.PRESENT_POSITION, 4)
    assert chain.register(7, X.LED, 1) == 1  # the marker still lit
    assert (after - before) % 4096 == 0 and (after == before) == (fault == "none")  # whole turns lost
    if message is None:
        _connect(chain, reached, robot_file).close()
        return
    with pytest.raises(InputError, match=message) as exc:
        _connect(chain, reached, robot_file)
    assert "\n" not in str(exc.value) and str(exc.value).endswith(f"--robot {robot_file}") is False
    assert "run crtraj home" in str(exc.value)


def test_torque_on_in_mode_3_loses_the_turn_count_and_a_clear_needs_the_torque_off():
    """The simulator, as the e-manual says: torque on in mode 3 wraps the reading into one turn plus the Homing
    Offset (the LED untouched); the Clear instruction is refused (result fail) while the torque is on."""
    from dxl_helpers import write

    from crtraj.hardware.dynamixel import X
    from crtraj.hardware.dynamixel import _protocol as dxl

    chain = ServoChain([1], [1020], initial=[-8 * 4096 + 100])
    write(chain, 1, X.LED, 1, 1)
    write(chain, 1, X.OPERATING_MODE, X.EXTENDED_POSITION, 1)
    write(chain, 1, X.TORQUE_ENABLE, 1, 1)
    (reply,) = chain.handle(dxl.Packet(1, dxl.CLEAR, dxl.CLEAR_MULTI_TURN), 0.0)
    assert dxl.PacketReader().feed(reply)[0].params[0] == dxl.ERR_RESULT_FAIL
    assert chain.register(1, X.PRESENT_POSITION, 4) == -8 * 4096 + 100
    write(chain, 1, X.TORQUE_ENABLE, 0, 1)
    chain.handle(dxl.Packet(1, dxl.WRITE, bytes([X.OPERATING_MODE, 0, X.POSITION])), 0.0)
    assert chain.register(1, X.PRESENT_POSITION, 4) == 100  # 8 turns lost: 100 ticks into its turn
    write(chain, 1, X.OPERATING_MODE, X.EXTENDED_POSITION, 1)
    chain.turn_by_hand(1, 3 * 4096)
    write(chain, 1, X.OPERATING_MODE, X.POSITION, 1)  # already counted 3 turns: switching loses them
    assert chain.register(1, X.PRESENT_POSITION, 4) == 100 and chain.register(1, X.LED, 1) == 1
    chain.turn_by_hand(1, 2 * 4096)  # in mode 3 with the torque off the shaft turns 2 turns: it reads them
    assert chain.register(1, X.PRESENT_POSITION, 4) == 100 + 2 * 4096
    write(chain, 1, X.TORQUE_ENABLE, 1, 1)  # torque on in mode 3: the turns are lost, the LED still lit
    assert chain.register(1, X.PRESENT_POSITION, 4) == 100 and chain.register(1, X.LED, 1) == 1


# ------------------------------------------------------------ Drive Mode bit 3: torque on by goal update
def test_torque_on_by_goal_update_is_refused_on_the_servo_and_in_the_robot_file(tmp_path, monkeypatch):
    """Drive Mode bit 3 found on a servo: one line naming the bit and how to clear it, before anything is written
    (torque off, Return Delay Time still the factory's); declared in the robot file: one line naming the key."""
    from dxl_helpers import homed_state, write

    from crtraj.core.errors import InputError
    from crtraj.hardware.dynamixel import X
    from crtraj.hardware.dynamixel import _link as dynamixel
    from crtraj.hardware.transport import TransportError

    monkeypatch.setattr(dynamixel, "port_factory", dynamixel.port_factory)
    acts = Actuators.from_robot(load_robot(dxl_helpers.ROBOT))
    chain = ServoChain(acts.bus.ids, acts.bus.models)
    write(chain, 3, X.DRIVE_MODE, X.DRIVE_TORQUE_ON_GOAL, 1)
    port = SimPort(chain, Clock(), name="/dev/sim")
    dynamixel.port_factory = lambda sdk, name: port
    with pytest.raises(TransportError) as exc:
        dynamixel.open_dynamixel("dynamixel:///dev/sim", acts, homing=homed_state(chain, acts), warn=lambda m: None)
    text = str(exc.value)
    assert text == (
        "servo id 3 (s1c3): Drive Mode 0x08 has bit 3 (torque on by goal update) set; crtraj does not support "
        "torque on by goal update (a goal would re-enable a stopped servo): clear bit 3 of register 10 (e.g. with "
        "Dynamixel Wizard)"
    )
    assert [chain.register(i, X.RETURN_DELAY, 1) for i in acts.bus.ids] == [X.RETURN_DELAY_DEFAULT] * 7
    assert not any(chain.torque(i) for i in acts.bus.ids) and chain.register(3, X.DRIVE_MODE, 1) == 0x08
    text = dxl_helpers.ROBOT.read_text().replace(
        "lead = 20.0", "drive_mode = { torque_on_by_goal_update = true }\nlead = 20.0"
    )
    assert "torque_on_by_goal_update" in text
    (path := tmp_path / "robot.toml").write_text(text)
    with pytest.raises(InputError) as exc:
        load_robot(path)
    assert str(exc.value) == (
        "robot.actuators.z.drive_mode.torque_on_by_goal_update: crtraj does not support torque on by goal update "
        "(a goal would re-enable a stopped servo): remove this key from the robot file"
    )


# ------------------------------------------------------------ crtraj home --check
def test_home_check_reports_each_actuators_position_without_writing(homed_at_start, tmp_path, monkeypatch, capsys):
    """`crtraj home --check`: servos homed at sim 1's start are all proven (exit 0); after the stage is switched
    to mode 3 behind its marker's back, and after a power cycle, the stage is not proven with the reason, the
    spools still are (unwrapped), exit 1 with one stderr line; no WRITE, SYNC WRITE or CLEAR reaches the bus."""
    from dxl_helpers import write

    from crtraj.hardware.dynamixel import X
    from crtraj.hardware.dynamixel import _protocol as dxl

    robot_file, chain0, reached = homed_at_start
    robot_file, chain = _fresh(robot_file, tmp_path), copy.deepcopy(chain0)
    sim = in_process(monkeypatch, chain, Clock(reached))
    seen = []
    handle = chain.handle
    chain.handle = lambda packet, now: seen.append(packet.instruction) or handle(packet, now)
    argv = ["home", "--check", "--dynamixel", sim.path, "--robot", str(robot_file)]
    names = Actuators.from_robot(load_robot(robot_file)).names
    assert main(argv) == 0
    assert capsys.readouterr().out.splitlines() == [f"{n}: proven" for n in names]
    for fault in ("mode 3", "power cycle"):
        if fault == "mode 3":
            write(chain, 7, X.OPERATING_MODE, X.POSITION, 1, reached)
        else:
            chain.power_cycle(reached)
        seen.clear()
        assert main(argv) == 1
        out = capsys.readouterr()
        lines = out.out.splitlines()
        assert lines[:-1] == [f"{n}: proven" for n in names[:-1]], lines
        why = "Operating Mode reads 3" if fault == "mode 3" else "not homed since its last power-up"
        assert lines[-1].startswith(f"z: not proven: servo id 7 (z): {why}"), lines[-1]
        err = out.err.strip().splitlines()
        assert err == [f"crtraj: home --check: position not proven for z; run crtraj home --dynamixel {sim.path} "
                       f"--robot {robot_file}"], err  # fmt: skip
        assert seen and not {dxl.WRITE, dxl.SYNC_WRITE, dxl.CLEAR, dxl.REBOOT} & set(seen)


class FreezingClock(Clock):
    """The shared virtual clock; the host freezes once for `pause` s when it first sleeps past `at` (s)."""

    def __init__(self, start: float, at: float, pause: float) -> None:
        super().__init__(start)
        self.at, self.pause = at, pause

    def sleep(self, s: float) -> None:
        super().sleep(s)
        if self.pause and self.now() >= self.at:
            pause, self.pause = self.pause, 0.0
            super().sleep(pause)


@pytest.mark.parametrize(("pause", "status"), [(0.15, "error"), (0.06, "done")])
def test_a_host_frozen_longer_than_the_watchdog_mid_stream_stops_naming_the_servo(
    sim1_plan, homed_at_start, monkeypatch, pause, status
):
    """A host frozen 150 ms mid-stream (nothing sent): the servos' watchdog (100 ms) stopped them, the next sync
    read sees it and the stream stops, naming the first servo; frozen 60 ms (within the watchdog) it completes."""
    from crtraj.hardware.dynamixel import _link as dynamixel
    from crtraj.hardware.dynamixel import open_dynamixel
    from crtraj.hardware.stream import Streamer, StreamOptions

    monkeypatch.setattr(dynamixel, "port_factory", dynamixel.port_factory)
    robot_file, chain0, reached = homed_at_start
    chain = copy.deepcopy(chain0)
    motion = admit_result(str(sim1_plan), str(robot_file), rate=100.0)
    clock = FreezingClock(reached, reached + 5.0, pause)
    port = SimPort(chain, clock, name="/dev/sim")
    dynamixel.port_factory = lambda sdk, name: port
    state = HomingState.load(state_path(robot_file))
    tr = open_dynamixel("dynamixel:///dev/sim", motion.actuators, homing=state, clock=clock, warn=lambda m: None)
    rep = Streamer(tr, motion.actuators, StreamOptions(rate=motion.rate, watchdog=10.0), None, clock=clock).run_path(
        motion
    )
    assert rep.status == status, rep.message
    if status == "error":
        assert "servo id 1 (s1c1): its bus watchdog stopped it (no instruction for 100 ms)" in rep.message
