"""Actuator limits as part of the robot description: what each actuator may do, in its own units.

Each cable is wound on the spool of one servo. With spool radius ``r_s`` (mm), zero offset ``a0``
(rad, the servo angle at which the cable has its straight-pose length ``L_k``) and winding sign
``s`` (+1 when a positive angle pays cable out) the servo angle is ``a0 + s (q - L_k) / r_s`` (rad);
the base stage is commanded in mm: ``z0 + s z``. Limits are in the actuator's own units: rad, rad/s,
rad/s^2 for servos; mm, mm/s, mm/s^2 for the stage.

Actuator names: ``s<k>c<i>`` for cable i of segment k (both 1-based), then ``z``. The TOML schema is
the ``[robot.actuators]`` table of problems/robots/cdsr2.toml. This module reads its limit and
scale keys (`read_actuator_table`); the hardware layer adds the bus keys through an `ExtraKeys`
reader (`crtraj.hardware.actuators`) and with it checks the whole table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.model.rate_limits import RateLimits

# Smallest spool radius (mm): below it one radian of servo is less than a micrometre of cable.
MIN_SPOOL = 1e-3
# Largest speed or acceleration limit (rad/s, mm/s, rad/s^2, mm/s^2).
MAX_RATE = 1e6


class ExtraKeys(Protocol):
    """Reads the keys of ``[robot.actuators]`` that are not limits (the hardware's bus keys)."""

    def shared(self, t: Table) -> dict[str, Any]:
        """The keys set once for all servos in the actuators table `t`."""
        ...

    def row(self, t: Table, shared: dict[str, Any], stage: bool) -> dict[str, Any]:
        """The keys of one actuator's table `t` (stage: the z stage), falling back to `shared`."""
        ...


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


def _read_row(t: Table, base: dict[str, Any], spool: bool) -> dict[str, Any]:
    """One actuator's limit and scale keys from `t`, falling back to `base` (the shared servo defaults)."""
    d: dict[str, Any] = {}
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


def _shared_keys(t: Table) -> dict[str, Any]:
    """The servo keys set once for all servos in the actuators table."""
    base: dict[str, Any] = {}
    if t.has("spool_radius"):
        base["spool_radius"] = t.float("spool_radius", ge=MIN_SPOOL, limit=MAX_LENGTH)
    base["zero_offset"] = t.float("zero_offset", 0.0, limit=MAX_LENGTH)
    base["sign"] = _sign(t, "sign", 1)
    base["position_limits"] = _limits(t, "position_limits") if t.has("position_limits") else None
    for key in ("velocity_limit", "acceleration_limit"):
        base[key] = t.float(key, gt=0.0, limit=MAX_RATE) if t.has(key) else None
    return base


def read_actuator_table(
    t: Table, n_segments: int, extra: ExtraKeys | None = None
) -> tuple[ActuatorLimits, list[dict[str, Any]], list[str]]:
    """Read ``[robot.actuators]``: shared servo keys, ``[servo.<name>]`` overrides and ``[z]``.

    Returns the limits, the rows `extra` read (one per actuator; empty dicts without it) and each
    row's table path. With `extra` every key is accounted for, so an unknown key is a one-line
    `InputError`; without it the other keys are left to the reader that knows them.
    """
    if n_segments < 1:
        raise t.error("", "needs at least one segment")
    base = _shared_keys(t)
    extra_base = {} if extra is None else extra.shared(t)
    names = [f"s{k + 1}c{i + 1}" for k in range(n_segments) for i in range(3)]
    over = t.table("servo")
    for key in over.keys():
        if key not in names:
            raise over.error(key, f"unknown actuator (known: {', '.join(names)})")
    rows, extras = [], []
    for name in names:
        st = over.table(name)
        rows.append(_read_row(st, base, spool=True))
        extras.append({} if extra is None else extra.row(st, extra_base, False))
        if extra is not None:
            st.finish()
    if not t.has("z"):
        raise t.error("z", "missing: add [robot.actuators.z] (the base stage; position_limits = [0, 0] if fixed)")
    zt = t.table("z")
    rows.append(_read_row(zt, {}, spool=False))
    extras.append({} if extra is None else extra.row(zt, extra_base, True))
    if extra is not None:
        zt.finish()
        over.finish()
        t.finish()
    where = [f"{t.path}.servo.{n}" for n in names] + [f"{t.path}.z"]
    limits = ActuatorLimits(
        n_segments=n_segments,
        spool_radius=np.array([r["spool_radius"] for r in rows[:-1]]),
        sign=np.array([r["sign"] for r in rows]),
        zero_offset=np.array([r["zero_offset"] for r in rows]),
        lower=np.array([r["position_limits"][0] for r in rows]),
        upper=np.array([r["position_limits"][1] for r in rows]),
        vmax=np.array([r["velocity_limit"] for r in rows]),
        amax=np.array([r["acceleration_limit"] for r in rows]),
    )
    return limits, extras, where


@dataclass(frozen=True)
class ActuatorLimits:
    """Per-actuator scale and limits over the nq = 3n+1 actuators (cable servos, then the z stage).

    spool_radius: (3n,) mm. sign: (nq,) +-1. zero_offset: (nq,) rad for servos, mm for the stage.
    lower/upper: position limits; vmax, amax: speed and acceleration limits (the actuator's units).
    """

    n_segments: int
    spool_radius: np.ndarray
    sign: np.ndarray
    zero_offset: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    vmax: np.ndarray
    amax: np.ndarray

    def __post_init__(self) -> None:
        for name in ("spool_radius", "sign", "zero_offset", "lower", "upper", "vmax", "amax"):
            a = np.asarray(getattr(self, name), dtype=float).copy()
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    @classmethod
    def from_robot(cls, robot: Any) -> ActuatorLimits:
        """The limits of `robot`'s raw ``[robot.actuators]`` table (one-line `InputError` naming a bad field)."""
        if robot.actuators is None:
            raise InputError("robot.actuators: missing; add a [robot.actuators] table")
        return read_actuator_table(Table(robot.actuators, "robot.actuators"), robot.n_segments)[0]

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

    @property
    def scale(self) -> np.ndarray:
        """d value / d q: sign / spool radius (rad/mm) for servos, sign for the stage."""
        return np.concatenate([self.sign[:-1] / self.spool_radius, self.sign[-1:]])

    def rate_limits(self, robot: Any) -> RateLimits:
        """The speed and acceleration limits as linear limits on configuration motion of `robot`.

        value = offset + scale (q - rest), q = q0 + A x: d value / d x = diag(scale) A.
        """
        A, _ = robot.cable_matrix()
        return RateLimits(self.scale[:, None] * np.asarray(A, dtype=float), self.vmax, self.amax, self.names)

    def command(self, q: np.ndarray, rest: np.ndarray) -> np.ndarray:
        """Actuator values (rad for servos, mm for the stage) of actuation q (..., nq) in mm, given the
        straight-pose actuation `rest` (mm)."""
        return self.zero_offset + (q - rest) * self.scale
