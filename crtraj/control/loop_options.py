"""The ``[loop]`` problem section: options of the closed loop (`crtraj.control.loop.ClosedLoop`).

The horizon NLP's own options stay in ``[replan]`` (`crtraj.control.horizon.ReplanOptions`).
Units: mm, s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, MAX_TIME, Table, check_float

# Most closed-loop steps of one run (duration / replan.dt): each is one NLP solve.
MAX_STEPS = 100_000

# float options: default and bounds (shared by Python construction and TOML reading)
_FLOATS: Mapping[str, tuple[float, dict[str, float]]] = MappingProxyType(
    {
        "duration": (60.0, {"gt": 0.0, "le": MAX_TIME}),
        "replan_period": (0.0, {"ge": 0.0, "le": MAX_TIME}),
        "planner_time": (1.0, {"gt": 0.0, "le": 3600.0}),
        "stall_time": (3.0, {"gt": 0.0, "le": MAX_TIME}),
        "reference_speed": (0.7, {"gt": 0.0, "le": 1.0}),
        "max_body_speed": (50.0, {"gt": 0.0}),
        "check_resolution": (1.0, {"ge": 0.01, "le": MAX_LENGTH}),
        "settle_time": (0.5, {"ge": 0.0, "le": MAX_TIME}),
    }
)
_INTS: Mapping[str, tuple[int, dict[str, int]]] = MappingProxyType(
    {
        "check_points": (21, {"ge": 2, "le": 1000}),
    }
)


@dataclass(frozen=True)
class LoopOptions:
    """The ``[loop]`` problem section (units mm, s).

    duration (s of simulated time at most), replan_period (s between
    periodic reference replans; 0 = only when needed), planner_time (s
    budget of one reference plan), stall_time (s without progress before
    the reference is replanned), reference_speed (fraction of the rate
    limits and of max_body_speed the reference is timed with),
    max_body_speed (mm/s, fastest body point motion the reference asks for,
    measured by `crtraj.planning.validity.MotionValidator.motion_bound`),
    check_resolution (mm of body motion between verification samples),
    check_points (backbone points of the verification), settle_time (s the
    tip must stay within the goal tolerance before the run ends).
    """

    duration: float = _FLOATS["duration"][0]
    replan_period: float = _FLOATS["replan_period"][0]
    planner_time: float = _FLOATS["planner_time"][0]
    stall_time: float = _FLOATS["stall_time"][0]
    reference_speed: float = _FLOATS["reference_speed"][0]
    max_body_speed: float = _FLOATS["max_body_speed"][0]
    check_resolution: float = _FLOATS["check_resolution"][0]
    check_points: int = _INTS["check_points"][0]
    settle_time: float = _FLOATS["settle_time"][0]

    def __post_init__(self) -> None:
        for name, (_, bounds) in _FLOATS.items():
            check_float(getattr(self, name), f"loop.{name}", **bounds)
        for name, (_, ib) in _INTS.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise InputError(f"loop.{name}: expected an integer, got {v!r}")
            if "ge" in ib and v < ib["ge"]:
                raise InputError(f"loop.{name}: must be >= {ib['ge']}, got {v}")
            if "le" in ib and v > ib["le"]:
                raise InputError(f"loop.{name}: must be <= {ib['le']}, got {v}")

    def steps(self, dt: float) -> int:
        """Control steps of a full run with steps of dt s (the replanner's); `InputError` above MAX_STEPS,
        so a huge run is refused before any work."""
        n = math.ceil(self.duration / dt - 1e-9)
        if n > MAX_STEPS:
            raise InputError(
                f"loop.duration: {self.duration:g} s is {n} steps of replan.dt {dt:g} s, more than {MAX_STEPS}; "
                "shorten it or raise dt"
            )
        return n

    @classmethod
    def from_table(cls, t: Table) -> LoopOptions:
        """Read a ``[loop]`` table; unknown keys and bad values raise `InputError`."""
        kw: dict[str, Any] = {name: t.float(name, d, **b) for name, (d, b) in _FLOATS.items()}
        kw.update({name: t.int(name, d, **b) for name, (d, b) in _INTS.items()})
        t.finish()
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the TOML schema."""
        return {f.name: getattr(self, f.name) for f in fields(self)}
