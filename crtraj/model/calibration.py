"""Calibration of the robot's parameters from motion-capture markers: one CasADi least-squares NLP.

A sample is the actuator values v (rad for servos, mm for the z stage) and the capture-frame positions
m_j (mm) of markers j sitting on the backbone. The model maps v to the markers' robot-frame positions
through the parameters theta (all in one vector, `Layout`):

    d_i   = sign_i spool_i (v_i - a0_i)        cable i's length change (mm), a0_i its zero offset (rad)
    z     = sign_z (v_z - z0)                   base translation (mm), z0 the stage's zero offset
    u_k   = B1_k d_k / r                        commanded bending vector (paper eq. 2-3), r the cable radius
    u_bar = C(c) u                              coupling (paper eq. 8-11), c the coupling gain
    p_j   = PCC forward kinematics with segment lengths L_k, at the marker's backbone point

and the capture frame by p = R(w) m + t (w a rotation vector, rad; t in mm; capture -> robot frame). The
residual of one marker is e_j = R(w) m_j + t - p_j (mm, robot frame). The fit minimises the
pseudo-Huber loss ``sum_j 2 delta^2 (sqrt(1 + |e_j|^2 / delta^2) - 1)``, quadratic for |e| << delta and
linear beyond, so a swapped or lost marker pulls with a bounded force. IPOPT solves it with CasADi's
exact gradient and Hessian, within the parameter bounds.

Identifiability (`identifiable`): the columns of the robust-weighted Jacobian, each scaled to unit norm,
are taken in a fixed priority order (capture frame, lengths, cable radius, coupling, zero offsets, base
z); a parameter whose column lies (to `tol`) in the span of the ones before it cannot be told apart from
them by this data and is held at its prior. Two such directions always exist: a common zero offset of a
segment's three cables does not change its bending (the pseudo-inverse of eq. 2-3 removes it), and the
stage's zero offset moves every marker like the capture frame's translation along the robot's z axis.

Standard errors come from the Gauss-Newton covariance at the solution, ``s^2 (J_w^T J_w)^-1`` with the
robust weights w_j = 1 / sqrt(1 + |e_j|^2 / delta^2) and ``s^2 = sum w_j |e_j|^2 / (m - p)``.

The model has no per-segment stiffness: eq. 8 uses one bending stiffness K_B for both segments (one
NiTi backbone), so no stiffness ratio is fitted. Units: mm, rad.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import ClassVar

import casadi as ca
import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.options import Options, option
from crtraj.model.kinematics import _arc, _f1_f2, _skew
from crtraj.model.robot import CABLE_SPACING, Robot

# The parameter groups a user may fit (`--fit`), in file order.
GROUPS = ("lengths", "coupling", "cable_radius", "zero_offsets", "base_z", "capture_frame")
# Identifiability priority: earlier groups keep a shared direction, later ones are held at their prior.
PRIORITY = ("capture_frame", "lengths", "cable_radius", "coupling", "zero_offsets", "base_z")
# Most samples and markers of one dataset (the NLP grows linearly with them).
MAX_SAMPLES = 200_000
MAX_MARKERS = 16
# Fewest usable fit samples, whatever is fitted.
MIN_SAMPLES = 20
# Spread of the markers relative to the model's (capture vs robot): outside this the file is in
# another unit (metres give 0.001, centimetres 0.1, inches 0.04).
PLAUSIBLE_SCALE = (0.8, 1.25)


@dataclass(frozen=True)
class MarkerSite:
    """Where a marker sits: segment (0-based), arc length from the segment's start (mm; None = its tip)."""

    name: str
    segment: int
    arc: float | None = None

    def to_dict(self) -> dict[str, object]:
        return {"segment": self.segment + 1, "arc": "tip" if self.arc is None else self.arc}


def check_sites(sites: Sequence[MarkerSite], robot: Robot) -> None:
    """Refuse a marker on a segment the robot lacks or beyond its segment's length (one line)."""
    if not 1 <= len(sites) <= MAX_MARKERS:
        raise InputError(f"markers: 1 to {MAX_MARKERS} markers, got {len(sites)}")
    for s in sites:
        if not 0 <= s.segment < robot.n_segments:
            raise InputError(f"marker {s.name}: segment {s.segment + 1}, the robot has {robot.n_segments}")
        L = robot.segments[s.segment].length
        if s.arc is not None and not 0 <= s.arc <= L:
            raise InputError(f"marker {s.name}: arc {s.arc:g} mm is beyond segment {s.segment + 1} ({L:g} mm long)")


def paper_markers(n_segments: int) -> tuple[MarkerSite, ...]:
    """The paper's markers: the base, the tip of the proximal segment, the distal tip."""
    sites = [MarkerSite("base", 0, 0.0)]
    sites += [MarkerSite(f"tip{k + 1}" if k < n_segments - 1 else "tip", k) for k in range(n_segments)]
    return tuple(sites)


@dataclass(frozen=True)
class CalibrateOptions(Options):
    """The ``[calibrate]`` section. loss_scale: pseudo-Huber delta (mm): residuals beyond it pull with a
    bounded force. holdout: fraction of samples kept out of the fit to test it. seed: the split's seed.
    max_iter: IPOPT iterations. tol: IPOPT's tolerance. identifiability_tol: smallest relative part of a
    parameter's (unit) Jacobian column outside the span of the columns before it. length_bound,
    radius_bound: largest relative change of a segment length and of the cable radius.
    hessian: "gauss-newton" (robust-weighted J^T J of the exact residual Jacobians) or "exact". coupling_bound:
    largest |c - prior|. offset_bound: largest |zero offset - prior| (rad). base_z_bound: mm."""

    SECTION: ClassVar[str] = "calibrate"

    loss_scale: float = option(1.0, gt=0.0, le=1000.0)
    holdout: float = option(0.2, ge=0.0, le=0.9)
    seed: int = option(0, ge=0, le=2**31 - 1)
    max_iter: int = option(200, ge=1, le=10_000)
    tol: float = option(1e-10, gt=0.0, le=1.0)
    identifiability_tol: float = option(1e-6, gt=0.0, lt=1.0)
    length_bound: float = option(0.3, gt=0.0, lt=1.0)
    radius_bound: float = option(0.5, gt=0.0, lt=1.0)
    coupling_bound: float = option(1.0, gt=0.0, le=10.0)
    offset_bound: float = option(0.5, gt=0.0, le=math.pi)
    base_z_bound: float = option(100.0, gt=0.0, le=1e4)
    hessian: str = option("gauss-newton", choices=("gauss-newton", "exact"))


@dataclass(frozen=True)
class Hardware:
    """The known actuator constants (not fitted): spool radii (3n,) mm, signs (nq,) +-1."""

    spool_radius: np.ndarray
    sign: np.ndarray


@dataclass(frozen=True)
class Layout:
    """Names, groups, units, priors and bounds of the parameter vector theta (see the module docstring)."""

    n_segments: int
    actuator_names: tuple[str, ...]
    names: tuple[str, ...]
    groups: tuple[str, ...]
    units: tuple[str, ...]
    prior: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    scale: np.ndarray  # typical size of a parameter's change, for the solver's variable scaling

    @property
    def n(self) -> int:
        return len(self.names)

    def index(self, group: str) -> np.ndarray:
        """Positions of the parameters of `group`."""
        return np.array([i for i, g in enumerate(self.groups) if g == group], dtype=int)

    @classmethod
    def build(
        cls,
        robot: Robot,
        zero_offsets: np.ndarray,
        capture: np.ndarray,
        options: CalibrateOptions,
    ) -> Layout:
        """The layout of `robot` with its current values as prior. zero_offsets: (nq,) the actuators' zero
        offsets (rad, the stage's in mm last). capture: (6,) rotation vector (rad) and translation (mm)."""
        n = robot.n_segments
        act = tuple(f"s{k + 1}c{i + 1}" for k in range(n) for i in range(3))
        names: list[str] = []
        groups: list[str] = []
        units: list[str] = []
        prior: list[float] = []
        lo: list[float] = []
        hi: list[float] = []
        sc: list[float] = []

        def add(name: str, group: str, unit: str, value: float, low: float, high: float, s: float) -> None:
            names.append(name)
            groups.append(group)
            units.append(unit)
            prior.append(float(value))
            lo.append(float(low))
            hi.append(float(high))
            sc.append(s)

        o = options
        for k, seg in enumerate(robot.segments):
            L = seg.length
            add(f"segment[{k}].length", "lengths", "mm", L, L * (1 - o.length_bound), L * (1 + o.length_bound), 1.0)
        c = robot.coupling
        add("coupling", "coupling", "", c, c - o.coupling_bound, c + o.coupling_bound, 0.01)
        r = robot.cable_radius
        add("cable_radius", "cable_radius", "mm", r, r * (1 - o.radius_bound), r * (1 + o.radius_bound), 0.01)
        for i, a in enumerate(act):
            a0 = float(zero_offsets[i])
            add(f"{a}.zero_offset", "zero_offsets", "rad", a0, a0 - o.offset_bound, a0 + o.offset_bound, 1e-3)
        z0 = float(zero_offsets[-1])
        add("z.zero_offset", "base_z", "mm", z0, z0 - o.base_z_bound, z0 + o.base_z_bound, 1.0)
        for j, ax in enumerate("xyz"):
            add(f"capture.rotation_{ax}", "capture_frame", "rad", capture[j], -2 * math.pi, 2 * math.pi, 1e-3)
        for j, ax in enumerate("xyz"):
            add(f"capture.translation_{ax}", "capture_frame", "mm", capture[3 + j], -1e5, 1e5, 1.0)
        return cls(
            n,
            (*act, "z"),
            tuple(names),
            tuple(groups),
            tuple(units),
            np.array(prior),
            np.array(lo),
            np.array(hi),
            np.array(sc),
        )


def parse_groups(text: str) -> tuple[str, ...]:
    """The groups of a ``--fit`` list (comma separated; "all" for every group)."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise InputError("--fit: empty; name one or more of " + ", ".join(GROUPS))
    if items == ["all"]:
        return GROUPS
    for s in items:
        if s not in GROUPS:
            raise InputError(f"--fit: unknown parameter group {s!r} (known: {', '.join(GROUPS)}, all)")
    return tuple(g for g in GROUPS if g in items)


# ------------------------------------------------------------------ rotations
def rotation_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector w (rad)."""
    w = np.asarray(w, dtype=float)
    th = float(np.linalg.norm(w))
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + math.sin(th) / th * W + (1 - math.cos(th)) / th**2 * W @ W


def rotation_vector(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of the rotation matrix R (angle in [0, pi])."""
    c = max(-1.0, min(1.0, (np.trace(R) - 1) / 2))
    th = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-8:
        return v / 2
    if th > math.pi - 1e-6:  # sin th ~ 0: the axis from the symmetric part
        M = (R + np.eye(3)) / 2
        axis = M[:, int(np.argmax(np.diag(M)))]
        axis = axis / np.linalg.norm(axis)
        return th * axis
    return th / (2 * math.sin(th)) * v


def align(m: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, spread ratio) of the rigid motion best taking points m to p (Kabsch), both (K, 3) mm.

    spread ratio: RMS distance of p from its centroid over that of m (1 when both are in mm).
    """
    cm, cp = m.mean(axis=0), p.mean(axis=0)
    A, B = m - cm, p - cp
    U, _, Vt = np.linalg.svd(A.T @ B)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0)])
    R = Vt.T @ D @ U.T
    sm = float(np.sqrt(np.mean(np.sum(A**2, axis=1))))
    sp = float(np.sqrt(np.mean(np.sum(B**2, axis=1))))
    return R, cp - R @ cm, (sp / sm) if sm > 0 else math.inf


# ----------------------------------------------------------------- the model
def _bending_inverse(robot: Robot, k: int) -> np.ndarray:
    """B1_k (2 x 3): u_k = B1_k d_k / r, the pseudo-inverse of eq. 4 at unit cable radius."""
    a = robot.segments[k].cable_phase + CABLE_SPACING * np.arange(3)
    A1 = np.stack([-np.cos(a), np.sin(a)], axis=1)
    return np.linalg.pinv(A1)


def _markers_expr(robot: Robot, hw: Hardware, sites: Sequence[MarkerSite], theta: ca.SX, v: ca.SX) -> ca.SX:
    """Robot-frame positions (3 x M) of the marker sites for parameters theta and actuator values v."""
    n = robot.n_segments
    L = theta[0:n]
    c = theta[n]
    r = theta[n + 1]
    a0 = theta[n + 2 : n + 2 + 3 * n]
    z0 = theta[n + 2 + 3 * n]
    d = ca.DM(hw.sign[:-1] * hw.spool_radius) * (v[: 3 * n] - a0)
    z = float(hw.sign[-1]) * (v[3 * n] - z0)
    u = [ca.DM(_bending_inverse(robot, k)) @ d[3 * k : 3 * k + 3] / r for k in range(n)]
    ub: list[ca.SX] = [None] * n  # type: ignore[list-item]
    acc = ca.SX.zeros(2)
    for k in reversed(range(n)):  # u_bar_k = u_k + c u_bar_{k+1}
        acc = u[k] + c * acc if k < n - 1 else u[k]
        ub[k] = acc
    R = ca.SX.eye(3)
    o = ca.vertcat(0, 0, z)
    cols: dict[str, ca.SX] = {}
    for k in range(n):
        for s in sites:
            if s.segment == k:
                frac = 1.0 if s.arc is None else s.arc / L[k]
                p, _ = _arc(ub[k], L[k], frac)
                cols[s.name] = o + R @ p
        p, Rk = _arc(ub[k], L[k], 1.0)
        o = o + R @ p
        R = R @ Rk
    return ca.horzcat(*[cols[s.name] for s in sites])


def _rotation_expr(w: ca.SX) -> ca.SX:
    f1, f2 = _f1_f2(ca.sumsqr(w))
    W = _skew([w[0], w[1], w[2]])
    return ca.SX.eye(3) + f2 * W + f1 * (W @ W)


class CalibrationModel:
    """The residual of one sample as CasADi functions of theta (built once per robot and marker set).

    ``markers(theta, v) -> P`` (3 x M, robot frame, mm); ``residual(theta, v, m) -> e`` (3M, mm) with m
    the stacked capture-frame positions; ``jacobian(theta, v, m) -> de/dtheta`` (3M x n).
    """

    def __init__(self, robot: Robot, hw: Hardware, sites: Sequence[MarkerSite], layout: Layout) -> None:
        self.robot, self.hw, self.sites, self.layout = robot, hw, tuple(sites), layout
        self.M = len(self.sites)
        th = ca.SX.sym("theta", layout.n)
        v = ca.SX.sym("v", 3 * robot.n_segments + 1)
        m = ca.SX.sym("m", 3 * self.M)
        P = _markers_expr(robot, hw, self.sites, th, v)
        nb = layout.n - 6
        Rw = _rotation_expr(th[nb : nb + 3])
        t = th[nb + 3 : nb + 6]
        e = ca.vertcat(*[Rw @ m[3 * j : 3 * j + 3] + t - P[:, j] for j in range(self.M)])
        self.markers = ca.Function("markers", [th, v], [P], {"cse": True})
        self.residual = ca.Function("residual", [th, v, m], [e], {"cse": True})
        self.jacobian = ca.Function("jacobian", [th, v, m], [ca.jacobian(e, th)], {"cse": True})
        mask = ca.SX.sym("mask", self.M)
        delta2 = ca.SX.sym("delta2")
        loss = 0
        for j in range(self.M):
            s = ca.sumsqr(e[3 * j : 3 * j + 3])
            loss += mask[j] * 2 * delta2 * (ca.sqrt(1 + s / delta2) - 1)
        self.loss = ca.Function("loss", [th, v, m, mask, delta2], [loss], {"cse": True})

    def predict(self, theta: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Robot-frame marker positions (N, M, 3) mm for actuator values (N, nq)."""
        N = values.shape[0]
        out = np.asarray(self.markers.map(N)(theta, values.T))  # 3 x (M N)
        return out.reshape(3, N, self.M).transpose(1, 2, 0)

    def residuals(self, theta: np.ndarray, values: np.ndarray, m: np.ndarray) -> np.ndarray:
        """Residuals (N, M, 3) mm; m (N, M, 3) capture-frame positions (NaN entries give NaN)."""
        N = values.shape[0]
        mm = np.nan_to_num(m).reshape(N, 3 * self.M)
        e = np.asarray(self.residual.map(N)(theta, values.T, mm.T)).T.reshape(N, self.M, 3)
        e[np.isnan(m).any(axis=2)] = np.nan
        return e

    def jacobians(self, theta: np.ndarray, values: np.ndarray, m: np.ndarray) -> np.ndarray:
        """d residual / d theta (N, M, 3, n)."""
        N = values.shape[0]
        mm = np.nan_to_num(m).reshape(N, 3 * self.M)
        J = np.asarray(self.jacobian.map(N)(theta, values.T, mm.T))  # (3M) x (n N)
        return J.reshape(3 * self.M, N, self.layout.n).transpose(1, 0, 2).reshape(N, self.M, 3, self.layout.n)


# ------------------------------------------------------------------- fitting
@dataclass(frozen=True)
class MarkerStats:
    """Residual norms of one marker (mm): RMS, 95th percentile, max, count; and the RMS without outliers
    (norms above OUTLIER_FACTOR times the median) with the outlier count."""

    rms: float
    p95: float
    max: float
    count: int
    rms_inliers: float = math.nan
    outliers: int = 0

    def to_dict(self) -> dict[str, float]:
        return {
            "rms_mm": self.rms,
            "p95_mm": self.p95,
            "max_mm": self.max,
            "count": self.count,
            "rms_inliers_mm": self.rms_inliers,
            "outliers": self.outliers,
        }


# A residual norm above this many times the marker's median is counted as an outlier in the report
# (for Gaussian noise the median norm is 1.54 sigma: 4 medians is 6 sigma).
OUTLIER_FACTOR = 4.0


def marker_stats(e: np.ndarray, names: Sequence[str]) -> dict[str, MarkerStats]:
    """Per-marker residual statistics of residuals (N, M, 3) mm (NaN rows are missing markers)."""
    out = {}
    for j, name in enumerate(names):
        d = np.linalg.norm(e[:, j], axis=1)
        d = d[np.isfinite(d)]
        if d.size == 0:
            out[name] = MarkerStats(math.nan, math.nan, math.nan, 0)
            continue
        inl = d[d <= OUTLIER_FACTOR * np.median(d)]
        out[name] = MarkerStats(
            float(np.sqrt(np.mean(d**2))),
            float(np.percentile(d, 95)),
            float(d.max()),
            int(d.size),
            float(np.sqrt(np.mean(inl**2))) if inl.size else math.nan,
            int(d.size - inl.size),
        )
    return out


@dataclass(frozen=True)
class Held:
    """A parameter the data cannot determine (held at its prior) and what it cannot be told apart from."""

    name: str
    confounded_with: tuple[str, ...]
    relative_residual: float


@dataclass(frozen=True)
class CalibrationResult:
    """The outcome of `fit` (mm, rad). theta: fitted parameters (prior where not fitted or held).
    free: the parameters fitted. std_error: standard errors (NaN where not fitted). singular_values: of the
    column-scaled, robust-weighted Jacobian of the fitted parameters (descending). held: parameters that
    were asked for but cannot be determined. before/after: per-marker residual statistics, split into
    'fit' and 'heldout'. before is the uncalibrated model (prior parameters with the best rigid capture
    frame). success, status, iterations, solve_time: IPOPT's verdict, its status text, iterations and
    time (s). residuals: after-fit residuals (N, M, 3); heldout_mask: (N,) True for held-out samples."""

    layout: Layout
    theta: np.ndarray
    prior: np.ndarray
    free: np.ndarray
    std_error: np.ndarray
    singular_values: np.ndarray
    held: tuple[Held, ...]
    before: dict[str, dict[str, MarkerStats]]
    after: dict[str, dict[str, MarkerStats]]
    success: bool
    status: str
    iterations: int
    solve_time: float
    sigma: float
    residuals: np.ndarray = field(repr=False)
    heldout_mask: np.ndarray = field(repr=False)
    at_bound: tuple[str, ...] = ()

    def value(self, name: str) -> float:
        return float(self.theta[self.layout.names.index(name)])

    def capture(self) -> np.ndarray:
        """The capture frame (6,): rotation vector (rad) and translation (mm), capture -> robot."""
        return self.theta[-6:].copy()


@dataclass(frozen=True)
class Observations:
    """What the fit reads: actuator values (N, nq), capture-frame marker positions (N, M, 3; NaN = not
    seen), the marker sites, and the held-out mask (N,)."""

    values: np.ndarray
    positions: np.ndarray
    sites: tuple[MarkerSite, ...]
    heldout: np.ndarray


def split(n: int, fraction: float, seed: int) -> np.ndarray:
    """A held-out mask of n samples: round(fraction n) of them, drawn with `seed`."""
    mask = np.zeros(n, dtype=bool)
    k = round(fraction * n)
    if k:
        mask[np.random.default_rng(seed).permutation(n)[:k]] = True
    return mask


def initial_capture(cm: CalibrationModel, theta: np.ndarray, obs: Observations, rows: np.ndarray) -> np.ndarray:
    """The capture frame (6,) that best aligns the markers with the model at theta; `InputError` when the
    plausibility check on lengths fails (the markers' spread about their centroid against the model's, which
    the segment lengths set): the marker file is in another unit than mm."""
    P = cm.predict(theta, obs.values[rows])
    m = obs.positions[rows]
    ok = np.isfinite(m).all(axis=2)
    R, t, ratio = align(m[ok], P[ok])
    lo, hi = PLAUSIBLE_SCALE
    if not lo <= ratio <= hi:
        raise InputError(
            f"markers: their distances are {1 / ratio:.4g} times what the robot's segment lengths give (expected "
            "about 1): the marker file is not in mm (metres? convert it) or the markers sit elsewhere"
        )
    return np.concatenate([rotation_vector(R), t])


def identifiable(Jw: np.ndarray, layout: Layout, free: np.ndarray, tol: float) -> tuple[np.ndarray, tuple[Held, ...]]:
    """(free parameters the data determines, the held ones) from the weighted Jacobian Jw (rows x n).

    Columns are scaled to unit norm and taken in `PRIORITY` order; one whose part outside the span of
    those already kept is below `tol` (relative) is held. Works on the n x n Gram matrix: a tall QR or SVD
    runs multi-threaded LAPACK, which is 25 times slower on a loaded machine; the Gram matrix keeps the
    relative residuals to ~1e-7 for the near-dependent columns that matter here (tol 1e-6).
    """
    G = Jw.T @ Jw
    norms = np.sqrt(np.maximum(np.diag(G), 0.0))
    order = [i for g in PRIORITY for i in layout.index(g) if free[i]]
    kept: list[int] = []
    held: list[Held] = []
    for i in order:
        if norms[i] == 0.0:
            held.append(Held(layout.names[i], (), 0.0))
            continue
        if kept:
            Gn = G[np.ix_(kept, kept)] / np.outer(norms[kept], norms[kept])
            g = G[kept, i] / (norms[kept] * norms[i])
            coef = np.linalg.lstsq(Gn, g, rcond=None)[0]
            rel = math.sqrt(max(1.0 - float(g @ coef), 0.0))
        else:
            coef, rel = np.zeros(0), 1.0
        if rel < tol:
            big = [layout.names[kept[j]] for j in np.argsort(-np.abs(coef))[:3] if abs(coef[j]) > 1e-3]
            held.append(Held(layout.names[i], tuple(big), rel))
            continue
        kept.append(i)
    out = np.zeros(layout.n, dtype=bool)
    out[kept] = True
    return out, tuple(held)


def scaled_singular_values(Jf: np.ndarray) -> np.ndarray:
    """Singular values (descending) of Jf with its columns scaled to unit norm, from the Gram matrix."""
    if Jf.size == 0:
        return np.zeros(0)
    G = Jf.T @ Jf
    d = np.sqrt(np.maximum(np.diag(G), 1e-300))
    ev = np.linalg.eigvalsh(G / np.outer(d, d))
    return np.sqrt(np.maximum(ev, 0.0))[::-1]


def _weighted(J: np.ndarray, e: np.ndarray, delta: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(weighted Jacobian rows x n, weighted residual rows, per-observation weights) of observed markers."""
    ok = np.isfinite(e).all(axis=2)
    s = np.sum(np.nan_to_num(e) ** 2, axis=2)
    w = np.where(ok, 1.0 / np.sqrt(1.0 + s / delta**2), 0.0)
    sw = np.sqrt(w)[..., None]
    Jw = (J * sw[..., None])[ok].reshape(-1, J.shape[-1])
    ew = (np.nan_to_num(e) * sw)[ok].reshape(-1)
    return Jw, ew, w[ok]


def _stats(
    cm: CalibrationModel, theta: np.ndarray, obs: Observations
) -> tuple[dict[str, dict[str, MarkerStats]], np.ndarray]:
    e = cm.residuals(theta, obs.values, obs.positions)
    names = [s.name for s in cm.sites]
    return {"fit": marker_stats(e[~obs.heldout], names), "heldout": marker_stats(e[obs.heldout], names)}, e


# long: one pipeline (initial frame, identifiability, NLP, covariance, statistics), each step a few lines
def fit(
    robot: Robot,
    hw: Hardware,
    zero_offsets: np.ndarray,
    obs: Observations,
    groups: Sequence[str],
    options: CalibrateOptions | None = None,
    capture: np.ndarray | None = None,
) -> CalibrationResult:
    """Fit the parameter groups `groups` to the observations; see the module docstring.

    zero_offsets: (nq,) the actuators' current zero offsets (prior). capture: (6,) prior capture frame
    (rotation vector rad, translation mm, capture -> robot); None: the best rigid alignment of the
    markers with the prior model (required when the capture frame is not fitted and unknown).
    """
    o = options or CalibrateOptions()
    for g in groups:
        if g not in GROUPS:
            raise InputError(f"--fit: unknown parameter group {g!r} (known: {', '.join(GROUPS)})")
    check_sites(obs.sites, robot)
    fit_rows = ~obs.heldout
    layout0 = Layout.build(robot, zero_offsets, np.zeros(6), o)
    cm0 = CalibrationModel(robot, hw, obs.sites, layout0)
    seen = np.isfinite(obs.positions).all(axis=2)
    n_fit = int(np.sum(seen[fit_rows].any(axis=1)))
    free = np.zeros(layout0.n, dtype=bool)
    for g in groups:
        free[layout0.index(g)] = True
    need = max(MIN_SAMPLES, int(free.sum()))
    if n_fit < need:
        raise InputError(f"samples: {n_fit} usable fit samples, need at least {need} (record more motion)")
    if capture is None:
        capture = initial_capture(cm0, layout0.prior, obs, np.flatnonzero(fit_rows))
    layout = Layout.build(robot, zero_offsets, np.asarray(capture, dtype=float), o)
    cm = cm0  # its functions take theta as an argument: only the prior changed
    prior = layout.prior
    before, _ = _stats(cm, prior, obs)
    if "capture_frame" not in groups:
        initial_capture(cm, prior, obs, np.flatnonzero(fit_rows))  # the unit check still applies
    # identifiability at the prior (the Jacobian depends on the motion, not on the noise)
    Vf, Pf = obs.values[fit_rows], obs.positions[fit_rows]
    e0 = cm.residuals(prior, Vf, Pf)
    Jw0, _, _ = _weighted(cm.jacobians(prior, Vf, Pf), e0, o.loss_scale)
    free, held = identifiable(Jw0, layout, free, o.identifiability_tol)
    if not free.any():
        names = ", ".join(h.name for h in held)
        raise InputError(f"--fit: this data determines none of the parameters asked for ({names})")
    theta, status, success, iters, t_solve = _solve(cm, layout, free, Vf, Pf, o)
    e = cm.residuals(theta, Vf, Pf)
    Jw, ew, _ = _weighted(cm.jacobians(theta, Vf, Pf), e, o.loss_scale)
    Jf = Jw[:, free]
    dof = max(Jw.shape[0] - int(free.sum()), 1)
    sigma2 = float(ew @ ew) / dof
    se = np.full(layout.n, math.nan)
    cov = sigma2 * np.linalg.pinv(Jf.T @ Jf)
    se[free] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sv = scaled_singular_values(Jf)
    after, e_all = _stats(cm, theta, obs)
    span = layout.upper - layout.lower
    at_bound = tuple(
        layout.names[i]
        for i in np.flatnonzero(free)
        if min(theta[i] - layout.lower[i], layout.upper[i] - theta[i]) < 1e-6 * span[i]
    )
    return CalibrationResult(
        layout=layout,
        theta=theta,
        prior=prior,
        free=free,
        std_error=se,
        singular_values=sv,
        held=held,
        before=before,
        after=after,
        success=success,
        status=status,
        iterations=iters,
        solve_time=t_solve,
        sigma=math.sqrt(sigma2),
        residuals=e_all,
        heldout_mask=obs.heldout.copy(),
        at_bound=at_bound,
    )


def _sample_functions(
    cm: CalibrationModel, layout: Layout, idx: np.ndarray, o: CalibrateOptions
) -> tuple[ca.Function, ca.Function]:
    """Per-sample loss and Hessian (upper triangle) as SX functions of the scaled free parameters xi.

    Hessian "gauss-newton": 2 sum_j w_j J_j^T J_j with the robust weights w_j (exact Jacobians J_j of the
    residuals; it drops the residuals' curvature and the loss's negative second derivative, so it is
    positive semidefinite and four times cheaper); "exact": CasADi's exact Hessian of the loss.
    """
    xi = ca.SX.sym("xi", idx.size)
    v = ca.SX.sym("v", 3 * layout.n_segments + 1)
    m = ca.SX.sym("m", 3 * cm.M)
    mask = ca.SX.sym("mask", cm.M)
    S = np.zeros((layout.n, idx.size))
    S[idx, np.arange(idx.size)] = layout.scale[idx]
    th = ca.DM(layout.prior) + ca.DM(S) @ xi
    d2 = o.loss_scale**2
    loss = cm.loss(th, v, m, mask, d2)
    if o.hessian == "exact":
        H = ca.hessian(loss, xi)[0]
    else:
        e = cm.residual(th, v, m)
        J = ca.jacobian(e, xi)
        w = ca.vertcat(*[mask[j] / ca.sqrt(1 + ca.sumsqr(e[3 * j : 3 * j + 3]) / d2) for j in range(cm.M)])
        Wr = ca.repmat(ca.reshape(ca.repmat(w.T, 3, 1), 3 * cm.M, 1), 1, idx.size)
        H = 2 * J.T @ (J * Wr)
    args = [xi, v, m, mask]
    return (
        ca.Function("loss_i", args, [loss], {"cse": True}),
        ca.Function("hess_i", args, [ca.triu(H)], {"cse": True}),
    )


def _solve(
    cm: CalibrationModel,
    layout: Layout,
    free: np.ndarray,
    values: np.ndarray,
    positions: np.ndarray,
    o: CalibrateOptions,
) -> tuple[np.ndarray, str, bool, int, float]:
    """IPOPT on the mean pseudo-Huber loss over the free parameters (scaled: theta = prior + scale xi).

    Returns (theta, IPOPT's status text, success, iterations, solve time s).
    """
    N = values.shape[0]
    mask = np.isfinite(positions).all(axis=2).astype(float)
    mm = np.nan_to_num(positions).reshape(N, 3 * cm.M)
    idx = np.flatnonzero(free)
    t0 = time.perf_counter()
    loss_i, hess_i = _sample_functions(cm, layout, idx, o)
    data = [ca.DM(values.T), ca.DM(mm.T), ca.DM(mask.T)]
    # mean over observations: the objective's size does not grow with N, so the tolerance means the same
    scale = 1.0 / max(float(mask.sum()), 1.0)
    xi = ca.MX.sym("xi", idx.size)
    # the parameters are shared by every sample (reduce_in) and the sums are taken inside the map
    f = scale * loss_i.map("loss_sum", "serial", N, [0], [0])(xi, *data)
    lam_f = ca.MX.sym("lam_f")
    H = lam_f * scale * hess_i.map("hess_sum", "serial", N, [0], [0])(xi, *data)
    hess_lag = ca.Function(
        "hess_lag",
        [xi, ca.MX.sym("p", 0), lam_f, ca.MX.sym("lam_g", 0)],
        [H],
        ["x", "p", "lam_f", "lam_g"],
        ["triu_hess_gamma_x_x"],
    )
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.max_iter": o.max_iter,
        "ipopt.tol": o.tol,
        "hess_lag": hess_lag,
    }
    solver = ca.nlpsol("calibrate", "ipopt", {"x": xi, "f": f}, opts)
    lbx = (layout.lower[idx] - layout.prior[idx]) / layout.scale[idx]
    ubx = (layout.upper[idx] - layout.prior[idx]) / layout.scale[idx]
    sol = solver(x0=np.zeros(idx.size), lbx=lbx, ubx=ubx)
    t_solve = time.perf_counter() - t0
    st = solver.stats()
    out = layout.prior.copy()
    out[idx] += layout.scale[idx] * np.asarray(sol["x"]).ravel()
    status = str(st.get("return_status", "unknown"))
    return out, status, bool(st.get("success", False)), int(st.get("iter_count", 0)), t_solve


def synthetic_values(robot: Robot, hw: Hardware, n: int, seed: int, *, planar_distal: bool = False) -> np.ndarray:
    """n actuator value samples (n, nq) spread over the workspace: random bending vectors within 60 % of
    each segment's theta_max (uniform over the disc), z over the middle of the stroke.
    planar_distal: keep the distal segment's cables at zero (its bending then comes only from offsets)."""
    rng = np.random.default_rng(seed)
    ns = robot.n_segments
    x = np.zeros((n, robot.nx))
    for k, seg in enumerate(robot.segments):
        if planar_distal and k == ns - 1:
            continue
        rad = 0.6 * seg.theta_max * np.sqrt(rng.random(n)) / max(1.0, 1.0 + abs(robot.coupling) * (ns - 1 - k))
        ang = rng.random(n) * 2 * math.pi
        x[:, 2 * k] = rad * np.cos(ang)
        x[:, 2 * k + 1] = rad * np.sin(ang)
    lo, hi = robot.z_range
    mid, half = (lo + hi) / 2, (hi - lo) / 4
    x[:, -1] = mid + half * (2 * rng.random(n) - 1)
    A, _ = robot.cable_matrix()
    dq = x @ A.T
    values = np.empty_like(dq)
    values[:, :-1] = hw.sign[:-1] * dq[:, :-1] / hw.spool_radius
    values[:, -1] = hw.sign[-1] * dq[:, -1]
    return values


def simulate_markers(
    robot: Robot,
    hw: Hardware,
    zero_offsets: np.ndarray,
    capture: np.ndarray,
    values: np.ndarray,
    sites: Sequence[MarkerSite],
    *,
    noise: float = 0.0,
    outliers: float = 0.0,
    outlier_size: float = 20.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic capture-frame marker positions (N, M, 3) mm of a robot with these true parameters, and
    the outlier mask (N, M).

    capture: (6,) true capture -> robot frame (rotation vector rad, translation mm). noise: standard
    deviation per axis (mm). outliers: fraction of marker observations displaced by a random vector of
    about outlier_size mm (a swapped or misidentified marker).
    """
    layout = Layout.build(robot, zero_offsets, capture, CalibrateOptions())
    cm = CalibrationModel(robot, hw, sites, layout)
    P = cm.predict(layout.prior, values)
    R = rotation_matrix(capture[:3])
    m = (P - capture[3:]) @ R  # p = R m + t  =>  m = R^T (p - t)
    rng = np.random.default_rng(seed)
    m = m + rng.normal(0.0, noise, m.shape)
    bad = rng.random(m.shape[:2]) < outliers
    m[bad] += rng.normal(0.0, outlier_size, (int(bad.sum()), 3))
    return m, bad


@dataclass(frozen=True)
class SyntheticTruth:
    """A robot perturbed from a nominal one, for synthetic calibration data: the true robot (lengths,
    coupling), the true zero offsets (nq,) and the true capture frame (6,) capture -> robot."""

    robot: Robot
    zero_offsets: np.ndarray
    capture: np.ndarray

    @property
    def theta(self) -> np.ndarray:
        """The true parameter vector in `Layout` order."""
        return Layout.build(self.robot, self.zero_offsets, self.capture, CalibrateOptions()).prior


def synthetic_truth(robot: Robot, zero_offsets: np.ndarray, seed: int = 0) -> SyntheticTruth:
    """The issue's synthetic ground truth: segment lengths +-5 %, coupling -0.8 (from -1), servo zero
    offsets uniform in +-0.05 rad, a capture frame rotated 10 degrees about a random axis and shifted
    50 mm in a random direction. Cable radius and the stage's zero offset stay nominal."""
    rng = np.random.default_rng(seed)
    segs = tuple(replace(s, length=s.length * (1 + 0.05 * rng.choice([-1.0, 1.0]))) for s in robot.segments)
    true_robot = replace(robot, segments=segs, coupling=-0.8)
    zo = np.asarray(zero_offsets, dtype=float).copy()
    zo[:-1] += rng.uniform(-0.05, 0.05, zo.size - 1)
    axis = rng.normal(size=3)
    shift = rng.normal(size=3)
    cap = np.concatenate([math.radians(10) * axis / np.linalg.norm(axis), 50.0 * shift / np.linalg.norm(shift)])
    return SyntheticTruth(true_robot, zo, cap)
