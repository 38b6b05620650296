"""The Dynamixel link through the official SDK against the Protocol 2.0 simulator, in process (`SimPort`):
connection checks (one line each), faults, torque off on e-stop and exit, and the paper's simulation 2
streamed end to end. The streamer and the simulated servos share a virtual clock: no wall-clock timing."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import paper_copy, require_module
from dxl_helpers import InProcessSim, homed_state, serve_in_process

from crtraj.app.devices import admit_result
from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.core.errors import AdmissionError, InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.dynamixel._link import DynamixelTransport, open_dynamixel
from crtraj.hardware.dynamixel._protocol import HW_OVERHEATING, HW_OVERLOAD, X
from crtraj.hardware.dynamixel._protocol import crc16 as dxl_crc16
from crtraj.hardware.dynamixel._protocol import status as dxl_status
from crtraj.hardware.dynamixel._sim_chain import ServoChain
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.hardware.transport import TransportError
from crtraj.world.scene import Scene


class Clock(VirtualClock):
    """Virtual time shared by the streamer and the simulated servos (which call it); `events` run a callback
    once at a time."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[tuple[float, object]] = []

    def __call__(self) -> float:
        return self.now()

    def sleep(self, s: float) -> None:
        super().sleep(s)
        for ev in [e for e in self.events if e[0] <= self.now()]:
            self.events.remove(ev)
            ev[1]()


@pytest.fixture(autouse=True)
def _sdk(monkeypatch):
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    serve_in_process(monkeypatch)  # the simulators below answer in process, on their virtual clock


@pytest.fixture
def acts(robot):
    return Actuators.from_robot(robot)


def _motion(robot, acts, seconds: float = 1.0, rate: float = 100.0):
    """A short admitted motion among no obstacles (as a successful plan of this robot would be)."""
    x0, x1 = robot.straight(0.0), np.array([0.3, -0.2, 0.1, 0.4, -10.0])
    s = np.linspace(0, 1, 11)
    X = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    record = MotionRecord("", "plan", "success", True, True, 0, 0, robot, Scene(), seconds * s, robot.cables(X))
    return admit(record, acts, rate=rate)


def _sim(acts, clock, start=None, **kw) -> InProcessSim:
    bus = acts.bus
    initial = None if start is None else bus.ticks(start)
    chain = ServoChain(bus.ids, bus.models, initial=initial, **kw)
    return InProcessSim(chain, clock=clock, wire_time=False).start()


def _stream(sim, acts, motion, clock, misses: int = 50, **opts):
    """Streamer and link on the simulator, all on `clock` (the SDK's reply timeouts too: the simulator answers in
    process). A test that is not about faults tolerates `misses` failed reads in a row, and the telemetry
    watchdog waits 10 s."""
    state = homed_state(sim.chain, acts, clock.now())  # the readings are absolute: homed where they stand
    tr = open_dynamixel(
        f"dynamixel://{sim.path}",
        acts,
        warn=lambda m: None,
        max_misses=misses,
        stop_torque="off",
        homing=state,
        clock=clock,
    )
    opts.setdefault("watchdog", 10.0)
    st = Streamer(tr, acts, StreamOptions(rate=motion.rate, **opts), None, clock=clock)
    return st, tr


def _settled(sim, acts, motion, clock) -> bool:
    """The servos' present positions (whole ticks, as they report them) are within the settle tolerance
    (rad, mm) of the final set-point: where the streamer's settle check saw them, the torque then off."""
    present = acts.bus.values(np.rint(sim.chain.positions(clock.now())))
    return bool(np.max(np.abs(present - motion.values[-1])) <= StreamOptions().settle_tolerance * (1 + 1e-9))


def _one_line_error(exc_info, *parts: str) -> str:
    text = str(exc_info.value)
    assert "\n" not in text
    for p in parts:
        assert p in text, text
    return text


# ------------------------------------------------------------ connect
def test_missing_port_is_one_line(acts, tmp_path):
    with pytest.raises(TransportError) as e:
        DynamixelTransport(str(tmp_path / "ttyUSB9"), 1_000_000, acts)
    _one_line_error(e, "ttyUSB9: no such port", "U2D2")


def test_not_a_bus_rate_is_one_line(acts):
    with pytest.raises(InputError) as e:
        DynamixelTransport("/dev/null", 12345, acts)
    _one_line_error(e, "--baud: 12345 is not a Dynamixel bus rate")


def test_a_robot_without_ids_or_with_ranges_beyond_the_servo_is_refused(robot, acts, tmp_path):
    with pytest.raises(InputError) as e:
        DynamixelTransport(str(tmp_path / "x"), 1_000_000, replace(acts, bus=None))
    _one_line_error(e, "robot.actuators: no Dynamixel ids")
    tiny_lead = replace(acts.bus, per_rev=(*acts.bus.per_rev[:-1], 0.001))  # 0.001 mm per revolution of z
    with pytest.raises(InputError) as e:
        DynamixelTransport(str(tmp_path / "x"), 1_000_000, replace(acts, bus=tiny_lead))
    _one_line_error(e, "robot.actuators (z): position limits [-200, 100] mm", "beyond the extended position range")


def test_wrong_baud_names_the_rate_the_servos_answer_at(acts):
    clock = Clock()
    sim = _sim(acts, clock, baud=57_600)
    try:
        with pytest.raises(TransportError) as e:
            DynamixelTransport(sim.path, 1_000_000, acts)
        _one_line_error(e, "no servo answers", "at 1000000 baud", "answers at 57600 baud", "--baud 57600")
        assert sim.wrong_baud > 0
    finally:
        sim.stop()


def test_no_servo_at_all(acts):
    sim = _sim(acts, Clock())
    for i in acts.bus.ids:
        sim.chain.remove(i)
    try:
        with pytest.raises(TransportError) as e:
            DynamixelTransport(sim.path, 1_000_000, acts)
        _one_line_error(e, "no servo answers", "power supply")
    finally:
        sim.stop()


def test_a_silent_servo_is_named_by_its_id(acts):
    sim = _sim(acts, Clock())
    sim.chain.remove(3)
    try:
        with pytest.raises(TransportError) as e:
            DynamixelTransport(sim.path, 1_000_000, acts)
        _one_line_error(e, "servo id 3 (s1c3) does not answer", "ids 1, 2, 4, 5, 6, 7 do")
    finally:
        sim.stop()


@pytest.mark.parametrize("params", [b"", (1234).to_bytes(2, "little")], ids=["write-status", "2-byte-read"])
def test_a_late_reply_of_another_size_is_not_taken_for_a_read(acts, params):
    """A servo's status packet to an earlier write or 2-byte read, arriving late (a starved host or device answers
    after the SDK's reply timeout), comes in before the reply to a 4-byte read: the SDK takes it (same id, valid CRC)
    and would index past a write's status (IndexError) or read a 2-byte reply and its CRC as the value. The link
    takes it as a corrupt reply and asks again: the servo's true reading."""
    clock = Clock()
    sim = _sim(acts, clock)
    try:
        tr = DynamixelTransport(sim.path, 1_000_000, acts, homing=homed_state(sim.chain, acts), clock=clock)
        dxl_id = acts.bus.ids[0]
        truth = tr.read(dxl_id, X.PRESENT_POSITION, 4)
        port = sim.ports[-1]
        send = port.writePort

        def late_first(packet):  # the SDK cleared the port before sending: the late reply comes after that
            port._rx += dxl_status(dxl_id, 0, params)
            port.writePort = send
            return send(packet)

        port.writePort = late_first
        assert tr.read(dxl_id, X.PRESENT_POSITION, 4) == truth
        assert port.writePort is send  # the late reply was there
        tr.close()
    finally:
        sim.stop()


def test_a_pseudo_terminal_allows_a_scheduler_delay_per_reply():
    """On a pseudo-terminal (sim-dynamixel's) each reply may take PTY_LATENCY_MS longer than the SDK allows a bus; a
    character device that is not one (a USB adapter's place: /dev/null here) keeps the SDK's timeout."""
    import os

    import dynamixel_sdk

    from crtraj.hardware.dynamixel._link import PTY_LATENCY_MS, sdk_port

    master, slave = os.openpty()
    try:
        pty = sdk_port(dynamixel_sdk, os.ttyname(slave))
        bus = sdk_port(dynamixel_sdk, "/dev/null")
        for port in (pty, bus):
            port.setPacketTimeout(11)
        assert pty.packet_timeout == pytest.approx(bus.packet_timeout + PTY_LATENCY_MS)
        # the SDK's own allowance (its port not opened: no bytes on the wire yet)
        assert bus.packet_timeout == pytest.approx(2.0 * dynamixel_sdk.port_handler.LATENCY_TIMER + 2.0)
    finally:
        os.close(master)
        os.close(slave)


def test_a_model_mismatch_is_refused(acts):
    bus = acts.bus
    chain = ServoChain(bus.ids, [*bus.models[:4], 1020, *bus.models[5:]])
    sim = InProcessSim(chain, clock=Clock(), wire_time=False).start()
    try:
        with pytest.raises(TransportError) as e:
            DynamixelTransport(sim.path, 1_000_000, acts)
        _one_line_error(e, "servo id 5 (s2c2) is model 1020, the robot file says 1030")
    finally:
        sim.stop()


def test_a_hardware_error_bit_is_refused_at_connect(acts):
    sim = _sim(acts, Clock())
    sim.chain.set_hardware_error(6, HW_OVERLOAD | HW_OVERHEATING)
    try:
        with pytest.raises(TransportError) as e:
            DynamixelTransport(sim.path, 1_000_000, acts)
        _one_line_error(e, "servo id 6 (s2c3): hardware error: overheating, overload (status 0x24)")
    finally:
        sim.stop()


def test_latency_timer_above_1ms_is_a_warning(acts, tmp_path):
    sim = _sim(acts, Clock())
    tty = Path(sim.path).name  # what /sys/bus/usb-serial/devices/<tty> would be called
    (tmp_path / tty).mkdir()
    (tmp_path / tty / "latency_timer").write_text("16\n")
    warned: list[str] = []
    try:
        homed = homed_state(sim.chain, acts)
        tr = DynamixelTransport(sim.path, 1_000_000, acts, warn=warned.append, sysfs=tmp_path, homing=homed)
        tr.close()
        assert len(warned) == 1 and "\n" not in warned[0]
        assert "latency timer is 16 ms" in warned[0] and f"echo 1 | sudo tee {tmp_path / tty}" in warned[0]
        (tmp_path / tty / "latency_timer").write_text("1\n")
        warned.clear()
        DynamixelTransport(sim.path, 1_000_000, acts, warn=warned.append, sysfs=tmp_path, homing=homed).close()
        assert warned == []
    finally:
        sim.stop()


def test_connect_sets_current_based_mode_caps_profiles_and_torque_without_moving(acts):
    """Connect puts each cable servo in current-based position mode (5) with its Goal Current at max_tension
    (20 N x 10 mm / (3.0 / 2.3 N*m/A) = 153.3 mA -> 57 units, rounded down), the stage (no max_force) in extended
    position mode (4), Shutdown with input voltage added (0x35), the profiles, and the torque on without moving."""
    start = acts.command(acts.rest) + np.array([0.5, -0.5, 1.0, 0, 0, 0, 30.0])
    sim = _sim(acts, Clock(), start=start)
    chain = sim.chain
    try:
        before = chain.positions(0.0).copy()
        tr = DynamixelTransport(sim.path, 1_000_000, acts, stop_torque="off", homing=homed_state(chain, acts))
        assert all(chain.torque(i) for i in acts.bus.ids)
        first = acts.bus.ids[0]
        assert chain.register(first, 11, 1) == 5  # current-based position control
        assert chain.register(first, 102, 2) == int(20.0 * 0.010 / (3.0 / 2.3) * 1000 / 2.69) == 57
        assert chain.register(acts.bus.ids[-1], 11, 1) == 4  # the stage: extended position control
        assert [chain.register(i, 63, 1) for i in acts.bus.ids] == [0x35] * 7
        # profile velocity: 5 rad/s = 47.75 rev/min -> ceil(47.75 / 0.229) = 209 units
        assert chain.register(first, 112, 4) == 209
        assert np.array_equal(chain.positions(1.0), before)  # torque on did not move anything
        tr.close()
        assert not any(chain.torque(i) for i in acts.bus.ids)  # torque off on exit
    finally:
        sim.stop()


# ------------------------------------------------------------- streaming
def test_a_short_motion_streams_and_ends_at_its_final_set_point(robot, acts):
    motion = _motion(robot, acts)
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0])
    try:
        st, _ = _stream(sim, acts, motion, clock)
        rep = st.run_path(motion)
        assert rep.status == "done" and rep.moves == len(motion.stamps)
        assert _settled(sim, acts, motion, clock)
        # one per frame, one torque off at connect (before the power-up check) and one at exit, and the bus
        # watchdog re-armed at the first frame (cleared, then set)
        assert sim.chain.counts["sync_writes"] == rep.frames + 4
        assert not any(sim.chain.torque(i) for i in acts.bus.ids)  # closed: torque off
    finally:
        sim.stop()


def test_torque_off_on_estop(robot, acts):
    motion = _motion(robot, acts)
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0])
    try:
        st, _ = _stream(sim, acts, motion, clock, watchdog=0.1)  # e-stop frames repeat one watchdog
        seen = {}

        def stop():
            seen["torque_before"] = [sim.chain.torque(i) for i in acts.bus.ids]
            st.estop("test e-stop")
            seen["torque_after"] = [sim.chain.torque(i) for i in acts.bus.ids]
            seen["positions"] = sim.chain.positions(clock.now()).copy()

        clock.events.append((0.3, stop))
        rep = st.run_path(motion)
        assert rep.status == "estop" and rep.estops >= 1 and rep.brakes == 1 and rep.brake_frames >= 2
        # the planned stop first (torque on while it brakes), then the e-stop: torque off (stop_torque="off")
        assert all(seen["torque_before"]) and all(seen["torque_after"])
        assert not any(sim.chain.torque(i) for i in acts.bus.ids)
        # with the torque off the servos stay where they were: nothing moves after the close
        here = sim.chain.positions(clock.now()).copy()
        assert np.array_equal(sim.chain.positions(clock.now() + 1.0), here)
    finally:
        sim.stop()


@pytest.mark.parametrize(
    ("fault", "status", "parts"),
    [
        ("error-bit", "error", ("servo id 4 (s2c1): hardware error: overload",)),
        ("missing", "error", ("servo id 2 (s1c2): no answer to 5 sync reads in a row",)),
        ("timeout", "error", ("servo id 1 (s1c1): no answer to 5 sync reads in a row",)),
        ("corrupt", "error", ("servo id 1 (s1c1): a corrupted reply to 5 sync reads in a row",)),
    ],
)
def test_faults_while_streaming_stop_and_name_the_servo(robot, acts, fault, status, parts):
    motion = _motion(robot, acts)
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0])
    chain = sim.chain
    inject = {
        "error-bit": lambda: chain.set_hardware_error(4, HW_OVERLOAD, clock.now()),
        "missing": lambda: chain.remove(2),
        "timeout": lambda: chain.drop_replies(10_000),
        "corrupt": lambda: chain.corrupt_replies(10_000),
    }[fault]

    def at_half():
        with sim.locked():
            inject()

    clock.events.append((0.5, at_half))
    try:
        st, _ = _stream(sim, acts, motion, clock, misses=5)
        rep = st.run_path(motion)
        assert rep.status == status and "transport error" in rep.message
        for p in parts:
            assert p in rep.message, rep.message
        assert 0 < rep.moves < len(motion.stamps)
        # torque off on exit after the fault (a servo that was unplugged cannot be reached)
        assert not any(chain.torque(i) for i in chain.present)
    finally:
        sim.stop()


def test_a_few_corrupted_replies_are_counted_not_fatal(robot, acts):
    motion = _motion(robot, acts)
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0])
    clock.events.append((0.3, lambda: sim.chain.corrupt_replies(2)))
    try:
        st, tr = _stream(sim, acts, motion, clock)
        rep = st.run_path(motion)
        assert rep.status == "done" and tr.counts["corrupt"] == 2 and rep.device["crc_errors"] == 2
    finally:
        sim.stop()


def test_a_motion_that_does_not_start_at_the_servos_is_refused_before_sending(robot, acts):
    motion = _motion(robot, acts)
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0] + np.array([0.3, 0, 0, 0, 0, 0, 0]))
    before = sim.chain.positions(0.0).copy()
    try:
        st, _ = _stream(sim, acts, motion, clock)
        rep = st.run_path(motion)
        assert rep.status == "refused" and rep.moves == 0 and "--approach" in rep.message
        # only the torque off at connect and at exit: no goal reached the servos
        assert sim.chain.counts["sync_writes"] == 2
        assert np.array_equal(sim.chain.positions(clock.now() + 1.0), before)
    finally:
        sim.stop()


def test_streamer_open_takes_a_dynamixel_url(acts, tmp_path):
    with pytest.raises(TransportError) as e:
        Streamer.open(f"dynamixel://{tmp_path}/ttyUSB7?baud=1000000", acts)
    _one_line_error(e, "ttyUSB7: no such port")


def test_cli_sim_dynamixel_prints_its_path(capsys):
    assert main(["sim-dynamixel", "--pty", "--duration", "0.1", "--no-wire-time"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert re.match(r"sim-dynamixel on /dev/pts/\d+ \(7 servos, ids 1, 2, 3, 4, 5, 6, 7, 1000000 baud", out[0])
    assert out[-1].startswith("sim-dynamixel stopped: 0 packets")


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--hardware-error", "9:overload"], "--hardware-error: expected ID:NAME"),
        (["--hardware-error", "3:tired"], "--hardware-error: expected ID:NAME"),
        (["--hardware-error", "\u00b3:overload"], "--hardware-error: expected ID:NAME"),  # isdigit, not int
        (["--hardware-error", "\u0663:overload"], "--hardware-error: expected ID:NAME"),  # int() takes it
        (["--missing", "42"], "--missing: 42 is not one of the robot's ids"),
        (["--silent-after", "-1"], "--silent-after: must be in 0..1000000000 packets, got -1"),
        (["--baud", "12345"], "--baud: a Dynamixel rate"),
    ],
)
def test_cli_sim_dynamixel_bad_flag_is_one_line(capsys, flags, message):
    assert main(["sim-dynamixel", "--pty", *flags, "--duration", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


# ------------------------------------------------------------ end to end
def _admit_paper_run(result: Path):
    """The run admitted at 100 Hz, slowed as admission suggests when the z stage's acceleration needs it
    (a known gap of the replanner's timing, tests/test_replan_limits.py)."""
    try:
        return admit_result(result, rate=100.0)
    except AdmissionError as exc:
        m = re.search(r"try --time-scale ([0-9.]+)", str(exc))
        if m is None:
            raise
        return admit_result(result, rate=100.0, time_scale=float(m.group(1)))


@pytest.mark.slow
def test_paper_simulation_2_streams_to_the_servos_end_to_end(tmp_path, capsys):
    out = tmp_path / "replan"
    # without the step deadline: the run streamed is the same on any machine
    assert main(["replan", str(paper_copy(tmp_path)), "--out", str(out), "--no-html", "--quiet"]) == 0
    capsys.readouterr()
    motion = _admit_paper_run(out / "run.json")
    acts = motion.actuators
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0])
    try:
        st, _ = _stream(sim, acts, motion, clock, misses=1000)
        rep = st.run_path(motion)
        assert rep.status == "done", rep.message
        assert rep.moves == len(motion.stamps) and not any(e[1] == "refused" for e in rep.events)
        # one bus transaction per set-point (plus the HOLD frames while settling, the torque off at connect and at
        # exit, the watchdog re-armed at the first frame)
        assert sim.chain.counts["sync_writes"] == rep.frames + 4
        goals = [sim.chain.register(i, 116, 4) for i in acts.bus.ids]
        assert goals == acts.bus.ticks(motion.values[-1]).tolist()  # the final set-point, in ticks, as sent
        assert _settled(sim, acts, motion, clock)
    finally:
        sim.stop()
    # the command line: a port that is not there is one line and exit 1, after admission passed
    scale = f"{motion.time_scale:g}"
    port = tmp_path / "ttyUSB9"
    assert main(["stream", str(out / "run.json"), "--dynamixel", str(port), "--time-scale", scale]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"crtraj: error: {port}: no such port (is the USB-serial adapter, e.g. a U2D2, plugged in? see ls /dev/ttyUSB*)"
    ]
    # replan --stream dynamixel://: the same link after the run (here to a port that is not there)
    # (without the step deadline too: under load the deadline's run differs, and its set-points may be refused at
    # admission before the port is opened)
    args = ["replan", str(paper_copy(tmp_path, "p2.toml")), "--out", str(tmp_path / "r2"), "--quiet", "--no-html"]
    assert main([*args, "--stream", f"dynamixel://{port}?baud=1000000", "--time-scale", scale]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"crtraj: error: {port}: no such port")


def test_crc_agrees_with_the_sdk_on_random_packets():
    """Two independent implementations of the Protocol 2.0 CRC (ours from the spec, the SDK's) agree."""
    sdk = require_module("dynamixel_sdk")
    ph = sdk.PacketHandler(2.0)
    rng = np.random.default_rng(7)
    for n in (1, 8, 50, 300):
        data = rng.integers(0, 256, size=n).tolist()
        assert dxl_crc16(bytes(data)) == ph.updateCRC(0, data, n)


@pytest.mark.parametrize("fault", ["reboot", "torque-off"])
def test_a_servo_rebooted_mid_stream_holds_at_once_naming_it(robot, acts, fault):
    """A servo that restarts (torque off, RAM reset) mid-stream is seen on the very next sync read: the link
    holds (no goal is written after it) and the report names the servo, long before the final settle check."""
    motion = _motion(robot, acts)
    clock = Clock()
    sim = _sim(acts, clock, start=motion.values[0])
    chain = sim.chain
    seen: dict[str, int] = {}

    def at_half():
        with sim.locked():
            if fault == "reboot":
                chain.reboot(3, clock.now())
            else:  # another program switched its torque off
                chain.torque_off(3, clock.now())
            seen["writes"] = chain.counts["sync_writes"]

    clock.events.append((0.5, at_half))
    try:
        st, _ = _stream(sim, acts, motion, clock)
        rep = st.run_path(motion)
        assert rep.status == "error" and "transport error" in rep.message
        assert "servo id 3 (s1c3): torque off mid-stream" in rep.message, rep.message
        # held at once: at most the goal already on its way when the reboot happened, then only the torque off
        assert rep.moves <= round(0.5 * motion.rate) + 2 < len(motion.stamps)
        # after it: the goal already on its way at most, then the torque off at exit
        assert chain.counts["sync_writes"] <= seen["writes"] + 2
    finally:
        sim.stop()


def test_a_signal_during_an_sdk_transaction_waits_for_its_end():
    """Ctrl-C or SIGTERM arriving inside one SDK call (the packet half on the wire) is raised after the call: a
    packet cut mid-way left the SDK's busy flag set, and the stop that follows failed with "Port is in use!"."""
    import os
    import signal
    from types import SimpleNamespace

    from crtraj.core import interrupt
    from crtraj.hardware.dynamixel._link import DynamixelTransport

    done = []

    def transaction():
        os.kill(os.getpid(), signal.SIGTERM)  # delivered at the next bytecode, inside the call
        done.append("second half")  # the rest of the packet
        return 7

    link = SimpleNamespace(_lost=None, _port=None)
    with interrupt.policy(), pytest.raises(interrupt.Interrupted):
        DynamixelTransport._bus(link, transaction)
    assert done == ["second half"]
