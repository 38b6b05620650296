"""Protocol 2.0 packets (CRC, stuffing, hostile input), the servo simulator's control table, and the
robot file's Dynamixel keys with their exact cable length -> rad -> ticks mapping. No SDK needed."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from conftest import PROBLEMS

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import read_toml
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import ServoChain


# ------------------------------------------------------------------ CRC
@pytest.mark.parametrize(
    "packet",
    [
        "FF FF FD 00 01 03 00 01 19 4E",  # e-manual, Protocol 2.0: PING id 1
        "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15",  # READ present position (132, 4 bytes) of id 1
        "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0",  # its status packet: 166 ticks
    ],
)
def test_crc_matches_the_published_example_packets(packet):
    raw = bytes.fromhex(packet.replace(" ", ""))
    assert dxl.crc16(raw[:-2]) == struct.unpack("<H", raw[-2:])[0]


def test_encode_gives_the_published_ping_and_status_packets():
    assert dxl.encode(1, dxl.PING) == bytes.fromhex("FFFFFD0001030001194E")
    assert dxl.status(1, 0, struct.pack("<i", 166)) == bytes.fromhex("FFFFFD000108005500A60000008CC0")


def test_crc16_check_value_of_the_catalogue():
    # CRC-16/BUYPASS (poly 0x8005, init 0, no reflection): check value of "123456789" is 0xFEE8
    assert dxl.crc16(b"123456789") == 0xFEE8


# ------------------------------------------------------------- stuffing
@pytest.mark.parametrize(
    "body",
    [b"\xff\xff\xfd", b"\xff\xff\xfd\xfd", b"\x01\xff\xff\xfd\xff\xff\xfd\x02", bytes(range(256)), b""],
)
def test_stuffing_round_trip_and_no_header_inside(body):
    s = dxl.stuff(body)
    assert dxl.unstuff(s) == body
    assert s.count(b"\xff\xff\xfd") == body.count(b"\xff\xff\xfd")
    assert b"\xff\xff\xfd\x00" not in s  # the header never appears in a stuffed body
    assert len(s) == len(body) + body.count(b"\xff\xff\xfd")


def test_stuffed_packet_parses_back():
    params = struct.pack("<HH", 116, 4) + bytes([1]) + b"\xff\xff\xfd\x00"  # a goal that looks like a header
    pkt = dxl.encode(dxl.BROADCAST_ID, dxl.SYNC_WRITE, params)
    (p,) = dxl.PacketReader().feed(pkt)
    assert (p.id, p.instruction, p.params, p.size) == (dxl.BROADCAST_ID, dxl.SYNC_WRITE, params, len(pkt))


# ------------------------------------------------------- hostile input
def test_reader_drops_bad_crc_and_resynchronises():
    good = dxl.encode(3, dxl.PING)
    bad = bytearray(dxl.encode(4, dxl.PING))
    bad[-1] ^= 0x01
    r = dxl.PacketReader()
    out = r.feed(b"\x00garbage" + bytes(bad) + good)
    assert [p.id for p in out] == [3] and r.bad_crc == 1


def test_reader_bounds_lengths_and_survives_byte_by_byte_feeding():
    huge = dxl.HEADER + struct.pack("<BH", 1, 0xFFFF) + b"\x01"  # claims 64 kB
    tiny = dxl.HEADER + struct.pack("<BH", 1, 1) + b"\x01"  # shorter than instruction + CRC
    good = dxl.encode(7, dxl.READ, struct.pack("<HH", 132, 4))
    r = dxl.PacketReader()
    out = []
    for b in huge + tiny + good:
        out += r.feed(bytes([b]))
    assert [(p.id, p.instruction) for p in out] == [(7, dxl.READ)]
    assert r.bad_length == 2
    r2 = dxl.PacketReader()
    assert r2.feed(b"\xff" * 100_000) == [] and len(r2._buf) <= 3  # noise never accumulates


def test_hardware_error_names():
    assert dxl.hardware_error_text(dxl.HW_OVERLOAD | dxl.HW_OVERHEATING) == "overheating, overload"
    assert dxl.hardware_error_text(dxl.HW_INPUT_VOLTAGE) == "input voltage"


# ------------------------------------------------------ simulated servos
def _ask(chain: ServoChain, dxl_id: int, inst: int, params: bytes = b"", now: float = 0.0) -> list[dxl.Packet]:
    replies = chain.handle(dxl.PacketReader().feed(dxl.encode(dxl_id, inst, params))[0], now)
    return [p for r in replies for p in dxl.PacketReader().feed(r)]


def _read4(chain: ServoChain, dxl_id: int, addr: int, now: float = 0.0) -> int:
    (p,) = _ask(chain, dxl_id, dxl.READ, struct.pack("<HH", addr, 4), now)
    assert p.params[0] & 0x7F == 0
    return struct.unpack("<i", p.params[1:5])[0]


def test_sim_answers_ping_read_and_refuses_bad_accesses():
    chain = ServoChain([1, 2], [1030, 1020], initial=[100, -5])
    (p,) = _ask(chain, 2, dxl.PING)
    assert p.instruction == dxl.STATUS and struct.unpack("<H", p.params[1:3])[0] == 1020
    assert [q.id for q in _ask(chain, dxl.BROADCAST_ID, dxl.PING)] == [1, 2]
    assert _read4(chain, 1, X.PRESENT_POSITION) == 100 and _read4(chain, 2, X.PRESENT_POSITION) == -5
    write = struct.pack("<H", X.MODEL_NUMBER) + b"\x01\x02"  # read-only
    assert _ask(chain, 1, dxl.WRITE, write)[0].params[0] == dxl.ERR_ACCESS
    assert _ask(chain, 1, dxl.READ, struct.pack("<HH", X.SIZE - 2, 4))[0].params[0] == dxl.ERR_DATA_RANGE
    assert _ask(chain, 1, 0x77)[0].params[0] == dxl.ERR_INSTRUCTION
    assert _ask(chain, 9, dxl.PING) == []  # nobody with that id


def test_sim_moves_within_its_profile_with_a_first_order_lag():
    chain = ServoChain([1], [1030], tau=0.0)  # ideal motor: the measured position is the profile
    w = lambda addr, fmt, v: _ask(chain, 1, dxl.WRITE, struct.pack("<H", addr) + struct.pack(fmt, v))  # noqa: E731
    assert w(X.OPERATING_MODE, "<B", X.EXTENDED_POSITION)[0].params[0] == 0
    w(X.PROFILE_VELOCITY, "<I", 100)  # 22.9 rev/min
    w(X.PROFILE_ACCELERATION, "<I", 50)  # 10728.85 rev/min^2
    assert w(X.TORQUE_ENABLE, "<B", 1)[0].params[0] == 0
    assert w(X.OPERATING_MODE, "<B", 3)[0].params[0] == dxl.ERR_ACCESS  # EEPROM is locked with torque on
    goal = 40_000  # ~9.8 revolutions: only extended position mode allows it
    assert w(X.GOAL_POSITION, "<i", goal)[0].params[0] == 0
    vmax = 100 * 0.229 / 60 * 4096  # ticks/s
    amax = 50 * 214.577 / 3600 * 4096  # ticks/s^2
    t_acc = vmax / amax
    t_end = t_acc + goal / vmax  # trapezoid: accelerate, cruise, brake
    # independent closed form of the trapezoid at the middle of the cruise
    t_mid = t_end / 2
    expected = 0.5 * amax * t_acc**2 + vmax * (t_mid - t_acc)
    assert chain.positions(t_mid)[0] == pytest.approx(expected, rel=1e-6)
    assert chain.positions(t_end + 0.01)[0] == pytest.approx(goal)
    assert w(X.GOAL_POSITION, "<i", X.EXTENDED_LIMIT + 1)[0].params[0] == dxl.ERR_DATA_LIMIT


def test_sim_first_order_lag_matches_the_exponential():
    tau = 0.05
    chain = ServoChain([1], [1030], tau=tau)
    _ask(chain, 1, dxl.WRITE, struct.pack("<HB", X.TORQUE_ENABLE, 1))
    _ask(chain, 1, dxl.WRITE, struct.pack("<Hi", X.GOAL_POSITION, 1000))  # unlimited profile: a step
    assert chain.positions(0.1)[0] == pytest.approx(1000 * (1 - math.exp(-0.1 / tau)), rel=1e-9)


def test_sim_hardware_error_drops_torque_and_sets_the_alert_bit():
    chain = ServoChain([1], [1030])
    _ask(chain, 1, dxl.WRITE, struct.pack("<HB", X.TORQUE_ENABLE, 1))
    chain.set_hardware_error(1, dxl.HW_OVERLOAD)
    (p,) = _ask(chain, 1, dxl.PING)
    assert p.params[0] & dxl.ERR_ALERT and not chain.torque(1)
    assert _ask(chain, 1, dxl.WRITE, struct.pack("<HB", X.TORQUE_ENABLE, 1))[0].params[0] == dxl.ERR_ALERT | 1
    _ask(chain, 1, dxl.REBOOT)
    (p,) = _ask(chain, 1, dxl.PING)
    assert p.params[0] == 0  # the reboot cleared it


def test_sim_sync_read_through_indirect_addresses_and_sync_write():
    chain = ServoChain([1, 2], [1030, 1030], initial=[7, -9])
    for i in (1, 2):  # mirror present position (132..135) into indirect data 224..227
        addrs = b"".join(struct.pack("<H", X.PRESENT_POSITION + j) for j in range(4))
        _ask(chain, i, dxl.WRITE, struct.pack("<H", X.INDIRECT_ADDRESS) + addrs)
    replies = _ask(chain, dxl.BROADCAST_ID, dxl.SYNC_READ, struct.pack("<HH", X.INDIRECT_DATA, 4) + bytes([2, 1]))
    assert [(p.id, struct.unpack("<i", p.params[1:5])[0]) for p in replies] == [(2, -9), (1, 7)]
    # position control mode (3, the factory default) takes goals in 0..4095 only: -500 is refused
    block = b"".join(bytes([i]) + struct.pack("<i", g) for i, g in ((1, 500), (2, -500)))
    for i in (1, 2):
        _ask(chain, i, dxl.WRITE, struct.pack("<HB", X.TORQUE_ENABLE, 1))
    assert _ask(chain, dxl.BROADCAST_ID, dxl.SYNC_WRITE, struct.pack("<HH", X.GOAL_POSITION, 4) + block) == []
    # servo 2 holds where it is: -9 wrapped into one turn, as torque on in mode 3 loses the turn count
    assert _read4(chain, 1, X.GOAL_POSITION) == 500 and _read4(chain, 2, X.GOAL_POSITION) == 4096 - 9
    # a malformed sync write (a block cut short) is ignored as a whole
    _ask(chain, dxl.BROADCAST_ID, dxl.SYNC_WRITE, struct.pack("<HH", X.GOAL_POSITION, 4) + block[:-1])
    assert _read4(chain, 1, X.GOAL_POSITION) == 500


# -------------------------------------------------- robot file and ticks
def _actuators(mutate=None) -> Actuators:
    data = read_toml(PROBLEMS / "robots" / "cdsr2.toml")
    table = data["robot"]["actuators"]
    if mutate is not None:
        mutate(table)
    return Actuators.from_table(Table(table, "robot.actuators"), 2)


def test_cable_length_to_ticks_is_exact(robot):
    acts = Actuators.from_robot(robot)
    bus = acts.bus
    assert bus.ids == (1, 2, 3, 4, 5, 6, 7) and set(bus.models) == {1030}
    rest = acts.rest
    # one spool circumference (2 pi r = 20 pi mm) of cable paid out is one revolution: 4096 ticks
    q = rest.copy()
    q[0] += 2 * math.pi * 10.0
    q[-1] = 20.0  # one lead of the z stage
    ticks = bus.ticks(acts.command(q))
    assert ticks[0] == 4096 and ticks[-1] == 4096 and np.all(ticks[1:-1] == 0)
    # ticks -> values -> ticks is exact; values -> ticks -> values within half a tick
    rng = np.random.default_rng(3)
    T = rng.integers(-200_000, 200_000, size=(500, 7))
    assert np.array_equal(bus.ticks(bus.values(T)), T)
    V = rng.uniform(acts.lower, acts.upper, size=(500, 7))
    assert np.all(np.abs(bus.values(bus.ticks(V)) - V) <= bus.resolution / 2 * (1 + 1e-12))
    # and through the cable lengths: q -> ticks -> q within half a tick of cable (r * 2 pi / 4096 mm)
    Q = acts.actuation(V)
    back = acts.actuation(bus.values(bus.ticks(acts.command(Q))))
    half = np.concatenate([10.0 * bus.resolution[:-1], bus.resolution[-1:]]) / 2
    assert np.all(np.abs(back - Q) <= half * (1 + 1e-9))


def test_sign_and_zero_offset_enter_the_ticks(robot):
    def flip(t):
        t["servo"]["s1c2"].update(sign=-1, zero_offset=0.5)

    acts = _actuators(flip).for_robot(robot)
    q = acts.rest.copy()
    q[1] += 3.0  # mm paid out
    angle = 0.5 - 3.0 / 10.0  # a0 + s dq / r
    assert acts.bus.ticks(acts.command(q))[1] == round(angle / (2 * math.pi) * 4096)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda t: t["servo"]["s1c3"].pop("id"), "robot.actuators.servo.s1c3.id: missing"),
        (lambda t: t["servo"]["s2c1"].update(id=2), "robot.actuators.servo.s2c1.id: 2 is also the id of s1c2"),
        (lambda t: t["z"].pop("lead"), "robot.actuators.z.lead: missing"),
        (lambda t: t.pop("model"), "robot.actuators.servo.s1c1.model: missing"),
        (lambda t: t["servo"]["s1c1"].update(id=300), "robot.actuators.servo.s1c1.id: must be <= 252"),
        (lambda t: t.update(id=1), "robot.actuators.id: set per servo"),
        (lambda t: t.update(ticks_per_rev=0), "robot.actuators.ticks_per_rev: must be >= 1"),
    ],
)
def test_bad_bus_keys_are_one_line_errors(mutate, message):
    with pytest.raises(InputError) as e:
        _actuators(mutate)
    assert str(e.value).startswith(message) and "\n" not in str(e.value)


def test_no_ids_means_no_bus():
    def strip(t):
        for s in t["servo"].values():
            s.pop("id")
        t["z"].pop("id")
        t["z"].pop("lead")

    assert _actuators(strip).bus is None


def test_sim_survives_hostile_packets_with_valid_crcs():
    """Random ids, instructions and params (valid CRC, so they reach the servos): never an exception, every
    reply a well-formed status packet of a servo that exists, and the servos still answer afterwards."""
    rng = np.random.default_rng(16)
    chain = ServoChain([1, 2, 3], [1030, 1030, 1030], initial=[0, 10, -10])
    reader = dxl.PacketReader()
    insts = [dxl.PING, dxl.READ, dxl.WRITE, dxl.REBOOT, dxl.SYNC_READ, dxl.SYNC_WRITE, 0x00, 0x55, 0xFF]
    for k in range(3000):
        dxl_id = int(rng.choice([1, 2, 3, dxl.BROADCAST_ID, int(rng.integers(0, 256))]))
        n = int(rng.integers(0, 40)) if rng.random() < 0.9 else int(rng.integers(0, 1200))
        params = rng.integers(0, 256, size=n, dtype=np.uint8).tobytes()
        if rng.random() < 0.5 and n >= 4:  # plausible addresses, so the writes and reads get somewhere
            params = struct.pack("<HH", int(rng.integers(0, X.SIZE + 8)), int(rng.integers(0, 12))) + params[4:]
        (p,) = reader.feed(dxl.encode(min(dxl_id, 0xFE), int(rng.choice(insts)), params))
        for r in chain.handle(p, 0.001 * k):
            (s,) = dxl.PacketReader().feed(r)
            assert s.instruction == dxl.STATUS and s.id in (1, 2, 3) and len(s.params) >= 1
        assert np.all(np.isfinite(chain.positions(0.001 * k)))
    chain.silent = chain.corrupt = 0
    for i in (1, 2, 3):
        (s,) = _ask(chain, i, dxl.PING, now=10.0)
        assert s.id == i


def test_sim_faults_from_a_packet_count_on():
    chain = ServoChain([1], [1030])
    chain.silent_after = 2
    assert len(_ask(chain, 1, dxl.PING)) == 1 and len(_ask(chain, 1, dxl.PING)) == 1
    assert _ask(chain, 1, dxl.PING) == [] and _ask(chain, 1, dxl.PING) == []  # a timeout from then on
    chain = ServoChain([1], [1030])
    chain.corrupt_after = 1
    assert len(_ask(chain, 1, dxl.PING)) == 1
    raw = chain.handle(dxl.PacketReader().feed(dxl.encode(1, dxl.PING))[0], 0.0)
    reader = dxl.PacketReader()
    assert len(raw) == 1 and reader.feed(raw[0]) == [] and reader.bad_crc == 1  # the reply's CRC is wrong
