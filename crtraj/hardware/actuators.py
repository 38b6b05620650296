"""Actuators of a cable-driven robot: cable lengths <-> servo angles, the z stage, and their limits.

Each cable is wound on the spool of one servo. With spool radius ``r_s`` (mm),
zero offset ``a0`` (rad, the servo angle at which the cable has its
straight-pose length ``L_k``) and winding sign ``s`` (+1 when a positive angle
pays cable out):

    angle = a0 + s (q - L_k) / r_s        (rad)
    q     = L_k + s r_s (angle - a0)      (mm)

The base translation is a linear stage commanded in mm:
``value = z0 + s z``. Limits are in the actuator's own units: rad, rad/s,
rad/s^2 for servos; mm, mm/s, mm/s^2 for the stage.

Actuator names: ``s<k>c<i>`` for cable i of segment k (both 1-based), then
``z``. The TOML schema is the ``[robot.actuators]`` table of
problems/robots/cdsr2.toml.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table, check_array
from crtraj.hardware.servo_bus import ServoBus, read_bus_keys
from crtraj.planning.rate_limits import RateLimits

# Smallest spool radius (mm): below it one radian of servo is less than a micrometre of cable.
MIN_SPOOL = 1e-3
# Largest speed or acceleration limit (rad/s, mm/s, rad/s^2, mm/s^2).
MAX_RATE = 1e6


def _sign(t: Table, key: str, default: Any) -> float:
    v = t.raw(key, default)
    if v not in (1, -1) or isinstance(v, bool):
        raise t.error(key, f"must be 1 or -1, got {v!r}")
    return float(v)


def _limits(t: Table, key: str) -> tuple[float, float]:
    lo, hi = t.vec(key, 2, limit=MAX_LENGTH)
    if lo > hi:
        raise t.error(key, f"must be [low, high] with low <= high, got [{lo:g}, {hi:g}]")
    return lo, hi


def _pick(t: Table, key: str, base: dict[str, Any], read: Any) -> Any:
    """`key` from `t` when present, else the shared default, else a missing-key error."""
    if t.has(key):
        return read()
    if base.get(key) is not None:
        return base[key]
    raise t.error(key, "missing (required; set it here or once for all servos in [robot.actuators])")


def _read_actuator(t: Table, base: dict[str, Any], spool: bool, bus_base: dict[str, Any]) -> dict[str, Any]:
    """Read one actuator's keys from `t`, falling back to `base` (the shared servo defaults);
    its Dynamixel bus keys (`crtraj.hardware.servo_bus`, defaults `bus_base`) go to ``d["bus"]``."""
    d: dict[str, Any] = {"bus": read_bus_keys(t, bus_base, stage=not spool)}
    if spool:
        d["spool_radius"] = _pick(
            t, "spool_radius", base, lambda: t.float("spool_radius", ge=MIN_SPOOL, limit=MAX_LENGTH)
        )
    d["zero_offset"] = t.float("zero_offset", base.get("zero_offset", 0.0), limit=MAX_LENGTH)
    d["sign"] = _sign(t, "sign", base.get("sign", 1))
    d["position_limits"] = _pick(t, "position_limits", base, lambda: _limits(t, "position_limits"))
    d["velocity_limit"] = _pick(t, "velocity_limit", base, lambda: t.float("velocity_limit", gt=0.0, limit=MAX_RATE))
    d["acceleration_limit"] = _pick(
        t, "acceleration_limit", base, lambda: t.float("acceleration_limit", gt=0.0, limit=MAX_RATE)
    )
    return d


@dataclass(frozen=True)
class Actuators:
    """Per-actuator conversion and limits, as arrays over the nq = 3n+1 actuators.

    scale: value units per mm of q (sign / spool radius for servos, sign for
    the stage). offset: value at the reference q. rest: reference q (mm) -
    straight-pose cable lengths and z = 0; None until bound to a robot
    (`for_robot`), because the segment lengths live in the robot table.
    lower/upper: position limits; vmax, amax: speed and acceleration limits.
    bus: the Dynamixel ids, models and tick scales (`ServoBus`), None without ids.
    """

    n_segments: int
    spool_radius: np.ndarray  # (3n,) mm
    sign: np.ndarray  # (nq,) +-1
    zero_offset: np.ndarray  # (nq,) rad for servos, mm for the stage
    lower: np.ndarray
    upper: np.ndarray
    vmax: np.ndarray
    amax: np.ndarray
    rest: np.ndarray | None = None
    bus: ServoBus | None = None  # Dynamixel ids and tick scales, when the robot file gives them

    def __post_init__(self) -> None:
        for name in ("spool_radius", "sign", "zero_offset", "lower", "upper", "vmax", "amax"):
            a = np.asarray(getattr(self, name), dtype=float).copy()
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    # ------------------------------------------------------------------ names
    @property
    def n(self) -> int:
        """Number of actuators (3 per segment + the z stage)."""
        return 3 * self.n_segments + 1

    @property
    def names(self) -> tuple[str, ...]:
        return (*tuple(f"s{k + 1}c{i + 1}" for k in range(self.n_segments) for i in range(3)), "z")

    @property
    def units(self) -> tuple[str, ...]:
        """Position unit of each actuator's value."""
        return ("rad",) * (3 * self.n_segments) + ("mm",)

    def index(self, name: str) -> int:
        """Position of actuator `name`; `InputError` for an unknown name."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(f"actuator {name!r}: unknown (known: {', '.join(self.names)})") from None

    @property
    def scale(self) -> np.ndarray:
        """d value / d q: sign / spool radius (rad/mm) for servos, sign for the stage."""
        return np.concatenate([self.sign[:-1] / self.spool_radius, self.sign[-1:]])

    # ---------------------------------------------------------- conversions
    def for_robot(self, robot: Any) -> Actuators:
        """A copy bound to `robot`'s straight-pose cable lengths (needed by `command`)."""
        if robot.n_segments != self.n_segments:
            raise InputError(
                f"robot.actuators: written for {self.n_segments} segments, robot {robot.name!r} has {robot.n_segments}"
            )
        _, q0 = robot.cable_matrix()
        return replace(self, rest=np.asarray(q0, dtype=float))

    def _rest(self) -> np.ndarray:
        if self.rest is None:
            raise InputError("actuators: not bound to a robot; use actuators.for_robot(robot) (needs segment lengths)")
        return self.rest

    def command(self, q: Any, name: str = "q") -> np.ndarray:
        """Actuator values (rad for servos, mm for the stage) for actuation q (..., nq) in mm."""
        a = np.asarray(q, dtype=float)
        a2 = check_array(a.reshape(1, -1) if a.ndim == 1 else a, name, (None, self.n))
        v = self.zero_offset + (a2 - self._rest()) * self.scale
        return v[0] if a.ndim == 1 else v

    def actuation(self, values: Any, name: str = "values") -> np.ndarray:
        """Actuation q (mm) for actuator values (..., nq); the inverse of `command`."""
        a = np.asarray(values, dtype=float)
        a2 = check_array(a.reshape(1, -1) if a.ndim == 1 else a, name, (None, self.n))
        q = self._rest() + (a2 - self.zero_offset) / self.scale
        return q[0] if a.ndim == 1 else q

    def rate_limits(self, robot: Any) -> RateLimits:
        """The speed and acceleration limits as linear limits on configuration motion of `robot`.

        value = offset + scale (q - rest), q = q0 + A x: d value / d x = diag(scale) A.
        """
        A, _ = robot.cable_matrix()
        return RateLimits(self.scale[:, None] * np.asarray(A, dtype=float), self.vmax, self.amax, self.names)

    def position_violation(self, values: np.ndarray) -> np.ndarray:
        """How far each value is outside its position limits (<= 0 inside), same shape as values."""
        v = np.asarray(values, dtype=float)
        return np.maximum(self.lower - v, v - self.upper)

    # ------------------------------------------------------------- file I/O
    @classmethod
    def from_robot(cls, robot: Any) -> Actuators:
        """Parse `robot`'s raw ``[robot.actuators]`` table and bind it to the robot (`for_robot`).

        One-line `InputError` naming the field when the table is missing or bad.
        """
        if robot.actuators is None:
            raise InputError("robot.actuators: missing; add a [robot.actuators] table")
        return cls.from_table(Table(robot.actuators, "robot.actuators"), robot.n_segments).for_robot(robot)

    @classmethod
    def from_table(cls, t: Table, n_segments: int) -> Actuators:
        """Read ``[robot.actuators]``: shared servo keys, ``[servo.<name>]`` overrides and ``[z]``."""
        if n_segments < 1:
            raise t.error("", "needs at least one segment")
        base: dict[str, Any] = {}
        if t.has("spool_radius"):
            base["spool_radius"] = t.float("spool_radius", ge=MIN_SPOOL, limit=MAX_LENGTH)
        base["zero_offset"] = t.float("zero_offset", 0.0, limit=MAX_LENGTH)
        base["sign"] = _sign(t, "sign", 1)
        base["position_limits"] = _limits(t, "position_limits") if t.has("position_limits") else None
        for key in ("velocity_limit", "acceleration_limit"):
            base[key] = t.float(key, gt=0.0, limit=MAX_RATE) if t.has(key) else None
        bus_base = {k: v for k, v in read_bus_keys(t, {}, stage=False).items() if k != "id"}
        if t.has("id"):
            raise t.error("id", "set per servo ([robot.actuators.servo.<name>] id = ...), not once for all")
        names = [f"s{k + 1}c{i + 1}" for k in range(n_segments) for i in range(3)]
        over = t.table("servo")
        for key in over.keys():
            if key not in names:
                raise over.error(key, f"unknown actuator (known: {', '.join(names)})")
        rows = []
        for name in names:
            st = over.table(name)
            rows.append(_read_actuator(st, base, spool=True, bus_base=bus_base))
            st.finish()
        over.finish()
        if not t.has("z"):
            raise t.error("z", "missing: add [robot.actuators.z] (the base stage; position_limits = [0, 0] if fixed)")
        zt = t.table("z")
        zrow = _read_actuator(zt, {}, spool=False, bus_base=bus_base)
        zt.finish()
        t.finish()
        rows.append(zrow)
        names_all = (*names, "z")
        where = [f"{t.path}.servo.{n}" for n in names] + [f"{t.path}.z"]
        bus = ServoBus.from_rows(names_all, [r["bus"] for r in rows], where)
        return cls(
            n_segments=n_segments,
            spool_radius=np.array([r["spool_radius"] for r in rows[:-1]]),
            sign=np.array([r["sign"] for r in rows]),
            zero_offset=np.array([r["zero_offset"] for r in rows]),
            lower=np.array([r["position_limits"][0] for r in rows]),
            upper=np.array([r["position_limits"][1] for r in rows]),
            vmax=np.array([r["velocity_limit"] for r in rows]),
            amax=np.array([r["acceleration_limit"] for r in rows]),
            bus=bus,
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the ``[robot.actuators]`` schema, every servo written out explicitly."""

        def row(i: int) -> dict[str, Any]:
            d: dict[str, Any] = {}
            if i < self.n - 1:
                d["spool_radius"] = float(self.spool_radius[i])
            d["zero_offset"] = float(self.zero_offset[i])
            d["sign"] = int(self.sign[i])
            d["position_limits"] = [float(self.lower[i]), float(self.upper[i])]
            d["velocity_limit"] = float(self.vmax[i])
            d["acceleration_limit"] = float(self.amax[i])
            if self.bus is not None:
                d.update(self.bus.rows()[i])
            return d

        return {"servo": {name: row(i) for i, name in enumerate(self.names[:-1])}, "z": row(self.n - 1)}

    def describe(self) -> list[str]:
        """One line per actuator: name, limits with units (for CLI output and logs)."""
        out = []
        for i, name in enumerate(self.names):
            u = self.units[i]
            out.append(
                f"{name}: [{self.lower[i]:g}, {self.upper[i]:g}] {u}, |v| <= {self.vmax[i]:g} {u}/s, "
                f"|a| <= {self.amax[i]:g} {u}/s^2"
            )
        return out
