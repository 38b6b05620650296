"""Actuators of a cable-driven robot: cable lengths <-> servo angles, the z stage, and the servo bus.

The robot description owns the actuators' scale and limits (`crtraj.model.actuator_limits`, where
the conversion is written out: ``angle = a0 + s (q - L_k) / r_s`` rad for a servo, ``z0 + s z`` mm
for the stage); this module adds the Dynamixel bus (ids, models, tick scales) and the mapping that
the streamer and the devices use. The TOML schema is the ``[robot.actuators]`` table of
problems/robots/cdsr2.toml.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import Table, check_array
from crtraj.hardware.dynamixel import ServoBus, read_bus_keys
from crtraj.model.actuator_limits import ActuatorLimits, read_actuator_table
from crtraj.model.rate_limits import RateLimits


class _BusKeys:
    """The bus keys of ``[robot.actuators]`` (`crtraj.hardware.dynamixel._servo_bus`), read beside the limits."""

    def shared(self, t: Table) -> dict[str, Any]:
        base = {k: v for k, v in read_bus_keys(t, {}, stage=False).items() if k != "id"}
        if t.has("id"):
            raise t.error("id", "set per servo ([robot.actuators.servo.<name>] id = ...), not once for all")
        return base

    def row(self, t: Table, shared: dict[str, Any], stage: bool) -> dict[str, Any]:
        return read_bus_keys(t, shared, stage=stage)


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
    # n, names, units and scale are the robot description's (`ActuatorLimits`): delegated, not repeated
    @property
    def n(self) -> int:
        """Number of actuators (3 per segment + the z stage)."""
        return self.limits.n

    @property
    def names(self) -> tuple[str, ...]:
        return self.limits.names

    @property
    def units(self) -> tuple[str, ...]:
        """Position unit of each actuator's value."""
        return self.limits.units

    def index(self, name: str) -> int:
        """Position of actuator `name`; `InputError` for an unknown name."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(f"actuator {name!r}: unknown (known: {', '.join(self.names)})") from None

    @property
    def scale(self) -> np.ndarray:
        """d value / d q: sign / spool radius (rad/mm) for servos, sign for the stage."""
        return self.limits.scale

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

    @cached_property
    def limits(self) -> ActuatorLimits:
        """The scale and limits of these actuators, as the robot description holds them (built once)."""
        arrays = (self.spool_radius, self.sign, self.zero_offset, self.lower, self.upper, self.vmax, self.amax)
        return ActuatorLimits(self.n_segments, *arrays)

    def rate_limits(self, robot: Any) -> RateLimits:
        """The speed and acceleration limits as linear limits on configuration motion of `robot`
        (`crtraj.model.actuator_limits.ActuatorLimits.rate_limits`)."""
        return self.limits.rate_limits(robot)

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
        """Read ``[robot.actuators]``: the limits (`crtraj.model.actuator_limits.read_actuator_table`)
        and the bus keys of every actuator; an unknown key is a one-line `InputError`."""
        limits, rows, where = read_actuator_table(t, n_segments, _BusKeys())
        names = limits.names
        bus = ServoBus.from_rows(names, rows, where)
        return cls(
            n_segments=n_segments,
            spool_radius=limits.spool_radius,
            sign=limits.sign,
            zero_offset=limits.zero_offset,
            lower=limits.lower,
            upper=limits.upper,
            vmax=limits.vmax,
            amax=limits.amax,
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
