"""Where each actuator sits on a Dynamixel bus, and its value in encoder ticks.

Keys of ``[robot.actuators]`` (shared default, ``[robot.actuators.servo.<name>]``
override, ``[robot.actuators.z]`` for the stage):

- ``id``: the servo's bus id (0..252), per actuator, all different;
- ``ticks_per_rev``: encoder ticks per output revolution (4096 for the X-series);
- ``model``: the model number the servo must report (XM430-W350: 1020);
- ``lead`` (z only): mm of stage travel per revolution of its servo;
- ``drive_mode = { reverse = true }``: the servo's Drive Mode register (10) as it must be
  (`DriveMode`): connect sets a declared reverse bit and refuses a bit it finds undeclared.

Either no actuator has an ``id`` (the robot has no Dynamixel bus) or every
actuator has one. The actuator value (`crtraj.hardware.actuators`: rad for a
cable servo, already through spool radius, zero offset and sign; mm for the
stage) maps to ticks by one revolution = ``2 pi`` rad or ``lead`` mm::

    ticks = round(value * ticks_per_rev / per_rev)
    value = ticks * per_rev / ticks_per_rev

so a round trip value -> ticks -> value is exact to half a tick
(`resolution` / 2) and ticks -> value -> ticks is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.core.options import Options, option

MAX_TICKS_PER_REV = 1 << 20
MAX_MODEL = 0xFFFF
BUS_KEYS = ("id", "ticks_per_rev", "model", "drive_mode")
# why the time-based profile is refused: with Drive Mode bit 2 the servo reads Profile Velocity and Profile
# Acceleration as times (ms per goal), so the speed and acceleration caps crtraj writes from the actuator limits
# (the servo's own backstop under every streamed set-point) would not exist
TIME_PROFILE_UNSUPPORTED = "crtraj does not support the time-based profile (it would void the servo's speed caps)"
# why "torque on by goal update" is refused: with Drive Mode bit 3 a goal written to a servo whose torque is off
# (after a shutdown, or a stop with torque = "off") turns its torque on and moves it
TORQUE_ON_GOAL_UNSUPPORTED = "crtraj does not support torque on by goal update (a goal would re-enable a stopped servo)"


@dataclass(frozen=True)
class DriveMode(Options):
    """Drive Mode (register 10, EEPROM) of one servo, as the robot file declares it: an inline table
    ``drive_mode = { reverse = true }`` in ``[robot.actuators.servo.<name>]``, ``[robot.actuators.z]`` or once for
    all servos in ``[robot.actuators]``.

    reverse: bit 0, the direction of rotation. ROBOTIS X-series e-manual: normal mode (0) counts
    counter-clockwise (seen from the front) as positive, reverse mode (1) clockwise; Goal Position, Present
    Position and Present Velocity all follow the bit. Declared, connect sets the bit (torque off) and the values
    crtraj sends and reads stay in the servo's own counting: the robot file's ``sign`` describes the values
    as the reversed servo reports them, crtraj never negates them itself. Setting the bit changes what the servo
    reads, so crtraj then clears the servo's homed marker: a spool is unwrapped again, a multi-turn actuator
    must be homed again. A reverse bit found on a servo that does not declare it is a one-line refusal.
    time_based_profile: bit 2. Only false: crtraj does not support the time-based profile, because the servo
    then reads Profile Velocity and Acceleration as times (ms per goal) and the speed and acceleration caps
    crtraj writes from the actuator limits would not exist; the bit found on a servo is a one-line refusal.
    torque_on_by_goal_update: bit 3. Only false: with it a goal written to a servo whose torque is off turns the
    torque on and moves it, so a servo that shut down, or stopped with ``torque = "off"``, would not stay
    stopped; the key, or the bit found on a servo, is a one-line refusal.
    """

    SECTION = "robot.actuators.drive_mode"

    reverse: bool = option(False)
    time_based_profile: bool = option(False)
    torque_on_by_goal_update: bool = option(False)

    @property
    def bits(self) -> int:
        """The register value these declarations give (bit 0 reverse, bit 2 time-based profile, bit 3 torque on
        by goal update)."""
        bits = (0x01 if self.reverse else 0) | (0x04 if self.time_based_profile else 0)
        return bits | (0x08 if self.torque_on_by_goal_update else 0)


def _drive_mode(t: Table, base: dict[str, Any]) -> DriveMode:
    """`DriveMode` of `t`'s ``drive_mode`` table (else `base`'s, else the default); one line for a bit crtraj
    cannot honour."""
    if not t.has("drive_mode"):
        return base.get("drive_mode") or DriveMode()
    sub = t.table("drive_mode")
    mode = DriveMode.from_table(sub)
    if mode.time_based_profile:
        raise sub.error("time_based_profile", f"{TIME_PROFILE_UNSUPPORTED}: remove this key from the robot file")
    if mode.torque_on_by_goal_update:
        raise sub.error(
            "torque_on_by_goal_update", f"{TORQUE_ON_GOAL_UNSUPPORTED}: remove this key from the robot file"
        )
    return mode


def read_bus_keys(t: Table, base: dict[str, Any], stage: bool) -> dict[str, Any]:
    """The bus keys of one actuator table `t` (``lead`` too for the stage), falling back to `base`."""
    d: dict[str, Any] = {"id": t.int("id", None, ge=0, le=252) if t.has("id") else None}
    for key, hi in (("ticks_per_rev", MAX_TICKS_PER_REV), ("model", MAX_MODEL)):
        d[key] = t.int(key, ge=1 if key == "ticks_per_rev" else 0, le=hi) if t.has(key) else base.get(key)
    d["drive_mode"] = _drive_mode(t, base)
    if stage:
        d["lead"] = t.float("lead", gt=0.0, limit=MAX_LENGTH) if t.has("lead") else None
    return d


@dataclass(frozen=True)
class ServoBus:
    """Bus ids, model numbers and tick scales of the nq actuators (cable servos, then the stage).

    per_rev: actuator units per output revolution (2 pi rad for servos, the lead in mm for the stage).
    drive_modes: each servo's declared Drive Mode (`DriveMode`; empty: every servo in normal mode).
    """

    names: tuple[str, ...]
    ids: tuple[int, ...]
    models: tuple[int, ...]
    ticks_per_rev: tuple[int, ...]
    per_rev: tuple[float, ...]
    drive_modes: tuple[DriveMode, ...] = ()

    @classmethod
    def from_rows(cls, names: tuple[str, ...], rows: list[dict[str, Any]], where: list[str]) -> ServoBus | None:
        """The bus of actuators `names` from their parsed `read_bus_keys` rows (None: no ids at all);
        one-line `InputError` naming the field (`where[i]` is row i's table path) otherwise."""
        if all(r["id"] is None for r in rows):
            for r, w in zip(rows, where, strict=True):
                if r.get("lead") is not None:
                    raise Table({}, w).error("lead", "set without an id (the bus keys need an id per actuator)")
            return None
        seen: dict[int, str] = {}
        per_rev: list[float] = []
        for name, r, w in zip(names, rows, where, strict=True):
            t = Table({}, w)
            if r["id"] is None:
                raise t.error("id", "missing: once one actuator has a Dynamixel id, every actuator needs one")
            if r["id"] in seen:
                raise t.error("id", f"{r['id']} is also the id of {seen[r['id']]}")
            seen[r["id"]] = name
            for key in ("ticks_per_rev", "model"):
                if r[key] is None:
                    raise t.error(key, "missing (required with an id; set it here or once in [robot.actuators])")
            if "lead" in r:
                if r["lead"] is None:
                    raise t.error("lead", "missing: mm of stage travel per revolution of its servo (needed with an id)")
                per_rev.append(float(r["lead"]))
            else:
                per_rev.append(2.0 * math.pi)
        return cls(
            names=tuple(names),
            ids=tuple(int(r["id"]) for r in rows),
            models=tuple(int(r["model"]) for r in rows),
            ticks_per_rev=tuple(int(r["ticks_per_rev"]) for r in rows),
            per_rev=tuple(per_rev),
            drive_modes=tuple(r.get("drive_mode") or DriveMode() for r in rows),
        )

    def drive_mode(self, k: int) -> DriveMode:
        """The declared Drive Mode of actuator k (normal when none was declared)."""
        return self.drive_modes[k] if self.drive_modes else DriveMode()

    @property
    def resolution(self) -> np.ndarray:
        """Actuator units (rad, mm) per tick."""
        return np.asarray(self.per_rev) / np.asarray(self.ticks_per_rev, dtype=float)

    def ticks(self, values: Any) -> np.ndarray:
        """Ticks (int64, nearest) of actuator values (..., nq) in rad / mm."""
        return np.rint(np.asarray(values, dtype=float) / self.resolution).astype(np.int64)

    def values(self, ticks: Any) -> np.ndarray:
        """Actuator values (rad, mm) of ticks (..., nq); the inverse of `ticks` up to half a tick."""
        return np.asarray(ticks, dtype=np.int64) * self.resolution

    def name_of(self, dxl_id: int) -> str:
        """``id 3 (s1c3)``: a servo as the messages name it."""
        return f"id {dxl_id} ({self.names[self.ids.index(dxl_id)]})" if dxl_id in self.ids else f"id {dxl_id}"

    def rows(self) -> list[dict[str, Any]]:
        """Each actuator's bus keys as written in ``[robot.actuators]``."""
        out = []
        for i in range(len(self.ids)):
            d: dict[str, Any] = {"id": self.ids[i], "ticks_per_rev": self.ticks_per_rev[i], "model": self.models[i]}
            if i == len(self.ids) - 1:
                d["lead"] = self.per_rev[i]
            if self.drive_mode(i).reverse:
                d["drive_mode"] = {"reverse": True}
            out.append(d)
        return out
