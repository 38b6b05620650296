"""Absolute position after a power-up: the homing state file, and the check every Dynamixel stream starts with.

An X-series servo in extended position mode keeps its multi-turn count only
while powered: after a power-up or reboot its Present Position reads within
one turn (0..4095 ticks) plus the Homing Offset (register 20, EEPROM). A z
stage spanning 15 turns, or a spool turned while unpowered, then reads
whole turns away from where it is.

How crtraj knows a servo's reading is absolute:

- Homing (`crtraj.hardware.dynamixel.Homer`) writes the Homing Offset that makes
  the reading equal the reference at the stop or mark, then sets the servo's
  LED register (65, RAM) to 1: the **homed marker**. RAM returns to its
  power-up defaults on every power-up and reboot, so a marker that reads 0
  means "powered up since it was homed". (Register 65 was chosen because
  nothing else crtraj does writes it, its default is documented as 0, and the
  lit LED shows a person which servos are homed.)
- The state file (`state_path`: ``<robot>.homing.json`` next to the robot
  file) records per servo its identity, the Homing Offset written and the
  time. The issue asks for a serial number: the X-series control table has
  none (EEPROM holds Model Number, Model Information, Firmware Version and ID,
  nothing per unit), so the identity is id + model number + model information
  + firmware version, and a servo whose identity or offset differs from the
  file is refused as not the one homed. Two units of one model and firmware
  look alike on the bus; a swapped one is still caught, by the marker: it
  was powered up after the homing, so its LED reads 0.

`PowerUpCheck` runs at connect, before torque comes on: a multi-turn actuator
(position limits spanning a turn or more) must carry the marker, read Operating Mode 4 or 5, match the
state file (Homing Offset, identity) and read within half a turn of where crtraj last let it go (the turn
cross-check: a count lost behind a lit marker moves the reading by whole turns), else a one-line refusal names
the servo. A single-turn actuator (a
spool whose limits span less than a turn) is unwrapped: without the marker its
reading is moved by whole turns into the turn centred on its limits window
(`unwrap`), which is exact whenever the spool is within its limits; a reading
that lands outside the window is refused naming the servo. A spool turned a
whole revolution while unpowered reads the same as one that was not: the
unwrap puts it back within its limits, where it has to be for the cable to be
taut; crtraj never uses it with a 2 pi offset.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable
from dataclasses import MISSING, asdict, dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_json, read_json
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.transport import TransportError

STATE_SUFFIX = ".homing.json"
MAX_STATE_BYTES = 1 << 20


class ServoIO(Protocol):
    """Register access to the servos of one bus (`crtraj.hardware.dynamixel._link.DynamixelTransport`)."""

    def read(self, dxl_id: int, addr: int, size: int) -> int:
        """Register value (signed for 2- and 4-byte registers)."""
        ...

    def write(self, dxl_id: int, addr: int, value: int, size: int, what: str) -> None:
        """Write a register; `TransportError` naming `what` when the servo refuses."""
        ...


def state_path(robot_file: str | Path) -> Path:
    """The homing state file of a robot file: ``problems/robots/cdsr2.toml`` -> ``cdsr2.homing.json`` beside it."""
    p = Path(robot_file)
    return p.with_name(p.stem + STATE_SUFFIX)


@dataclass(frozen=True)
class HomedServo:
    """One homed servo: bus id, actuator name, model number, Homing Offset written (ticks), method, UTC time,
    and the rest of its identity: Model Information (register 2) and Firmware Version (register 6); -1 in a
    file written before they were recorded (it then matches no servo: home again). last: its Present Position
    (ticks) when crtraj last let it go (the end of the homing, of each stream); None: not recorded."""

    id: int
    name: str
    model: int
    offset: int
    method: str
    time: str
    model_information: int = -1
    firmware: int = -1
    last: int | None = None

    def identity(self) -> tuple[int, int, int]:
        """(model number, model information, firmware version)."""
        return (self.model, self.model_information, self.firmware)


def identity(io: ServoIO, dxl_id: int) -> tuple[int, int, int]:
    """(model number, model information, firmware version) read from servo `dxl_id`."""
    return (
        io.read(dxl_id, X.MODEL_NUMBER, 2) & 0xFFFF,
        io.read(dxl_id, X.MODEL_INFORMATION, 4),
        io.read(dxl_id, X.FIRMWARE, 1),
    )


@dataclass(frozen=True)
class HomingState:
    """The servos homed (the state file's content)."""

    servos: tuple[HomedServo, ...] = ()

    def get(self, dxl_id: int) -> HomedServo | None:
        return next((s for s in self.servos if s.id == dxl_id), None)

    @classmethod
    def load(cls, path: str | Path) -> HomingState:
        """The state in `path` (empty when there is no file); one-line `InputError` for a damaged file."""
        p = Path(path)
        if not p.exists():
            return cls()
        # crtraj writes this file itself (atomically): a damaged one is fixed by homing again, not by editing it
        again = "delete it and run crtraj home again"
        try:
            data = read_json(p, MAX_STATE_BYTES)
        except InputError as exc:
            why = str(exc).removeprefix(f"{p}: ").split(";")[0]
            raise InputError(f"{p}: damaged homing state file ({why}); {again}") from None
        try:
            rows = data["servos"]
            fields = HomedServo.__dataclass_fields__
            return cls(
                tuple(HomedServo(**{k: r[k] for k in fields if k in r or fields[k].default is MISSING}) for r in rows)
            )
        except (KeyError, TypeError) as exc:
            raise InputError(f"{p}: not a homing state file (servos: {exc}); {again}") from None

    def save(self, path: str | Path) -> Path:
        """Write atomically (a crash leaves the old file or the new one, never half of one)."""
        return atomic_write_json(path, {"kind": "crtraj-homing", "servos": [asdict(s) for s in self.servos]})

    def moved(self, readings: dict[int, int]) -> HomingState:
        """This state with `last` set to `readings` (ticks, by id) for the servos it holds."""
        return HomingState(tuple(replace(s, last=readings.get(s.id, s.last)) for s in self.servos))

    def merged(self, new: list[HomedServo]) -> HomingState:
        """This state with the entries of `new` replacing those of the same id."""
        ids = {s.id for s in new}
        return HomingState(tuple(sorted([*(s for s in self.servos if s.id not in ids), *new], key=lambda s: s.id)))


def now_text() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def windows(acts: Actuators) -> np.ndarray:
    """(nq, 2) position limits of each actuator in ticks (low, high)."""
    t = acts.bus.ticks(np.stack([acts.lower, acts.upper]))
    return np.sort(t, axis=0).T


def multi_turn(acts: Actuators) -> np.ndarray:
    """(nq,) bool: the actuator's limits span a turn or more (its reading needs homing after a power-up)."""
    w = windows(acts)
    return (w[:, 1] - w[:, 0]) >= np.asarray(acts.bus.ticks_per_rev)


def unwrap(reading: int, lo: int, hi: int, per_rev: int) -> int | None:
    """Whole turns (ticks, a multiple of `per_rev`) to add to a within-one-turn `reading` so that it lies in
    [lo, hi], choosing the turn centred on the window; None when that turn does not hold it."""
    centre = 0.5 * (lo + hi)
    k = round((centre - reading) / per_rev)
    shift = int(k) * per_rev
    return shift if lo <= reading + shift <= hi else None


class PowerUpCheck:
    """The connect-time check of absolute positions (see the module doc). `command`: what to run to home."""

    def __init__(self, io: ServoIO, acts: Actuators, state: HomingState, command: str = "crtraj home") -> None:
        self.io, self.acts, self.state, self.command = io, acts, state, command
        self.unwrapped: dict[str, int] = {}  # actuator name -> turns moved by the unwrap

    def run(self) -> None:
        """Check (and unwrap) every servo; `InputError` naming the first that cannot be used. Torque must be off."""
        bus, win, multi = self.acts.bus, windows(self.acts), multi_turn(self.acts)
        marked = [self.io.read(dxl_id, X.LED, 1) == 1 for dxl_id in bus.ids]
        for k, dxl_id in enumerate(bus.ids):  # first the refusals, before anything is written
            if multi[k]:
                self._check_homed(k, dxl_id, marked[k])
        for k, dxl_id in enumerate(bus.ids):
            if not multi[k] and not marked[k]:
                self._unwrap(k, dxl_id, self.io.read(dxl_id, X.PRESENT_POSITION, 4), win[k])
            lo, hi = win[k]
            reading = self.io.read(dxl_id, X.PRESENT_POSITION, 4)
            if not lo <= reading <= hi:
                value, unit = float(bus.values(np.full(len(bus.ids), reading))[k]), self.acts.units[k]
                raise InputError(
                    f"servo {bus.name_of(dxl_id)}: reads {value:.4g} {unit}, outside its position limits "
                    f"[{self.acts.lower[k]:g}, {self.acts.upper[k]:g}] {unit}: move it back within them with the "
                    f"torque off, then run {self.command}"
                )

    def _check_homed(self, k: int, dxl_id: int, marked: bool) -> None:
        bus = self.acts.bus
        who = f"servo {bus.name_of(dxl_id)}"
        if not marked:
            raise InputError(
                f"{who}: not homed since its last power-up or reboot (its position reads within one turn); "
                f"run {self.command}"
            )
        # the marker is RAM: switching to Operating Mode 3 (or torque on in it) loses the turns and leaves it lit,
        # so it counts only with a multi-turn mode read back (this check runs before connect writes mode 4)
        mode = self.io.read(dxl_id, X.OPERATING_MODE, 1)
        if mode not in (X.EXTENDED_POSITION, X.CURRENT_POSITION):
            raise InputError(
                f"{who}: Operating Mode reads {mode}, not 4 or 5 (multi-turn): in mode 3 a servo loses its turn "
                f"count though its homed marker stays lit; run {self.command}"
            )
        entry = self.state.get(dxl_id)
        offset = self.io.read(dxl_id, X.HOMING_OFFSET, 4)
        if entry is None or entry.offset != offset:
            was = "no entry" if entry is None else f"offset {entry.offset}"
            raise InputError(
                f"{who}: its homing offset {offset} does not match the homing state file ({was}); run {self.command}"
            )
        found = identity(self.io, dxl_id)
        if found != entry.identity():
            raise InputError(
                f"{who}: model {found[0]}, model information {found[1]}, firmware {found[2]} is not the servo the "
                f"homing state file recorded (model {entry.model}, model information {entry.model_information}, "
                f"firmware {entry.firmware}): another servo on this id; run {self.command}"
            )
        self._check_last(k, dxl_id, entry)

    def _check_last(self, k: int, dxl_id: int, entry: HomedServo) -> None:
        """The turn cross-check, at every connect of every multi-turn servo: it must read within half a turn of
        where crtraj last let it go (`HomedServo.last`, recorded by the homing and by every stream's end). A Clear
        instruction or a spell in mode 3 moves the reading by whole turns with the marker, the mode and the
        Homing Offset unchanged (a lost count keeps the phase within the turn, so only the turns tell). An entry
        without `last` (written before crtraj recorded it) cannot be cross-checked: refused, home again."""
        if entry.last is None:
            raise InputError(
                f"servo {self.acts.bus.name_of(dxl_id)}: the homing state file does not record where crtraj last let "
                f"it go (an older crtraj wrote it), so its turn count cannot be cross-checked; run {self.command}"
            )
        n = int(self.acts.bus.ticks_per_rev[k])
        reading = self.io.read(dxl_id, X.PRESENT_POSITION, 4)
        if abs(reading - entry.last) * 2 >= n:
            raise InputError(
                f"servo {self.acts.bus.name_of(dxl_id)}: reads {reading} ticks, {(reading - entry.last) / n:+.2f} "
                f"turns from where crtraj left it ({entry.last}): its turn count was lost (a Clear instruction, "
                f"Operating Mode 3) or it was turned by hand; run {self.command}"
            )

    def _unwrap(self, k: int, dxl_id: int, reading: int, win: np.ndarray) -> None:
        bus, n = self.acts.bus, int(self.acts.bus.ticks_per_rev[k])
        shift = unwrap(reading, int(win[0]), int(win[1]), n)
        if shift is None:
            unit = self.acts.units[k]
            raise InputError(
                f"servo {bus.name_of(dxl_id)}: after a power-up it reads {reading % n} ticks within its turn, which "
                f"lies in no turn within its position limits [{self.acts.lower[k]:g}, {self.acts.upper[k]:g}] "
                f"{unit}: turn it by hand into its limits (or check zero_offset), then connect again"
            )
        if shift:
            offset = self.io.read(dxl_id, X.HOMING_OFFSET, 4)
            self.io.write(dxl_id, X.HOMING_OFFSET, (offset + shift) & 0xFFFFFFFF, 4, "homing offset")
            self.unwrapped[bus.names[k]] = shift // n
        self.io.write(dxl_id, X.LED, 1, 1, "homed marker (LED)")


def homing_command(robot_file: Any, device: str) -> str:
    """The command line that homes the robot (for the refusals' text). Without a robot file the stream has no
    homing state to read (it lies beside the robot file), so the text says to pass one: else `crtraj home`
    would succeed and the same refusal would follow."""
    if not robot_file:
        return f"crtraj home --dynamixel {device} --robot ROBOT.toml, then stream with the same --robot ROBOT.toml"
    return f"crtraj home --dynamixel {device} --robot {robot_file}"


def record_last(
    io: ServoIO, bus_ids: tuple[int, ...], state: HomingState, path: Path | None, warn: Callable[[str], None]
) -> None:
    """Where each homed servo of `state` among `bus_ids` on `io` is let go (`HomedServo.last`), into the state
    file `path` (None: not kept in a file): the next connect refuses one whose reading moved by whole turns since
    (a lost turn count). A failed read or write is a warning, never an error (the servos are being let go)."""
    if path is None or not state.servos:
        return
    try:
        ids = [s.id for s in state.servos if s.id in bus_ids]
        state.moved({i: io.read(i, X.PRESENT_POSITION, 4) for i in ids}).save(path)
    except (TransportError, OSError) as exc:
        warn(f"warning: {path}: where the servos stopped is not recorded ({exc})")
