"""A chain of simulated Dynamixel X-series servos speaking Protocol 2.0 on a pseudo-terminal.

Written from the public Protocol 2.0 description (`crtraj.hardware.dynamixel._protocol`),
not from the SDK, so tests through the official SDK check it against an
independent reading of the spec.

`ServoChain` is the servos without a port: `handle` one instruction packet at
a device time (s) and get the status packets back. It answers PING, READ,
WRITE, SYNC READ, SYNC WRITE and REBOOT on the X-series control table
(`X`: model number, operating mode, torque enable, hardware error status,
profile acceleration and velocity, goal, present velocity and position,
indirect addresses and data, ...),
refuses writes to read-only bytes and to EEPROM while the torque is on
(access error), goal positions outside the operating mode's range, PWM Limit above 885 and Current Limit above
the model's maximum (data limit error) and reads past the table (data range error). Each servo with torque on
follows its goal on the time-optimal profile within its profile velocity and
acceleration (`ServoProfile`; 0 means unlimited), and its measured position
follows that reference through a first-order lag ``tau``; with torque off it
stays where it is. Injectable faults: `drop_replies` (a timeout: the next
packets get no answer), `corrupt_replies` (a wrong CRC), `set_hardware_error`
(an error bit: the servo drops its torque and flags the alert bit),
`remove` (a missing id), `jam` (a jammed spool: the shaft stalls, its current rises to its mode's cap), `cut`
(a cut tendon: its load current collapses), `heat` (Present Temperature; past Temperature Limit (31) the
overheating bit, and torque off as Shutdown (63) says) and `supply` (Present Input Voltage; outside the voltage
limits (32, 34) the input voltage bit, likewise). Present Current follows
`crtraj.hardware.dynamixel._sim_shaft`: capped by Goal Current (102, at most Current Limit (38)) in mode 5, and only
by PWM Limit (36), up to the stall current, in modes 3 and 4.

`crtraj.hardware.dynamixel.SimDynamixel` puts a chain on a pseudo-terminal (`os.openpty`, raw mode) and
serves it from a thread: the host opens `path` like a USB serial port. A pty
has no baud rate, so the simulator reads the host's configured rate from the
terminal settings and ignores a host at another rate (as a real bus would
see garbage), and with ``wire_time`` delays every reply by the time its bytes
and the request's take on a real wire (10 bits per byte at the bus rate,
one transfer at a time), so measured rates are those of a real bus. Each reply
also waits its servo's Return Delay Time (register 9, 2 us units, factory
default 250 = 500 us; `crtraj stream` sets it to 0 at connect), and the
Status Return Level (register 68) decides which instructions are answered.

Power-up as on a real X-series servo: `power_cycle` and REBOOT turn the torque
off, put RAM at its defaults (the LED, crtraj's homed marker, reads 0) and lose
the multi-turn count: the present position reads within one turn (0..4095)
plus the Homing Offset (register 20, EEPROM, kept). Each shaft may have
mechanical ``stops`` (physical ticks); pressing one, the servo's Present Current rises with its position error
to the cap of its mode (current-based position mode 5: the Goal Current), which is what hard-stop homing detects.

The multi-turn count is also lost, the LED untouched, by switching to Operating Mode 3 (position control), by
the torque coming on in mode 3, and by the Clear instruction (0x10, torque off only), as the e-manual says.

Bus Watchdog (register 98) as the e-manual defines it: with the torque on and the register at 1..127 (20 ms
units), a servo that hears no instruction packet for longer stops, braking with its profile from the
reference's velocity; the register then reads -1 and the goal values are read-only (a range error) until 0 is
written.

Drive Mode's reverse bit (register 10, bit 0) as the e-manual defines it: in
reverse mode the servo counts clockwise as positive, so Goal Position, Present
Position and Present Velocity all run against the shaft's normal direction.
The chain keeps each shaft's physical position (`shaft`, in the ticks of
``initial``, normal counting); writing the bit (torque off, EEPROM) flips the
reading about the Homing Offset with the shaft left where it is.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from types import MappingProxyType

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_shaft import P_GAIN_DEFAULT, ChainFaults, ShaftLoads
from crtraj.hardware.sim import ServoProfile

TICKS_PER_REV = 4096  # X-series encoder
_UNLIMITED = 1e12  # ticks/s or ticks/s^2 for a profile register of 0
_READ_ONLY = (range(0, 7), range(70, 71), range(120, X.INDIRECT_ADDRESS), range(X.INDIRECT_DATA, X.SIZE))
_EEPROM_END = 64
_CURRENT_LIMIT_MAX = MappingProxyType({1120: 2047, 1130: 2047})  # units, by model number (XM540); XM430: 1193


def _watching(t: bytearray) -> bool:
    """The servo with control table `t` has its Bus Watchdog armed: torque on and 1..127 (20 ms units)."""
    return bool(t[X.TORQUE_ENABLE]) and 0 < t[X.BUS_WATCHDOG] <= 127


def _watchdog_due(tables: list[bytearray], heard: float, reached: float | None, now: float) -> float | None:
    """The device time (s) in [reached, now) when the first Bus Watchdog fires (a servo that heard no instruction
    packet since `heard` for longer than its watchdog); None when none fires by `now`."""
    first = min((heard + t[X.BUS_WATCHDOG] * X.WATCHDOG_UNIT for t in tables if _watching(t)), default=None)
    return first if first is not None and reached is not None and reached <= first < now else None


def _watchdog_stops(tables: list[bytearray], heard: float, now: float) -> list[int]:
    """The servos whose Bus Watchdog fires by `now` (s): each register then reads -1 (ROBOTIS e-manual: the
    servo stops, its goal values read-only until 0 is written)."""
    out = [k for k, t in enumerate(tables) if _watching(t) and now >= heard + t[X.BUS_WATCHDOG] * X.WATCHDOG_UNIT]
    for k in out:
        tables[k][X.BUS_WATCHDOG] = X.WATCHDOG_TRIPPED
    return out


def _over_maximum(t: bytearray, addr: int, data: bytes) -> bool:
    """A write of `data` at `addr` puts PWM Limit (36) above 885 or Current Limit (38) above its model's maximum
    (e-manual: 1193 on the XM430, 2047 on the XM540): the servo refuses it (data limit error)."""
    trial = bytearray(t[X.PWM_LIMIT : X.CURRENT_LIMIT + 2])
    lo, hi = max(addr, X.PWM_LIMIT), min(addr + len(data), X.CURRENT_LIMIT + 2)
    if lo >= hi:
        return False
    trial[lo - X.PWM_LIMIT : hi - X.PWM_LIMIT] = data[lo - addr : hi - addr]
    pwm, current = struct.unpack("<HH", trial)
    model = struct.unpack_from("<H", t, X.MODEL_NUMBER)[0]
    return pwm > X.PWM_LIMIT_DEFAULT or current > _CURRENT_LIMIT_MAX.get(model, X.CURRENT_LIMIT_DEFAULT)


def _clear_refusal(t: bytearray, params: bytes) -> int:
    """The status error of a Clear instruction to the servo with control table `t` (0: its turn count is lost):
    only `dxl.CLEAR_MULTI_TURN`, only while stopped (torque off)."""
    if bytes(params) != dxl.CLEAR_MULTI_TURN:
        return dxl.ERR_DATA_RANGE
    return dxl.ERR_RESULT_FAIL if t[X.TORQUE_ENABLE] else 0


class ServoChain(ChainFaults):
    """Simulated X-series servos on one bus. ids, models: bus ids and model numbers. initial: start
    positions (ticks). tau: motor time constant (s, >= 0). Times are the caller's device clock (s)."""

    def __init__(
        self,
        ids: Sequence[int],
        models: Sequence[int],
        *,
        initial: Sequence[int] | None = None,
        tau: float = 0.03,
        baud: int = 1_000_000,
        stops: Sequence[tuple[float, float]] | None = None,
    ) -> None:
        if len(ids) != len(models) or not ids or len(set(ids)) != len(ids):
            raise InputError("sim-dynamixel: needs distinct ids, one model number each")
        if not all(0 <= i <= dxl.MAX_ID for i in ids):
            raise InputError(f"sim-dynamixel: ids must be in 0..{dxl.MAX_ID}")
        if not (math.isfinite(tau) and tau >= 0):
            raise InputError(f"--tau: must be >= 0, got {tau}")
        codes = {v: k for k, v in dxl.BAUD_CODES.items()}
        if baud not in codes:
            raise InputError(f"--baud: a Dynamixel rate ({', '.join(map(str, dxl.BAUD_CODES.values()))}), got {baud}")
        self.ids = tuple(int(i) for i in ids)
        self.baud = int(baud)
        self.tau = float(tau)
        n = len(self.ids)
        x0 = np.zeros(n) if initial is None else np.asarray(initial, dtype=float).reshape(-1)
        if x0.shape != (n,) or not np.all(np.abs(x0) <= X.EXTENDED_LIMIT):
            raise InputError(f"sim-dynamixel: initial positions must be {n} tick values within the extended range")
        self._table = [bytearray(X.SIZE) for _ in range(n)]
        for k, t in enumerate(self._table):
            struct.pack_into("<H", t, X.MODEL_NUMBER, int(models[k]))
            t[X.FIRMWARE], t[X.ID], t[X.BAUD_RATE] = 46, self.ids[k], codes[self.baud]
            t[X.OPERATING_MODE], t[13] = 3, 2  # position control, protocol 2
            t[X.RETURN_DELAY] = X.RETURN_DELAY_DEFAULT
            struct.pack_into("<H", t, X.CURRENT_LIMIT, X.CURRENT_LIMIT_DEFAULT)
            t[X.TEMPERATURE_LIMIT] = 80
            struct.pack_into("<HHH", t, X.MAX_VOLTAGE, 160, 95, X.PWM_LIMIT_DEFAULT)  # 32, 34, 36
            t[X.SHUTDOWN] = X.SHUTDOWN_DEFAULT
            struct.pack_into("<H", t, X.POSITION_P_GAIN, P_GAIN_DEFAULT)
            t[X.STATUS_RETURN] = 2  # status return level: answer every instruction
            struct.pack_into("<H", t, X.GOAL_CURRENT, X.CURRENT_LIMIT_DEFAULT)
            struct.pack_into("<H", t, X.PRESENT_VOLTAGE, 120)
            t[X.PRESENT_TEMPERATURE] = 35
            struct.pack_into("<i", t, X.GOAL_POSITION, int(np.rint(x0[k])))
        self._x = x0.copy()  # measured positions (ticks, as reported: the shaft's position plus `_shift`)
        self._shift = np.zeros(n)  # reported minus physical position (ticks): changes at power-up and homing offset
        lim = np.full((n, 2), [-np.inf, np.inf]) if stops is None else np.asarray(stops, dtype=float).reshape(n, 2)
        self.stops = lim  # mechanical stops of each shaft (physical ticks, the frame of `initial`)
        self._v = np.zeros(n)  # measured velocities (ticks/s)
        self.loads = ShaftLoads(n)  # tendons and jams (`crtraj.hardware.dynamixel._sim_shaft`)
        self._profile = ServoProfile(np.full(n, _UNLIMITED), np.full(n, _UNLIMITED), x0)
        self._t: float | None = None  # device time reached; the first call's time is the start
        self.present = set(self.ids)
        self.silent = 0  # timeout fault: packets left to ignore
        self.corrupt = 0  # corrupted-reply fault: packets left whose replies get a wrong CRC
        self.silent_after: int | None = None  # timeout fault from this packet count on (None: never)
        self.corrupt_after: int | None = None  # corrupted-reply fault from this packet count on (None: never)
        self.counts = {"packets": 0, "replies": 0, "sync_writes": 0}
        self._heard = 0.0  # device time (s) of the last instruction packet on the bus (the Bus Watchdog's)

    # --------------------------------------------------------------- faults
    def drop_replies(self, packets: int) -> None:
        """Timeout fault: answer none of the next `packets` instruction packets (writes still apply)."""
        self.silent = int(packets)

    def corrupt_replies(self, packets: int) -> None:
        """Corrupted-reply fault: the replies to the next `packets` packets carry a wrong CRC."""
        self.corrupt = int(packets)

    def remove(self, dxl_id: int) -> None:
        """Missing-id fault: the servo no longer answers (unplugged)."""
        self.present.discard(dxl_id)

    def reboot(self, dxl_id: int, now: float = 0.0) -> None:
        """Reboot fault (a brown-out, or a REBOOT from another program): the servo restarts with its
        torque off, its RAM (indirect addresses included) at the defaults and its position kept."""
        self.advance(now)
        self._reboot(self.ids.index(dxl_id), now)

    def turn_by_hand(self, dxl_id: int, ticks: float, now: float = 0.0) -> None:
        """A person turns the shaft of `dxl_id` (torque off) by `ticks`, within its mechanical stops."""
        self.advance(now)
        k = self.ids.index(dxl_id)
        if self._table[k][X.TORQUE_ENABLE]:
            raise InputError(f"sim-dynamixel: servo {dxl_id} holds its position (torque on): cannot turn it")
        self._x[k] = float(self._clamp(self._x + np.eye(len(self.ids))[k] * ticks * self._direction()[k])[k])
        self._replan(now)

    def shaft(self, now: float) -> np.ndarray:
        """Physical shaft positions (ticks, float, normal counting in the frame of ``initial``) at `now`:
        what the mechanism sees whatever the Drive Mode, the Homing Offset or a power-up does to the readings."""
        self.advance(now)
        return self._direction() * (self._x - self._shift)

    def _direction(self) -> np.ndarray:
        """+1 per servo in normal mode, -1 in reverse mode (Drive Mode bit 0)."""
        return np.array([-1.0 if t[X.DRIVE_MODE] & X.DRIVE_REVERSE else 1.0 for t in self._table])

    def register(self, dxl_id: int, addr: int, size: int) -> int:
        """The register of `dxl_id` as a READ would return it (signed for 2 and 4 bytes)."""
        data = self._read(self.ids.index(dxl_id), addr, size)
        if data is None:
            raise InputError(f"sim-dynamixel: no register {addr} of size {size}")
        return int.from_bytes(data, "little", signed=size > 1)

    def power_cycle(self, now: float = 0.0, dxl_id: int | None = None) -> None:
        """Power-cycle fault: every servo (or `dxl_id`) loses power and starts again, as a REBOOT does."""
        self.advance(now)
        for k in range(len(self.ids)) if dxl_id is None else [self.ids.index(dxl_id)]:
            self._reboot(k, now)

    def _reboot(self, k: int, now: float) -> None:
        """Restart servo k: torque off, RAM (indirect addresses included) at its power-up defaults, and the
        multi-turn count lost: the present position reads within one turn (0..4095) plus the homing offset."""
        t = self._table[k]
        t[X.HARDWARE_ERROR] = 0
        self._lose_turns(k, now)
        self._torque(k, False, now)  # after the wrap: the reference restarts from the position as read now
        t[64:120] = bytes(56)  # RAM back to its defaults (zero here), the shaft where it is
        t[X.STATUS_RETURN] = 2
        t[X.GOAL_CURRENT : X.GOAL_CURRENT + 2] = t[X.CURRENT_LIMIT : X.CURRENT_LIMIT + 2]
        struct.pack_into("<H", t, X.POSITION_P_GAIN, P_GAIN_DEFAULT)
        for j in range(X.INDIRECT_COUNT):  # each indirect address names its own data byte again
            struct.pack_into("<H", t, X.INDIRECT_ADDRESS + 2 * j, X.INDIRECT_DATA + j)
        struct.pack_into("<i", t, X.GOAL_POSITION, int(np.rint(self._x[k])))

    def _lose_turns(self, k: int, now: float) -> None:
        """Servo k reads within one turn (0..4095) plus the Homing Offset, the shaft where it is (a lost count)."""
        (offset,) = struct.unpack_from("<i", self._table[k], X.HOMING_OFFSET)
        wrapped = (self._x[k] - offset) % TICKS_PER_REV + offset
        self._shift[k] += wrapped - self._x[k]
        self._x[k], self._v[k] = wrapped, 0.0
        struct.pack_into("<i", self._table[k], X.GOAL_POSITION, int(np.rint(wrapped)))
        self._replan(now)

    def positions(self, now: float) -> np.ndarray:
        """Measured positions (ticks, float) at device time `now`."""
        self.advance(now)
        return self._x.copy()

    def torque(self, dxl_id: int) -> bool:
        return bool(self._table[self.ids.index(dxl_id)][X.TORQUE_ENABLE])

    def advance(self, now: float) -> None:
        """Integrate the servos to `now` (s) in steps of at most 1 ms; earlier times are ignored."""
        if self._t is None:
            self._t = now
            self._profile.plan(self._x, np.zeros_like(self._x), self._x, now)
        trip = _watchdog_due(self._table, self._heard, self._t, now)
        if trip is not None:  # the Bus Watchdog fires first: move to then, stop the servos it stops, go on
            self.advance(trip)
            r, v = self._profile.sample(trip)  # each stops as its profile brakes, from the reference's velocity
            goals = self._profile.target
            for k in _watchdog_stops(self._table, self._heard, trip):
                goals[k] = r[k] + v[k] * abs(v[k]) / (2 * self._profile.amax[k])
                struct.pack_into("<i", self._table[k], X.GOAL_POSITION, int(np.rint(goals[k])))
            self._profile.plan(r, v, goals, trip)
        on = np.array([t[X.TORQUE_ENABLE] == 1 for t in self._table])  # constant between packets
        while now > self._t + 1e-12:
            if self._t >= self._profile.end_time:  # the reference is at rest: one exact step to `now`
                r = self._profile.target
                decay = math.exp(-(now - self._t) / self.tau) if self.tau > 0 else 0.0
                x_new = self._clamp(np.where(on, r + (self._x - r) * decay, self._x))
                self._v = np.where(on, (r - x_new) / self.tau, 0.0) if self.tau > 0 else np.zeros_like(r)
                self._v = np.where(x_new == self._x, 0.0, self._v)  # at a stop the shaft stands still
                self._x, self._t = x_new, now
                return
            h = min(1e-3, now - self._t)
            self._t += h
            r, _ = self._profile.sample(self._t)
            x_new = r + (self._x - r) * (math.exp(-h / self.tau) if self.tau > 0 else 0.0)
            x_new = self._clamp(np.where(on, x_new, self._x))
            self._v = (x_new - self._x) / h
            self._x = x_new

    def _stops_read(self) -> np.ndarray:
        """(n, 2) the mechanical stops as the servos read them (reported ticks, low <= high)."""
        return np.sort(self._direction()[:, None] * self.stops + self._shift[:, None], axis=1)

    def _clamp(self, x: np.ndarray) -> np.ndarray:
        """Positions `x` (reported ticks) held at the mechanical stops."""
        lim = self._stops_read()
        give = self.loads.give(self._table)  # a stop pressed at the cap yields by its compliance
        return self.loads.hold(np.clip(x, lim[:, 0] - give, lim[:, 1] + give))

    def _current(self, k: int) -> int:
        """Present Current (2.69 mA units) of servo k (`crtraj.hardware.dynamixel._sim_shaft.ShaftLoads.current`):
        its tendon's load, plus the position loop's output while the shaft presses a stop toward its reference,
        within the cap of its operating mode."""
        r = float(self._profile.sample(self._t if self._t is not None else 0.0)[0][k])
        lo, hi = self._stops_read()[k]
        pressing = (r > hi and self._x[k] >= hi) or (r < lo and self._x[k] <= lo)
        return self.loads.current(self._table[k], k, r, float(self._x[k]), bool(pressing))

    def reply_time(self, request_size: int, replies: list[bytes]) -> float:
        """Bus time (s) of one transaction: the request's and replies' bytes at 10 bits each at the bus rate,
        plus each replying servo's Return Delay Time (a sync read's replies come one after another)."""
        wire = (request_size + sum(len(r) for r in replies)) * 10.0 / self.baud
        return wire + sum(self.reply_delay(r[4]) for r in replies)

    def reply_delay(self, dxl_id: int) -> float:
        """The Return Delay Time of servo `dxl_id` (s): 2 us per unit of its register, before each reply."""
        return 2e-6 * self._table[self.ids.index(dxl_id)][X.RETURN_DELAY]

    def _replan(self, now: float) -> None:
        """Re-plan every servo's reference from where it is toward its goal (or its position, torque off)."""
        p, v = self._profile.sample(now)
        goals, vmax, amax = [], [], []
        for k, t in enumerate(self._table):
            on = t[X.TORQUE_ENABLE] == 1
            if not on:
                p[k], v[k] = self._x[k], 0.0
            goals.append(struct.unpack_from("<i", t, X.GOAL_POSITION)[0] if on else self._x[k])
            pv, pa = struct.unpack_from("<II", t, X.PROFILE_ACCELERATION)[::-1]
            vmax.append(pv * X.VELOCITY_UNIT / 60.0 * TICKS_PER_REV if pv else _UNLIMITED)
            amax.append(pa * X.ACCELERATION_UNIT / 3600.0 * TICKS_PER_REV if pa else _UNLIMITED)
        self._profile.vmax, self._profile.amax = np.array(vmax), np.array(amax)
        self._profile.plan(p, v, np.array(goals, dtype=float), now)

    def _torque(self, k: int, on: bool, now: float) -> None:
        t = self._table[k]
        t[X.TORQUE_ENABLE] = 1 if on else 0
        if on:  # a servo whose torque comes on holds where it is
            struct.pack_into("<i", t, X.GOAL_POSITION, int(np.rint(self._x[k])))
        self._replan(now)

    # ------------------------------------------------------------- protocol
    def handle(self, packet: dxl.Packet, now: float) -> list[bytes]:
        """The status packets that answer one instruction packet at device time `now` (s)."""
        self.advance(now)
        self._heard = now
        self.counts["packets"] += 1
        levels = {i: self._table[k][X.STATUS_RETURN] for k, i in enumerate(self.ids)}  # as the packet arrived
        replies = self._returned(packet, self._dispatch(packet, now), levels)
        n = self.counts["packets"]
        if self.silent > 0 or (self.silent_after is not None and n > self.silent_after):
            self.silent = max(self.silent - 1, 0)
            return []
        late = self.corrupt_after is not None and n > self.corrupt_after
        if (self.corrupt > 0 or late) and replies:
            self.corrupt = max(self.corrupt - 1, 0)
            replies = [r[:-1] + bytes([r[-1] ^ 0xFF]) for r in replies]
        self.counts["replies"] += len(replies)
        return replies

    def _returned(self, p: dxl.Packet, replies: list[bytes], levels: dict[int, int]) -> list[bytes]:
        """The replies each servo's Status Return Level lets out: 0 answers PING only, 1 PING and reads, 2 all."""
        need = 0 if p.instruction == dxl.PING else 1 if p.instruction in (dxl.READ, dxl.SYNC_READ) else 2
        return [r for r in replies if levels[r[4]] >= need]

    def _dispatch(self, p: dxl.Packet, now: float) -> list[bytes]:
        if p.instruction == dxl.SYNC_READ and p.id == dxl.BROADCAST_ID:
            return self._sync_read(p.params)
        if p.instruction == dxl.SYNC_WRITE and p.id == dxl.BROADCAST_ID:
            self._sync_write(p.params, now)
            return []
        if p.instruction == dxl.PING and p.id == dxl.BROADCAST_ID:
            return [self._status(k, 0, self._ping_params(k)) for k in self._answering(self.ids)]
        if p.id not in self.present:
            return []  # another id, or broadcast writes we do not model: no answer
        k = self.ids.index(p.id)
        if p.instruction == dxl.PING:
            return [self._status(k, 0, self._ping_params(k))]
        if p.instruction == dxl.READ:
            if len(p.params) != 4:
                return [self._status(k, dxl.ERR_DATA_LENGTH)]
            addr, length = struct.unpack("<HH", p.params)
            data = self._read(k, addr, length)
            return [self._status(k, dxl.ERR_DATA_RANGE)] if data is None else [self._status(k, 0, data)]
        if p.instruction == dxl.WRITE:
            if len(p.params) < 3:
                return [self._status(k, dxl.ERR_DATA_LENGTH)]
            (addr,) = struct.unpack_from("<H", p.params)
            return [self._status(k, self._write(k, addr, p.params[2:], now))]
        if p.instruction == dxl.CLEAR:
            error = _clear_refusal(self._table[k], p.params)
            if not error:  # the turn count lost, the LED (crtraj's homed marker) untouched
                self._lose_turns(k, now)
            return [self._status(k, error)]
        if p.instruction == dxl.REBOOT:
            reply = self._status(k, 0)
            self._reboot(k, now)
            return [reply]
        return [self._status(k, dxl.ERR_INSTRUCTION)]

    def _answering(self, ids: Sequence[int]) -> list[int]:
        return [self.ids.index(i) for i in ids if i in self.present]

    def _ping_params(self, k: int) -> bytes:
        return bytes(self._table[k][X.MODEL_NUMBER : X.MODEL_NUMBER + 2]) + bytes([self._table[k][X.FIRMWARE]])

    def _status(self, k: int, error: int, params: bytes = b"") -> bytes:
        alert = dxl.ERR_ALERT if self._table[k][X.HARDWARE_ERROR] else 0
        return dxl.status(self.ids[k], alert | error, params)

    def _read(self, k: int, addr: int, length: int) -> bytes | None:
        if length < 1 or addr + length > X.SIZE:
            return None
        t = self._table[k]
        struct.pack_into("<i", t, X.PRESENT_POSITION, int(np.rint(self._x[k])))
        rpm_units = self._v[k] * 60.0 / TICKS_PER_REV / X.VELOCITY_UNIT
        struct.pack_into("<i", t, X.PRESENT_VELOCITY, int(np.clip(np.rint(rpm_units), -(2**31), 2**31 - 1)))
        goal = struct.unpack_from("<i", t, X.GOAL_POSITION)[0]
        t[X.MOVING] = 1 if abs(self._x[k] - goal) > 1 else 0
        struct.pack_into("<h", t, X.PRESENT_CURRENT, self._current(k))
        first = max(0, addr - X.INDIRECT_DATA)
        for j in range(first, min(X.INDIRECT_COUNT, addr + length - X.INDIRECT_DATA)):  # mirrors of the bytes named
            (src,) = struct.unpack_from("<H", t, X.INDIRECT_ADDRESS + 2 * j)
            t[X.INDIRECT_DATA + j] = t[src] if src < X.INDIRECT_ADDRESS else 0
        return bytes(t[addr : addr + length])

    def _write(self, k: int, addr: int, data: bytes, now: float, replan: bool = True) -> int:
        """Apply a write; the status error number (0: done). replan: re-plan the motion now when the write
        changes it (a sync write re-plans once, after its last servo)."""
        t = self._table[k]
        end = addr + len(data)
        if end > X.SIZE:
            return dxl.ERR_DATA_RANGE
        if any(a in r for a in range(addr, end) for r in _READ_ONLY):
            return dxl.ERR_ACCESS
        locked = addr < _EEPROM_END or (addr < X.INDIRECT_DATA and end > X.INDIRECT_ADDRESS)
        if locked and t[X.TORQUE_ENABLE]:
            return dxl.ERR_ACCESS  # EEPROM and the indirect addresses are locked while the torque is on
        trial = bytearray(t[X.OPERATING_MODE : X.GOAL_POSITION + 4])  # the bytes the checks below read
        base = X.OPERATING_MODE
        lo_b, hi_b = max(addr, base), min(end, X.GOAL_POSITION + 4)
        if lo_b < hi_b:
            trial[lo_b - base : hi_b - base] = data[lo_b - addr : hi_b - addr]
        goal = struct.unpack_from("<i", trial, X.GOAL_POSITION - base)[0]
        extended = trial[0] in (X.EXTENDED_POSITION, X.CURRENT_POSITION)
        lo, hi = (-X.EXTENDED_LIMIT, X.EXTENDED_LIMIT) if extended else (0, 4095)
        if addr < X.GOAL_POSITION + 4 and end > X.GOAL_POSITION and not lo <= goal <= hi:
            return dxl.ERR_DATA_LIMIT
        if addr < X.GOAL_CURRENT + 2 and end > X.GOAL_CURRENT:  # e-manual: never above Current Limit (38)
            g = bytearray(t[X.GOAL_CURRENT : X.GOAL_CURRENT + 2])
            lo_g, hi_g = max(addr, X.GOAL_CURRENT), min(end, X.GOAL_CURRENT + 2)
            g[lo_g - X.GOAL_CURRENT : hi_g - X.GOAL_CURRENT] = data[lo_g - addr : hi_g - addr]
            if struct.unpack("<H", g)[0] > struct.unpack_from("<H", t, X.CURRENT_LIMIT)[0]:
                return dxl.ERR_DATA_LIMIT
        if _over_maximum(t, addr, data):
            return dxl.ERR_DATA_LIMIT
        if t[X.BUS_WATCHDOG] == X.WATCHDOG_TRIPPED and addr < X.GOAL_POSITION + 4 and end > X.GOAL_PWM:
            return dxl.ERR_DATA_RANGE  # after a watchdog stop the goal values are read-only until 98 reads 0
        torque = trial[X.TORQUE_ENABLE - base]
        if addr <= X.TORQUE_ENABLE < end and torque == 1 and t[X.HARDWARE_ERROR]:
            return dxl.ERR_RESULT_FAIL  # a servo in shutdown needs a reboot first
        if addr <= X.TORQUE_ENABLE < end and torque > 1:
            return dxl.ERR_DATA_LIMIT
        was_on, was_mode = t[X.TORQUE_ENABLE], t[X.OPERATING_MODE]
        (offset,) = struct.unpack_from("<i", t, X.HOMING_OFFSET)
        reverse = t[X.DRIVE_MODE] & X.DRIVE_REVERSE
        t[addr:end] = data
        if (t[X.DRIVE_MODE] & X.DRIVE_REVERSE) != reverse:  # the counting flips about the offset, the shaft stays
            self._x[k], self._shift[k] = 2 * offset - self._x[k], 2 * offset - self._shift[k]
            self._v[k] = 0.0
            struct.pack_into("<i", t, X.GOAL_POSITION, int(np.rint(self._x[k])))
            self._replan(now)
        if addr < X.HOMING_OFFSET + 4 and end > X.HOMING_OFFSET:  # the reading moves with the offset
            d = struct.unpack_from("<i", t, X.HOMING_OFFSET)[0] - offset
            self._x[k] += d
            self._shift[k] += d
            self._replan(now)
        mode3 = t[X.OPERATING_MODE] == X.POSITION
        if mode3 and (was_mode != X.POSITION or (t[X.TORQUE_ENABLE] and not was_on)):
            self._lose_turns(k, now)  # e-manual: switching to position mode, or torque on in it, resets the turns
        if addr <= X.TORQUE_ENABLE < end and t[X.TORQUE_ENABLE] != was_on:
            self._torque(k, bool(t[X.TORQUE_ENABLE]), now)
        elif end > X.PROFILE_ACCELERATION and addr < X.GOAL_POSITION + 4 and replan:
            self._replan(now)
        return 0

    def _sync_read(self, params: bytes) -> list[bytes]:
        if len(params) < 5:
            return []
        addr, length = struct.unpack_from("<HH", params)
        out = []
        for k in self._answering(list(params[4:])):
            data = self._read(k, addr, length)
            out.append(self._status(k, dxl.ERR_DATA_RANGE) if data is None else self._status(k, 0, data))
        return out

    def _sync_write(self, params: bytes, now: float) -> None:
        if len(params) < 4:
            return
        addr, length = struct.unpack_from("<HH", params)
        block = 1 + length
        body = params[4:]
        if length < 1 or len(body) % block:
            return  # malformed: a real servo ignores it
        self.counts["sync_writes"] += 1
        for j in range(0, len(body), block):
            dxl_id = body[j]
            if dxl_id in self.present:
                self._write(self.ids.index(dxl_id), addr, body[j + 1 : j + block], now, replan=False)
        if addr < X.GOAL_POSITION + 4 and addr + length > X.PROFILE_ACCELERATION:
            self._replan(now)
