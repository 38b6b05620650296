"""One spherical obstacle that moves and breathes over time, as plain data (units mm, rad, s).

Every obstacle is plain data, never code to evaluate:

    radius(t) = A + B sin(omega t + phase)              (B = 0: constant radius)
    centre(t) = c0 + s(t) (to - c0)                     (no `to`: fixed centre)

with the motion progress s(t) chosen by ``profile`` and ``duration`` D (the
time at which the centre first reaches ``to``):

    "linear": s = clip(t / D, 0, 1)                    one way, then rests at `to`
    "cos":    s = (1 - cos(pi t / D)) / 2              ping-pong c0 -> to -> c0, period 2 D
    "sin":    s = sin(pi t / (2 D))                    oscillates about c0 between to and 2 c0 - to, period 4 D

So the paper's ``60 + 10 sin(a t)`` is A=60, B=10, omega=a, phase=0 and
``45 + 15 cos(b t)`` is A=45, B=15, omega=b, phase=pi/2. Every centre moves
on the straight line through c0 and `to`, which makes the swept volume over
a time interval an exact capsule (see `crtraj.world.scene.Scene.swept`).
`sin_range` gives the exact range of the sine over an interval, from which
the exact radius and progress ranges follow. `crtraj.world.scene.Scene`
evaluates many obstacles at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_TIME, Table

PROFILES = ("linear", "sin", "cos")
# Integer code of each motion profile (vectorised evaluation in `Scene`).
PROFILE_CODE = MappingProxyType({"linear": 0, "sin": 1, "cos": 2})
# Largest radius frequency (rad/s): a sphere breathing faster than ~160 Hz is
# not a physical obstacle, and larger values only lose precision in sin().
MAX_OMEGA = 1.0e3
# Coordinates of obstacles and workspace are at most this far from the base (mm):
# padding slots (`crtraj.world.packing`) sit far beyond and must stay outside every real scene.
MAX_COORDINATE = 1.0e5
# Shortest motion duration or period (s): a sphere crossing the workspace in
# less than a millisecond is not physical.
MIN_DURATION = 1.0e-3


@dataclass(frozen=True)
class Obstacle:
    """One sphere: radius ``A + B sin(omega t + phase)``, centre moving from `center` toward `to`.

    center: c0 (mm), the centre at t = 0. radius: mean radius A (mm).
    amplitude: B (mm), with |B| <= A so the radius never goes negative.
    omega: rad/s. phase: rad. to: end point of the motion (mm) or None for a
    fixed centre. duration: time (s) to first reach `to`. profile: "linear",
    "sin" or "cos" (module docstring). name: a label for views and messages.
    """

    center: tuple[float, float, float]
    radius: float
    amplitude: float = 0.0
    omega: float = 0.0
    phase: float = 0.0
    to: tuple[float, float, float] | None = None
    duration: float = 1.0
    profile: str = "linear"
    name: str = ""

    def __post_init__(self) -> None:
        where = f"obstacle {self.name!r}" if self.name else "obstacle"
        c = tuple(float(v) for v in self.center)
        if len(c) != 3 or not all(math.isfinite(v) for v in c):
            raise InputError(f"{where}.center: expected 3 finite numbers, got {self.center!r}")
        object.__setattr__(self, "center", c)
        if self.to is not None:
            to = tuple(float(v) for v in self.to)
            if len(to) != 3 or not all(math.isfinite(v) for v in to):
                raise InputError(f"{where}.motion.to: expected 3 finite numbers, got {self.to!r}")
            object.__setattr__(self, "to", to)
        for key in ("radius", "amplitude", "omega", "phase", "duration"):
            if not math.isfinite(getattr(self, key)):
                raise InputError(f"{where}.{key}: must be finite, got {getattr(self, key)}")
        if self.radius < 0:
            raise InputError(f"{where}.radius: mean radius must be >= 0 mm, got {self.radius:g}")
        if abs(self.amplitude) > self.radius:
            raise InputError(
                f"{where}.radius.amplitude: |amplitude| must be <= mean radius {self.radius:g} mm "
                f"(the radius would go negative), got {self.amplitude:g}"
            )
        if not self.duration > 0:
            raise InputError(f"{where}.motion.duration: must be > 0 s, got {self.duration:g}")
        if self.profile not in PROFILES:
            raise InputError(f"{where}.motion.profile: must be one of {', '.join(PROFILES)}; got {self.profile!r}")

    # ----------------------------------------------------------- evaluation
    @property
    def displacement(self) -> np.ndarray:
        """to - c0 (mm); zero for a fixed centre."""
        if self.to is None:
            return np.zeros(3)
        return np.asarray(self.to) - np.asarray(self.center)

    @property
    def max_radius(self) -> float:
        """Largest radius over all time (mm)."""
        return self.radius + abs(self.amplitude)

    @property
    def center_speed_max(self) -> float:
        """max_t |dc/dt| (mm/s): |d|/D (linear) or |d| pi / (2 D) (sin, cos)."""
        dist = float(np.linalg.norm(self.displacement))
        if self.profile == "linear":
            return dist / self.duration
        return dist * math.pi / (2.0 * self.duration)

    @property
    def radius_rate_max(self) -> float:
        """max_t |dR/dt| = |B omega| (mm/s)."""
        return abs(self.amplitude * self.omega)

    # --------------------------------------------------------------- file I/O
    @classmethod
    def from_table(cls, t: Table) -> Obstacle:
        """Read one ``[[scene.obstacle]]`` table (schema in `Scene.from_table`)."""
        name = t.str("name", "", max_len=100)
        center = t.vec("center", 3, limit=MAX_COORDINATE)
        rv = t.raw("radius")
        if isinstance(rv, dict):
            rt = Table(rv, f"{t.path}.radius")
            mean = rt.float("mean", ge=0.0, limit=MAX_COORDINATE)
            amp = rt.float("amplitude", 0.0, limit=MAX_COORDINATE)
            omega = rt.float("omega", 0.0, limit=MAX_OMEGA)
            phase = rt.float("phase", 0.0, limit=1e3)
            rt.finish()
            if abs(amp) > mean:
                raise rt.error("amplitude", f"|amplitude| must be <= mean {mean:g} mm, got {amp:g}")
        else:
            mean = t.float("radius", ge=0.0, limit=MAX_COORDINATE)
            amp, omega, phase = 0.0, 0.0, 0.0
        to: tuple[float, ...] | None = None
        duration, profile = 1.0, "linear"
        if t.has("motion"):
            mt = t.table("motion")
            to = mt.vec("to", 3, limit=MAX_COORDINATE)
            profile = mt.str("profile", "linear", choices=PROFILES)
            has_d, has_p = mt.has("duration"), mt.has("period")
            if has_d and has_p:
                raise mt.error("period", "give either duration or period, not both")
            if has_p:
                if profile == "linear":
                    raise mt.error("period", "a linear motion has no period; give duration (s)")
                period = mt.float("period", ge=MIN_DURATION, limit=MAX_TIME)
                # time to first reach `to`: half a period for cos, a quarter for sin
                duration = period / 2.0 if profile == "cos" else period / 4.0
            else:
                duration = mt.float("duration", ge=MIN_DURATION, limit=MAX_TIME)
            mt.finish()
        t.finish()
        return cls(
            center=(center[0], center[1], center[2]),
            radius=mean,
            amplitude=amp,
            omega=omega,
            phase=phase,
            to=None if to is None else (to[0], to[1], to[2]),
            duration=duration,
            profile=profile,
            name=name,
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the TOML schema (round-trips through `from_table`)."""
        d: dict[str, Any] = {}
        if self.name:
            d["name"] = self.name
        d["center"] = list(self.center)
        if self.amplitude == 0.0 and self.omega == 0.0 and self.phase == 0.0:
            d["radius"] = self.radius
        else:
            d["radius"] = {"mean": self.radius, "amplitude": self.amplitude, "omega": self.omega, "phase": self.phase}
        if self.to is not None:
            d["motion"] = {"to": list(self.to), "duration": self.duration, "profile": self.profile}
        return d


def sin_range(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact (min, max) of sin over [min(a,b), max(a,b)], elementwise."""
    lo_t, hi_t = np.minimum(a, b), np.maximum(a, b)
    sa, sb = np.sin(lo_t), np.sin(hi_t)
    lo, hi = np.minimum(sa, sb), np.maximum(sa, sb)
    two_pi = 2.0 * np.pi
    # first crest (pi/2 + 2k pi) and trough (-pi/2 + 2k pi) at or after lo_t
    crest = np.pi / 2 + two_pi * np.ceil((lo_t - np.pi / 2) / two_pi)
    trough = -np.pi / 2 + two_pi * np.ceil((lo_t + np.pi / 2) / two_pi)
    hi = np.where(crest <= hi_t, 1.0, hi)
    lo = np.where(trough <= hi_t, -1.0, lo)
    return lo, hi
