"""Robot parameters, limits and the linear cable <-> bending-vector maps.

Configuration ``x = (u_1, ..., u_n, z)``: per segment the commanded bending
vector ``u_k = theta_k (cos phi_k, sin phi_k)`` (rad) and the base translation
``z`` (mm). Actuation ``q = (q_1,1, q_1,2, q_1,3, ..., q_n,3, z)``: absolute
cable lengths (mm) and z (mm), the paper's eq. 12 for n = 2.

Everything from cables to the *effective* (coupled) bending vectors is linear:
    q = q0 + A x                      (paper eq. 4, cable i at angle a_i)
    x = A^+ (q - q0)                  (paper eq. 2-3, exact for consistent q)
    u_bar = C u                       (paper eq. 8-11 as u_bar_{k-1} = u_{k-1} + c u_bar_k)
so the maps are constant matrices, shared by the numpy and CasADi code.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table, check_name
from crtraj.model.actuator_limits import ActuatorLimits
from crtraj.model.rate_limits import RateLimits

CABLE_SPACING = 2.0 * math.pi / 3.0  # rad, paper's xi: three cables 120 degrees apart
# Size bounds, checked before any model is built: every solver's size grows
# with them (the paper's robot: 2 segments, 10 collision points).
MAX_SEGMENTS = 16
MAX_COLLISION_POINTS = 200
# Smallest length a robot dimension may have (mm): 1 um, far below any real
# cable radius or segment, far above values that make the maps ill-conditioned.
MIN_DIMENSION = 1e-3
# Largest |coupling gain|: the paper's is -1; powers of c up to MAX_SEGMENTS stay finite.
MAX_COUPLING = 10.0


@dataclass(frozen=True)
class Segment:
    """One constant-curvature segment.

    length: backbone length L_k (mm). theta_max: largest bending angle of the
    effective (coupled) bending (rad). cable_phase: angle of cable 1 around
    the backbone (rad). cable_stroke: largest |q - L| of any cable (mm); None
    means ``2 * cable_radius * theta_max`` (enough for full coupling).
    """

    length: float
    theta_max: float = math.pi
    cable_phase: float = 0.0
    cable_stroke: float | None = None


@dataclass(frozen=True)
class Robot:
    """A cable-driven continuum robot: segments, cable radius, base stroke, coupling.

    cable_radius: backbone axis to cable hole (mm). z_range: base translation
    stroke (mm). coupling: gain c in ``u_bar[k-1] = u[k-1] + c u_bar[k]``
    (c = 0 is plain PCC, c = -1 the paper's eq. 10-11). body_radius: radius of
    the robot's discs (mm), added to the backbone for collision checks.
    collision_points: backbone points the solvers keep clear (paper: 10).
    actuators: the raw ``[robot.actuators]`` table (an immutable mapping) or
    None. `actuator_limits` reads its scale and limits (`crtraj.model.actuator_limits`);
    `crtraj.hardware.actuators.Actuators.from_robot` adds the bus keys, and `crtraj.io.problem`
    validates the whole table when a robot file is loaded.
    """

    name: str
    cable_radius: float
    segments: tuple[Segment, ...]
    z_range: tuple[float, float] = (0.0, 0.0)
    coupling: float = 0.0
    body_radius: float = 3.0
    collision_points: int = 10
    description: str = ""
    actuators: Mapping[str, Any] | None = field(default=None, compare=False)
    # the raw [robot.mechanics] table (immutable) or None; `crtraj.model.mechanics.Mechanics.from_robot`
    # parses it. Left out of `to_dict`: results describe the kinematic robot they were planned with.
    mechanics: Mapping[str, Any] | None = field(default=None, compare=False)
    # the raw [robot.homing] and [robot.stop] tables (read by `crtraj.hardware.dynamixel._homing_spec`), or None
    homing: Mapping[str, Any] | None = field(default=None, compare=False)
    stop: Mapping[str, Any] | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not self.segments:
            raise InputError("robot.segment: at least one [[robot.segment]] is required")
        if not (self.cable_radius > 0 and math.isfinite(self.cable_radius)):
            raise InputError(f"robot.cable_radius: must be > 0, got {self.cable_radius}")
        lo, hi = self.z_range
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
            raise InputError(f"robot.z_range: must be [low, high] with low <= high, got {list(self.z_range)}")
        if not math.isfinite(self.coupling):
            raise InputError(f"robot.coupling: must be finite, got {self.coupling}")
        if self.body_radius < 0:
            raise InputError(f"robot.body_radius: must be >= 0, got {self.body_radius}")
        if not 2 <= self.collision_points <= MAX_COLLISION_POINTS:
            raise InputError(
                f"robot.collision_points: must be in [2, {MAX_COLLISION_POINTS}], got {self.collision_points}"
            )
        if len(self.segments) > MAX_SEGMENTS:
            raise InputError(f"robot.segment: at most {MAX_SEGMENTS} segments, got {len(self.segments)}")
        for k, s in enumerate(self.segments):
            where = f"robot.segment[{k}]"
            if not (s.length > 0 and math.isfinite(s.length)):
                raise InputError(f"{where}.length: must be > 0, got {s.length}")
            if not (0 < s.theta_max <= 2 * math.pi):
                raise InputError(f"{where}.theta_max: must be in (0, 2 pi], got {s.theta_max}")
            if s.cable_stroke is not None and not s.cable_stroke > 0:
                raise InputError(f"{where}.cable_stroke: must be > 0, got {s.cable_stroke}")
        if self.actuators is not None:
            if not isinstance(self.actuators, Mapping):
                raise InputError(f"robot.actuators: expected a table, got {type(self.actuators).__name__}")
            object.__setattr__(self, "actuators", _frozen(self.actuators))
        for name in ("mechanics", "homing", "stop"):
            v = getattr(self, name)
            if v is not None:
                if not isinstance(v, Mapping):
                    raise InputError(f"robot.{name}: expected a table, got {type(v).__name__}")
                object.__setattr__(self, name, _frozen(v))

    def actuator_limits(self) -> ActuatorLimits | None:
        """The actuators' scale and speed/acceleration/position limits, or None without ``[robot.actuators]``."""
        return None if self.actuators is None else ActuatorLimits.from_robot(self)

    def rate_limits(self) -> RateLimits | None:
        """The actuators' full speed and acceleration limits on configuration motion (None: no actuators)."""
        limits = self.actuator_limits()
        return None if limits is None else limits.rate_limits(self)

    # ------------------------------------------------------------------ sizes
    @property
    def n_segments(self) -> int:
        return len(self.segments)

    @property
    def nx(self) -> int:
        """Configuration size: 2 per segment + z."""
        return 2 * self.n_segments + 1

    @property
    def nq(self) -> int:
        """Actuation size: 3 cables per segment + z."""
        return 3 * self.n_segments + 1

    @property
    def total_length(self) -> float:
        """Backbone length (mm)."""
        return float(sum(s.length for s in self.segments))

    def cable_stroke(self, k: int) -> float:
        """Largest |q - L_k| of segment k's cables (mm)."""
        s = self.segments[k]
        if s.cable_stroke is not None:
            return s.cable_stroke
        return 2.0 * self.cable_radius * s.theta_max

    def cable_angles(self, k: int) -> np.ndarray:
        """Angles (rad) of segment k's three cables around the backbone."""
        return self.segments[k].cable_phase + CABLE_SPACING * np.arange(3)

    # ------------------------------------------------------------- linear maps
    def cable_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """(A, q0) with ``q = q0 + A @ x`` (mm); paper eq. 4 in bending-vector form."""
        A, q0 = self._cable_maps
        return A.copy(), q0.copy()

    @functools.cached_property
    def _cable_maps(self) -> tuple[np.ndarray, np.ndarray]:
        # computed once per robot: the planners' limit checks call for it thousands of times per query
        n, r = self.n_segments, self.cable_radius
        A = np.zeros((self.nq, self.nx))
        q0 = np.zeros(self.nq)
        for k, seg in enumerate(self.segments):
            a = self.cable_angles(k)
            # r theta cos(phi + a) = r (u_x cos a - u_y sin a)
            A[3 * k : 3 * k + 3, 2 * k] = -r * np.cos(a)
            A[3 * k : 3 * k + 3, 2 * k + 1] = r * np.sin(a)
            q0[3 * k : 3 * k + 3] = seg.length
        A[3 * n, 2 * n] = 1.0
        return A, q0

    def cable_inverse(self) -> np.ndarray:
        """B with ``x = B @ (q - q0)``; the least-squares inverse of A (paper eq. 2-3)."""
        A, _ = self.cable_matrix()
        return np.linalg.pinv(A)

    def coupling_matrix(self) -> np.ndarray:
        """C (2n x 2n) with ``u_bar = C @ u``: u_bar_k = sum_{j>=k} c^(j-k) u_j."""
        return self._coupling.copy()

    @functools.cached_property
    def _coupling(self) -> np.ndarray:
        n, c = self.n_segments, self.coupling
        C = np.zeros((2 * n, 2 * n))
        for k in range(n):
            for j in range(k, n):
                C[2 * k : 2 * k + 2, 2 * j : 2 * j + 2] = (c ** (j - k)) * np.eye(2)
        return C

    # ---------------------------------------------------------- numpy helpers
    def cables(self, x: np.ndarray) -> np.ndarray:
        """Actuation q (mm) for configurations x (..., nx)."""
        A, q0 = self.cable_matrix()
        return np.asarray(x, dtype=float) @ A.T + q0

    def config(self, q: np.ndarray) -> np.ndarray:
        """Configurations x (..., nx) from actuation q (..., nq) (mm)."""
        _, q0 = self.cable_matrix()
        return (np.asarray(q, dtype=float) - q0) @ self.cable_inverse().T

    def bending(self, x: np.ndarray) -> np.ndarray:
        """Effective (coupled) bending vectors (..., n, 2) in rad."""
        x = np.asarray(x, dtype=float)
        ub = x[..., : 2 * self.n_segments] @ self.coupling_matrix().T
        return ub.reshape(*x.shape[:-1], self.n_segments, 2)

    def straight(self, z: float | None = None) -> np.ndarray:
        """The straight configuration at base translation z (mm; default: 0 clipped to the stroke)."""
        x = np.zeros(self.nx)
        lo, hi = self.z_range
        x[-1] = min(max(0.0 if z is None else z, lo), hi)
        return x

    def config_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Loose box bounds on x implied by the limits (for samplers and solvers)."""
        lo = np.empty(self.nx)
        hi = np.empty(self.nx)
        for k in range(self.n_segments):
            umax = self.cable_stroke(k) / self.cable_radius
            lo[2 * k : 2 * k + 2] = -umax
            hi[2 * k : 2 * k + 2] = umax
        lo[-1], hi[-1] = self.z_range
        return lo, hi

    def limit_violation(self, x: np.ndarray) -> np.ndarray:
        """Largest limit violation per configuration (<= 0 means within limits).

        Units are mixed on purpose (rad for bending, mm for cables and z); only
        the sign matters.
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        ub = self.bending(x)
        theta = np.linalg.norm(ub, axis=-1)
        tmax = np.array([s.theta_max for s in self.segments])
        v_theta = np.max(theta - tmax, axis=-1)
        A, _q0 = self.cable_matrix()
        dq = (x @ A.T)[:, : 3 * self.n_segments]
        strokes = np.repeat([self.cable_stroke(k) for k in range(self.n_segments)], 3)
        v_cable = np.max(np.abs(dq) - strokes, axis=-1)
        lo, hi = self.z_range
        v_z = np.maximum(lo - x[:, -1], x[:, -1] - hi)
        return np.maximum(np.maximum(v_theta, v_cable), v_z)

    # ------------------------------------------------------------- file I/O
    @classmethod
    def from_table(cls, t: Table) -> Robot:
        """Read a ``[robot]`` table (see problems/robots/cdsr2.toml for the schema)."""
        segs = []
        seg_tables = t.tables("segment", most=MAX_SEGMENTS)
        if not seg_tables:
            raise t.error("segment", "missing: at least one [[robot.segment]] is required")
        for st in seg_tables:
            segs.append(
                Segment(
                    length=st.float("length", ge=MIN_DIMENSION, limit=MAX_LENGTH),
                    theta_max=st.float("theta_max", math.pi, gt=0.0, le=2 * math.pi),
                    cable_phase=st.float("cable_phase", 0.0, limit=1e3),
                    cable_stroke=st.float("cable_stroke", None, ge=MIN_DIMENSION, limit=MAX_LENGTH),
                )
            )
            st.finish()
        z = t.vec("z_range", 2, (0.0, 0.0), limit=MAX_LENGTH)
        if z[0] > z[1]:
            raise t.error("z_range", f"must be [low, high] with low <= high, got {list(z)}")
        # kept raw: read by `actuator_limits` (limits) and the hardware layer (bus keys)
        actuators = t.raw("actuators", None)
        robot = cls(
            name=check_name(t.str("name"), t.path + ".name" if t.path else "name"),
            cable_radius=t.float("cable_radius", ge=MIN_DIMENSION, limit=MAX_LENGTH),
            segments=tuple(segs),
            z_range=(z[0], z[1]),
            coupling=t.float("coupling", 0.0, limit=MAX_COUPLING),
            body_radius=t.float("body_radius", 3.0, ge=0.0, limit=MAX_LENGTH),
            collision_points=t.int("collision_points", 10, ge=2, le=MAX_COLLISION_POINTS),
            description=t.str("description", "", max_len=10_000),
            actuators=actuators,
            mechanics=t.raw("mechanics", None),  # kept raw: crtraj.model.mechanics owns the schema
            homing=t.raw("homing", None),
            stop=t.raw("stop", None),
        )
        t.finish()
        return robot

    def to_dict(self) -> dict[str, Any]:
        """Plain data, the same schema as the TOML ``[robot]`` table."""
        d: dict[str, Any] = {
            "name": self.name,
            "cable_radius": self.cable_radius,
            "z_range": list(self.z_range),
            "coupling": self.coupling,
            "body_radius": self.body_radius,
            "collision_points": self.collision_points,
            "segment": [
                {"length": s.length, "theta_max": s.theta_max, "cable_phase": s.cable_phase}
                | ({} if s.cable_stroke is None else {"cable_stroke": s.cable_stroke})
                for s in self.segments
            ],
        }
        if self.description:
            d["description"] = self.description
        if self.actuators is not None:
            d["actuators"] = plain(self.actuators)
        for name in ("homing", "stop"):
            if getattr(self, name) is not None:
                d[name] = plain(getattr(self, name))
        return d


def _frozen(v: Any) -> Any:
    """A read-only deep copy of TOML data: tables become mappingproxies, arrays tuples."""
    if isinstance(v, Mapping):
        return MappingProxyType({str(k): _frozen(x) for k, x in v.items()})
    if isinstance(v, (list, tuple)):
        return tuple(_frozen(x) for x in v)
    return v


def plain(v: Any) -> Any:
    """The plain dicts and lists of `_frozen` data (for JSON and TOML writers, and the `Table` reader, which
    takes lists, not tuples)."""
    if isinstance(v, Mapping):
        return {k: plain(x) for k, x in v.items()}
    if isinstance(v, tuple):
        return [plain(x) for x in v]
    return v
