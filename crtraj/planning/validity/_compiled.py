"""Compiled, batched validity kernels: body clearance, backbone points, tip Jacobians and motion bounds in C.

The interpreted path evaluates CasADi graphs through CasADi's virtual machine, one mapped call per
batch, and converts every result through DM objects. Here the same symbolic expressions are generated
as C by CasADi (so both paths compute the same numbers, in the same order up to the compiler's
rounding), and a small hand-written C driver loops over a whole batch in one call:

- ``crtraj_points(N, X, P)``: backbone check points (N, n, 3) mm of configurations X (N, nx);
- ``crtraj_clearance(N, X, K, S, stride, d)``: per configuration, min over obstacle slots and chords of
  (distance from the slot's centre to the chord segment) minus the slot's radius (mm). S holds K
  obstacle slots in `crtraj.world.packing`'s layout ``[cx, cy, cz, r, active]``; slots with active 0
  are padding and skipped, so one library serves every obstacle count. stride 0: the same slots for
  every configuration (a static scene); 5 K: slots of their own per configuration (swept spheres);
- ``crtraj_tip_jac(N, X, P, J)``: tip positions (N, 3) mm and tip Jacobians (N, 3, nx);
- ``crtraj_project(N, X, target, ...)``: the safe IK's batched damped least-squares projection onto a tip
  target (`crtraj.planning.ik.SafeIK.project`), the whole Newton loop per configuration in C, each
  configuration stopping as soon as its tip is on the target;
- ``crtraj_path_clearance(...)``: `crtraj.planning.validity.MotionValidator.path_clearance` (a result's measured
  clearance) in one call, with an exact broad phase per motion (the same minima);
- ``crtraj_bspline(...)``: `crtraj.core.splines.BSplineCurve` at many parameters, operation for operation (the
  smoothing's spline samples, `crtraj.planning.postprocess`);
- ``crtraj_phase_law(...)``: the retiming's phase-plane pass along a smoothed curve and the law's knot times
  (`crtraj.planning.retime`), operation for operation, so the same numbers;
- ``crtraj_natural_slopes(...)``, ``crtraj_hermite(...)``: the natural cubic spline's slopes and the cubic's values
  and derivatives (`crtraj.core.splines`), operation for operation: the retiming's curve in C;
- ``crtraj_verify_motion(...)``: the closed loop's dense verification of a step's move in one call
  (`MotionValidator.held_clearance`);
- ``crtraj_motion_bound(N, dX, B)``: the body-motion bound B(dx) (mm, `crtraj.planning.metric`; it agrees
  with numpy's to 1e-12, but the planners keep numpy's, whose rounding times every motion, so that both
  paths give identical plans);
- ``crtraj_check_edges(...)``: the adaptive certification of straight motions of
  `crtraj.planning.validity.MotionValidator.check_edges` for a static scene, the whole refinement loop
  in C with numpy's arithmetic, operation for operation (so it returns the same numbers);
  ``crtraj_check_static(...)`` the same with each motion's first interval count computed in C, as the
  validator counts them (what the planners call: less Python per call);
- ``crtraj_check_moving_auto(...)``: the same among moving, breathing obstacles: every interval is
  checked against the spheres that contain each obstacle over its time window (`Scene.swept_spheres`,
  computed in C from `Scene.motion_table` with numpy's arithmetic: libm's sin, the same operation order,
  no contraction into fused multiply-adds), so it too returns the numpy loop's numbers bit for bit.
  Both take a broad phase (``broad``: from that many obstacles on): per motion, an obstacle whose clearance
  at the motion's start, minus the motion's body-motion bound, exceeds every interval's h cannot decide any
  sample (each would be certified whichever obstacle is nearest), so only the others enter the narrow
  phase; the certified fractions are the same bit for bit, `lower` may be smaller (still a lower bound).

The library is built once per robot (its kinematic description), check-point count and generator
version through `crtraj.core.build_cache.BuildCache` and called with ctypes on numpy buffers
(`benchmarks/plan.py`, section 5, measures it against ``casadi.external``). Without a C compiler
`ValidityKernel.load` returns None and the callers keep the interpreted path.
"""

from __future__ import annotations

import ctypes
import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache, BuildKey
from crtraj.model.codegen import codegen_builder
from crtraj.model.kinematics import Model
from crtraj.planning.metric import metric_matrix
from crtraj.planning.validity import _rod_body as rod_body
from crtraj.planning.validity._driver import DRIVER as EDGE_DRIVER
from crtraj.planning.validity._path_driver import PATH_DRIVER
from crtraj.planning.validity._retime_driver import CURVE_DRIVER, RETIME_DRIVER, VERIFY_DRIVER
from crtraj.world import packing

# The hand-written C around the generated functions: the edge checks' driver, the path functions, the retiming's.
DRIVER = EDGE_DRIVER + PATH_DRIVER + RETIME_DRIVER + CURVE_DRIVER + VERIFY_DRIVER
# Version of the generated code and driver: raising it makes every cached kernel foreign (rebuilt).
GENERATOR = 20
# Most check points a kernel is generated for: the generated FK grows with them (100 points: ~15 s of
# gcc); denser checks (reports, tests) stay on the interpreted path.
MAX_COMPILED_POINTS = 200
# Compiler flags of the kernel after the build cache's defaults (-O2, no contraction into fused multiply-adds):
# -O3 keeps IEEE arithmetic (no reassociation), so the same numbers, ~10 % faster backbone points.
KERNEL_FLAGS = ("-O3",)
# Largest batch one driver call takes; callers split larger ones (bounds the driver's int arithmetic).
MAX_BATCH = 1 << 24


def motion_bound_expr(dx: Any, M: np.ndarray, n_segments: int) -> Any:
    """B(dx) = sum_k |(M dx)_k| + |dz| (mm) as a CasADi expression (`crtraj.planning.metric.BodyMetric`)."""
    dy = ca.DM(M) @ dx
    blocks = [ca.norm_2(dy[2 * k : 2 * k + 2]) for k in range(n_segments)]
    return ca.sum1(ca.vertcat(*blocks)) + ca.fabs(dy[-1])


def kernel_key(model: Model, check_points: int) -> BuildKey:
    """The cache key of a kernel: the robot's kinematic description (its robot-file table without the
    description and the actuators, which the code does not depend on), the check points, the generator
    and the driver's SHA-256."""
    robot = {k: v for k, v in model.robot.to_dict().items() if k not in ("description", "actuators")}
    # the driver's text is part of the key too: a changed driver can never load a stale library
    driver = hashlib.sha256(DRIVER.encode("utf-8")).hexdigest()
    spec = {"robot": robot, "check_points": int(check_points), "generator": GENERATOR, "driver": driver}
    spec["flags"] = list(KERNEL_FLAGS)
    if model.identity() is not None:  # a body other than PCC's (the rod's): its own library
        spec["body"] = model.identity()
    if rod_body.is_rod(model):  # the rod's hand-written body (`body_source`): a changed one never loads stale
        spec["rod_body"] = hashlib.sha256(Path(rod_body.__file__).read_bytes()).hexdigest()
    return BuildKey("crtraj_validity", spec)


def kernel_functions(model: Model, check_points: int) -> list[ca.Function]:
    """The CasADi functions the kernel library is generated from (one configuration each). A rod model's
    (`RodModel`): PCC's body and tip as ``crtraj_bbp`` and ``crtraj_tjp``, around which `body_source` writes
    ``crtraj_bb`` and ``crtraj_tipjac`` by hand."""
    robot = model.robot
    metric = metric_matrix(robot)
    x = ca.SX.sym("x", robot.nx)
    rod = rod_body.is_rod(model)
    pcc = Model(robot) if rod else model
    bb = pcc.backbone_function(check_points)
    return [
        ca.Function("crtraj_bbp" if rod else "crtraj_bb", [x], [bb(x)]),
        # common subexpressions of the tip and its Jacobian computed once (-14 % operations; the same numbers)
        ca.Function("crtraj_tjp" if rod else "crtraj_tipjac", [x], [pcc.tip(x), pcc.jac_tip(x)], {"cse": True}),
        ca.Function("crtraj_mb", [x], [motion_bound_expr(x, metric, robot.n_segments)]),
    ]


def _builder(model: Model, check_points: int, name: str) -> Callable[[Path, str], Path]:
    """A kernel's build step: generated functions, then the driver (a rod model's body, `rod_body.body_source`,
    before it and its tips after it; written on a miss only)."""
    defines = f"\n#define CRTRAJ_NX {model.robot.nx}\n#define CRTRAJ_NP {int(check_points)}\n"

    def build(folder: Path, compiler: str) -> Path:
        rod = rod_body.is_rod(model)
        extra = defines + (rod_body.body_source(model, check_points) if rod else "") + DRIVER
        extra += rod_body.ROD_TIPS_C if rod else ""
        return codegen_builder(lambda: kernel_functions(model, check_points), name, extra, KERNEL_FLAGS)(
            folder, compiler
        )

    return build


_P = ctypes.c_void_p
_N = ctypes.c_longlong


def per_item(a: Any, n: int) -> np.ndarray:
    """a (a scalar, or one value per item (n,)) as a contiguous float64 (n,) array: what
    ``np.ascontiguousarray(np.broadcast_to(a, (n,)), dtype=float)`` gives, without its ~5 us per call (the edge
    checks call it several times per batch, many batches per query)."""
    a = np.asarray(a, dtype=float)
    if a.shape == (n,):
        return np.ascontiguousarray(a)
    if a.ndim == 0:
        return np.full(n, float(a))
    return np.ascontiguousarray(np.broadcast_to(a, (n,)))


def _ptr(a: np.ndarray) -> int:
    """The address of a contiguous array's data. A ctypes view of a writable buffer gives it in ~0.5 us, a third
    of ``a.__array_interface__`` (which builds a dict per call; the edge checks pass eight arrays per call, many
    calls per query); read-only and empty arrays take that slower way."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):
        return a.__array_interface__["data"][0]


def _mode(prefix: bool, first: bool, verdict: bool) -> int:
    """The edge checks' mode bits: 1 prefix, 2 first (stop after the first motion certified whole), 4 verdict."""
    return int(bool(prefix)) | (2 if first else 0) | (4 if verdict else 0)


class ValidityKernel:
    """A loaded kernel library for one robot and check-point count (see the module docstring).

    Built by `load`; the methods take and return numpy arrays (mm, rad). One kernel may be shared by
    threads: the driver keeps no state between calls.
    """

    def __init__(self, library: Path, nx: int, check_points: int) -> None:  # long: one ctypes binding per C function
        self.library = library
        self.nx = int(nx)
        self.check_points = int(check_points)
        lib = ctypes.CDLL(str(library))
        self._points = lib.crtraj_points
        self._points.argtypes = [_N, _P, _P]
        self._clearance = lib.crtraj_clearance
        self._clearance.argtypes = [_N, _P, _N, _P, _N, _P]
        self._clearance_windows = lib.crtraj_clearance_windows
        self._clearance_windows.argtypes = [_N, _P, _N, _P, ctypes.c_double, _P, _P, _P]
        self._tip_jac = lib.crtraj_tip_jac
        self._tip_jac.argtypes = [_N, _P, _P, _P]
        self._motion_bound = lib.crtraj_motion_bound
        self._project = lib.crtraj_project
        self._project.argtypes = [_N, _P, _P, _N, _P] + [ctypes.c_double] * 3 + [_N, _P, _P, _P]
        self._project.argtypes += [ctypes.c_double, ctypes.c_double, _P]
        self._motion_bound.argtypes = [_N, _P, _P]
        self._check_edges = lib.crtraj_check_edges
        self._check_edges.argtypes = [_N, _P, _P, _P, _P, _N, _P, ctypes.c_double, ctypes.c_double, ctypes.c_int]
        self._check_edges.argtypes += [_N, _P, _P, _P]
        self._path_clearance = lib.crtraj_path_clearance
        self._path_clearance.argtypes = [_N, _P, _P, _P, ctypes.c_double, _N, _P, _P] + [ctypes.c_double] * 3
        self._path_clearance.argtypes += [_P, _P]
        self._bspline = lib.crtraj_bspline
        self._bspline.argtypes = [_N, _P, _N, _P, _N, _N, _P, _N, _P]
        self._check_static = lib.crtraj_check_static
        self._check_static.argtypes = [_N, _P, _P, _P, ctypes.c_double, _N, _P, ctypes.c_double, ctypes.c_double]
        self._check_static.argtypes += [ctypes.c_int, _N, _P, _P, _P]
        self._check_moving_auto = lib.crtraj_check_moving_auto
        self._check_moving_auto.argtypes = [_N, _P, _P, _P, ctypes.c_double, _P, _P, _N, _P] + [ctypes.c_double] * 5
        self._check_moving_auto.argtypes += [ctypes.c_int, _N, _P, _P, _P]
        self._phase_law = lib.crtraj_phase_law
        self._phase_law.argtypes = [_N, _N, _P, _P, _P, _P, _P, _P]
        self._natural_slopes = lib.crtraj_natural_slopes
        self._natural_slopes.argtypes = [_N, _N, _P, _P, _P]
        self._hermite = lib.crtraj_hermite
        self._hermite.argtypes = [_N, _N, _P, _P, _P, _N, _P, ctypes.c_int, _P]
        self._verify_motion = lib.crtraj_verify_motion
        self._verify_motion.argtypes = [_N, _P, _P, ctypes.c_int, ctypes.c_double, ctypes.c_double, _N, _P, _P]
        self._verify_motion.argtypes += [ctypes.c_double, ctypes.c_double, _P]
        # the last static slots and obstacle table passed, with their addresses: the same scene's arrays come back
        # call after call (a table is read-only, whose address costs a dict per call)
        self._slots: tuple[Any, int] = (None, 0)
        self._table: tuple[Any, int] = (None, 0)
        for f in (
            self._points,
            self._clearance,
            self._clearance_windows,
            self._tip_jac,
            self._motion_bound,
            self._project,
            self._check_edges,
            self._check_static,
            self._check_moving_auto,
            self._bspline,
            self._path_clearance,
            self._phase_law,
            self._natural_slopes,
            self._hermite,
            self._verify_motion,
        ):
            f.restype = ctypes.c_int

    @classmethod
    def load(cls, model: Model, check_points: int, cache: BuildCache) -> ValidityKernel | None:
        """The kernel of `model` at `check_points`, from `cache` (built on a miss); None without a C compiler."""
        key = kernel_key(model, check_points)
        return cache.load(
            key, _builder(model, check_points, key.name), lambda lib: cls(lib, model.robot.nx, check_points)
        )

    def _configs(self, X: Any) -> np.ndarray:
        X = np.ascontiguousarray(X, dtype=float)
        if X.ndim != 2 or X.shape[1] != self.nx:
            raise ValueError(f"configurations: expected shape (N, {self.nx}), got {X.shape}")
        if len(X) > MAX_BATCH:
            raise ValueError(f"configurations: at most {MAX_BATCH} per call, got {len(X)}")
        return X

    @staticmethod
    def _check(rc: int, what: str) -> None:
        if rc != 0:
            raise RuntimeError(f"compiled {what} failed (code {rc})")

    def points(self, X: Any) -> np.ndarray:
        """Check points (N, check_points, 3) mm of configurations X (N, nx)."""
        X = self._configs(X)
        out = np.empty((len(X), self.check_points, 3))
        self._check(self._points(len(X), _ptr(X), _ptr(out)), "backbone points")
        return out

    def clearance(self, X: Any, slots: Any) -> np.ndarray:
        """Min over active slots and chords of distance minus slot radius (mm), per configuration (N,).

        slots: (K * 5,) the same packed slots for every configuration, or (N, K * 5) slots per configuration
        (`crtraj.world.packing` layout). No active slot: +inf.
        """
        X = self._configs(X)
        S = np.ascontiguousarray(slots, dtype=float)
        per = S.ndim == 2
        if (per and S.shape[0] != len(X)) or S.shape[-1] % packing.WIDTH or S.ndim not in (1, 2):
            raise ValueError(f"slots: expected (K*{packing.WIDTH},) or ({len(X)}, K*{packing.WIDTH}), got {S.shape}")
        K = S.shape[-1] // packing.WIDTH
        out = np.empty(len(X))
        stride = packing.WIDTH * K if per else 0
        self._check(self._clearance(len(X), _ptr(X), K, _ptr(S), stride, _ptr(out)), "clearance")
        return out

    def clearance_windows(self, X: Any, table: Any, origin: float, lo: Any, hi: Any) -> np.ndarray:
        """Min over obstacles and chords of distance minus radius (mm) per configuration (N,), each against
        the spheres that contain the obstacles of `table` (`Scene.motion_table`, (M, 12)) over its own window
        [lo[i], hi[i]] (s, relative to the scene's time origin `origin` s): `clearance` with the slots of
        `Scene.swept_spheres`, computed in C. No obstacle: +inf."""
        X = self._configs(X)
        N = len(X)
        T = np.ascontiguousarray(table, dtype=float)
        if T.ndim != 2 or T.shape[1] != 12:
            raise ValueError(f"clearance_windows: an obstacle table (M, 12) expected, got {T.shape}")
        lo = per_item(lo, N)
        hi = per_item(hi, N)
        out = np.empty(N)
        args = (N, _ptr(X), len(T), _ptr(T), float(origin), _ptr(lo), _ptr(hi))
        self._check(self._clearance_windows(*args, _ptr(out)), "clearance")
        return out

    def tip_jacobian(self, X: Any) -> tuple[np.ndarray, np.ndarray]:
        """Tip positions (N, 3) mm and Jacobians d tip / d x (N, 3, nx) of configurations X (N, nx)."""
        X = self._configs(X)
        P = np.empty((len(X), 3))
        Jt = np.empty((len(X), self.nx, 3))  # CasADi's column-major 3 x nx is a C-ordered (nx, 3)
        self._check(self._tip_jac(len(X), _ptr(X), _ptr(P), _ptr(Jt)), "tip Jacobian")
        # contiguous (N, 3, nx), as the interpreted path returns it: numpy's batched products round
        # differently on strided views, and both paths must give the same plans bit for bit
        return P, np.ascontiguousarray(np.swapaxes(Jt, 1, 2))

    def check_edges(
        self,
        XA: np.ndarray,
        dX: np.ndarray,
        bound: np.ndarray,
        n0: np.ndarray | float,
        slots: np.ndarray,
        inflate: float,
        finest: float,
        prefix: bool,
        broad: int = 0,
        first: bool = False,
        verdict: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, int] | None:
        """The static-scene adaptive edge check (`MotionValidator.check_edges`) in C.

        XA, dX (E, nx): motion starts and changes; bound (E,) mm: their body-motion bounds; n0: (E,) first
        intervals per motion, or a number, coarse (mm of body motion per first interval): then each motion's
        max(1, ceil(bound / coarse)) first intervals are counted in C, as `MotionValidator.check_edges` counts
        them (less Python per call; None, with nothing checked, when a bound is not finite); slots: the scene's
        packed obstacles; inflate (mm) subtracted from every clearance; finest (mm): the smallest interval's h.
        broad: with at least this many obstacle slots (0: never), a broad phase per motion keeps only the
        obstacles that can decide one of its samples (module docstring): fail is the same either way; lower
        stays a lower bound of the clearance but may be smaller. first: stop after the first motion certified
        whole; the motions after it are not checked (fail -1, lower -inf). verdict (with prefix False): a
        motion stops at its first unsafe interval, so fail < 1 marks it unsafe without being its first unsafe
        fraction (and lower is not the whole motion's); safe motions are checked exactly as without it.
        Returns (fail (E,), lower (E,) mm, samples).
        """
        S, p_slots = self._slots
        if slots is not S:  # the same scene's slots come back call after call: their address is kept
            S = np.ascontiguousarray(slots, dtype=float)
            if S.ndim != 1:
                raise ValueError(f"check_edges: flat slots (K*{packing.WIDTH},) expected, got {S.shape}")
            p_slots = _ptr(S)
            if S is slots:
                self._slots = (S, p_slots)
        K = S.shape[0] // packing.WIDTH
        flags = (float(inflate), float(finest), _mode(prefix, first, verdict), int(broad))
        if np.ndim(n0) == 0:
            return self._run_auto(self._check_static, XA, dX, bound, float(n0), (K, p_slots), flags)
        return self._run_edges(self._check_edges, XA, dX, bound, n0, (K, p_slots, *flags))

    def check_edges_moving(
        self,
        XA: np.ndarray,
        dX: np.ndarray,
        bound: np.ndarray,
        coarse: float,
        TA: np.ndarray,
        dT: np.ndarray,
        table: np.ndarray,
        origin: float,
        limits: tuple[float, float, float, float],
        prefix: bool,
        broad: int = 0,
        first: bool = False,
        verdict: bool = False,
    ) -> tuple[np.ndarray, np.ndarray, int] | None:
        """`check_edges` (first intervals counted in C) among moving obstacles: TA, dT (E,) s: each motion's
        start time and duration (relative to the scene's time origin `origin` s); table (M, 12):
        `Scene.motion_table`; limits = (inflate mm, finest mm, enlargement mm/s: how fast a window's swept sphere
        can outgrow any one instant's, time_resolution s: the longest window an uncertified interval may be
        declared unsafe at without being split). None, with nothing checked, when a bound, start time or
        duration is not finite."""
        E = len(XA)
        TA = per_item(TA, E)
        dT = per_item(dT, E)
        T, p_table = self._table
        if table is not T:
            T = np.ascontiguousarray(table, dtype=float)
            if T.ndim != 2 or T.shape[1] != 12:
                raise ValueError(f"check_edges_moving: an obstacle table (M, 12) expected, got {T.shape}")
            p_table = _ptr(T)
            if T is table:
                self._table = (T, p_table)
        middle = (_ptr(TA), _ptr(dT), len(T), p_table, float(origin))
        flags = (*(float(x) for x in limits), _mode(prefix, first, verdict), int(broad))
        return self._run_auto(self._check_moving_auto, XA, dX, bound, coarse, middle, flags)

    def _run_auto(
        self, fn: Any, XA: Any, dX: Any, bound: Any, coarse: float, middle: tuple[Any, ...], flags: tuple[Any, ...]
    ) -> tuple[np.ndarray, np.ndarray, int] | None:
        """Call a C edge check that counts first intervals itself: (E, XA, dX, bound, coarse, *middle, *flags,
        fail, lower, &samples); None when it found a value not finite (code 3)."""
        XA = self._configs(XA)
        dX = self._configs(dX)
        E = len(XA)
        bound = np.ascontiguousarray(bound, dtype=float)
        if dX.shape != XA.shape or bound.shape != (E,):
            raise ValueError("check_edges: XA, dX (E, nx) and bound (E,) expected")
        out = np.empty(2 * E)  # fail, then lower
        samples = np.zeros(1, dtype=np.int64)
        p = _ptr(out)
        rc = fn(E, _ptr(XA), _ptr(dX), _ptr(bound), float(coarse), *middle, *flags, p, p + 8 * E, _ptr(samples))
        if rc == 3:
            return None
        self._check(rc, "edge check")
        return out[:E], out[E:], int(samples[0])

    def _run_edges(
        self, fn: Any, XA: Any, dX: Any, bound: Any, n0: Any, middle: tuple[Any, ...]
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """Call a C edge check: (E, XA, dX, bound, n0, *middle, fail, lower, &samples), inputs checked."""
        XA = self._configs(XA)
        dX = self._configs(dX)
        E = len(XA)
        bound = np.ascontiguousarray(bound, dtype=float)
        n0 = np.ascontiguousarray(n0, dtype=np.int64)
        if dX.shape != XA.shape or bound.shape != (E,) or n0.shape != (E,):
            raise ValueError("check_edges: XA, dX (E, nx), bound and n0 (E,) expected")
        fail, lower = np.empty(E), np.empty(E)
        samples = ctypes.c_longlong(0)
        head = (E, _ptr(XA), _ptr(dX), _ptr(bound), _ptr(n0))
        rc = fn(*head, *middle, _ptr(fail), _ptr(lower), ctypes.addressof(samples))
        self._check(rc, "edge check")
        return fail, lower, int(samples.value)

    def path_clearance(
        self,
        X: Any,
        T: Any,
        bound: Any,
        resolution: float,
        obstacles: tuple[np.ndarray | None, np.ndarray | None, float],
        inflate: float,
        enlargement: float,
    ) -> tuple[np.ndarray, int] | None:
        """`MotionValidator.path_clearance`'s per-motion minima (K - 1,) mm of the path X (K, nx) timed T (K,) s,
        sampled every `resolution` mm of body motion (bound: the motions' body-motion bounds (K - 1,) mm), with
        the exact broad phase of the C function (the same minima). obstacles: (static slots, None, 0) or (None,
        `Scene.motion_table`, the scene's time origin s); enlargement (mm/s): how fast an obstacle's clearance
        can change. Returns (minima, samples), or None when a value is not finite (nothing computed)."""
        X = self._configs(X)
        T = np.ascontiguousarray(T, dtype=float)
        bound = np.ascontiguousarray(bound, dtype=float)
        K = len(X)
        if T.shape != (K,) or bound.shape != (max(K - 1, 0),):
            raise ValueError("path_clearance: X (K, nx), T (K,) and bound (K-1,) expected")
        S, table, origin = obstacles
        if table is not None:
            A = np.ascontiguousarray(table, dtype=float)
            M, pS, pT = len(A), 0, _ptr(A)
        else:
            A = np.ascontiguousarray(S, dtype=float)
            M, pS, pT = len(A) // packing.WIDTH, _ptr(A), 0
        out = np.empty(max(K - 1, 0))
        samples = np.zeros(1, dtype=np.int64)
        args = (K, _ptr(X), _ptr(T), _ptr(bound), float(resolution), M, pS, pT, float(origin), float(inflate))
        rc = self._path_clearance(*args, float(enlargement), _ptr(out) if len(out) else 0, _ptr(samples))
        if rc == 3:
            return None
        self._check(rc, "path clearance")
        return out, int(samples[0])

    def bspline(self, knots: np.ndarray, coeffs: np.ndarray, k: int, x: Any) -> np.ndarray:
        """The B-spline curve of degree k with these knots (nc + k + 1,) and coefficients (nc, dim) at the
        parameters x (N,): `crtraj.core.splines.BSplineCurve` (already checked there) evaluated in C, the same
        numbers. Returns (N, dim)."""
        tk = np.ascontiguousarray(knots, dtype=float)
        C = np.ascontiguousarray(coeffs, dtype=float)
        x = np.ascontiguousarray(x, dtype=float)
        if C.ndim != 2 or x.ndim != 1 or tk.shape != (len(C) + k + 1,):
            raise ValueError(f"bspline: knots (nc+k+1,), coefficients (nc, dim), x (N,) expected, got {C.shape}")
        out = np.empty((len(x), C.shape[1]))
        rc = self._bspline(len(x), _ptr(x), len(tk), _ptr(tk), len(C), C.shape[1], _ptr(C), int(k), _ptr(out))
        self._check(rc, "B-spline")
        return out

    def phase_law(self, cap: Any, num: Any, den: Any, ds: Any) -> tuple[np.ndarray, np.ndarray]:
        """The retiming's phase-plane pass (`crtraj.planning.retime._phase_pass`) and the law's knot times in one C
        call, the same numbers: cap (n,) speed caps on (ds/dt)^2; num, den (n - 1, m): the interval bounds
        x_next <= (x + num) / den; ds (n - 1,) mm: the grid's spacings. Returns (ds/dt (n,) mm/s, times (n,) s)."""
        cap = np.ascontiguousarray(cap, dtype=float)
        num = np.ascontiguousarray(num, dtype=float)
        den = np.ascontiguousarray(den, dtype=float)
        ds = np.ascontiguousarray(ds, dtype=float)
        n = len(cap)
        if n < 2 or num.ndim != 2 or num.shape != den.shape or num.shape[0] != n - 1 or ds.shape != (n - 1,):
            raise ValueError(f"phase_law: cap (n,), num and den (n-1, m), ds (n-1,) expected, got {num.shape}")
        sd, T = np.empty(n), np.empty(n)
        rc = self._phase_law(n, num.shape[1], _ptr(cap), _ptr(num), _ptr(den), _ptr(ds), _ptr(sd), _ptr(T))
        self._check(rc, "phase law")
        return sd, T

    def natural_slopes(self, t: Any, Y: Any) -> np.ndarray:
        """Slopes (n, d) of the natural cubic spline through Y (n, d) at strictly increasing t (n,), n >= 3:
        `crtraj.core.splines.natural_cubic`'s, the same numbers."""
        t = np.ascontiguousarray(t, dtype=float)
        Y = np.ascontiguousarray(Y, dtype=float)
        if t.ndim != 1 or len(t) < 3 or Y.ndim != 2 or len(Y) != len(t):
            raise ValueError(f"natural_slopes: t (n,) with n >= 3 and Y (n, d) expected, got {Y.shape}")
        out = np.empty_like(Y)
        self._check(self._natural_slopes(len(t), Y.shape[1], _ptr(t), _ptr(Y), _ptr(out)), "natural cubic")
        return out

    def hermite(self, t: np.ndarray, Y: np.ndarray, S: np.ndarray, x: Any, nu: int = 0) -> np.ndarray:
        """The nu-th derivative (nu 0-2) at x (N,) of the cubic through Y (n, d) with slopes S (n, d) at the knots t
        (n,), contiguous float64 arrays: `crtraj.core.splines.HermiteCubic`'s, the same numbers. Returns (N, d)."""
        x = np.ascontiguousarray(x, dtype=float)
        out = np.empty((len(x), Y.shape[1]))
        rc = self._hermite(len(t), Y.shape[1], _ptr(t), _ptr(Y), _ptr(S), len(x), _ptr(x), int(nu), _ptr(out))
        self._check(rc, "cubic")
        return out

    def verify_motion(
        self, X: Any, T: Any, after: tuple[float, float] | None, obstacles: tuple[Any, Any, float], inflate: float
    ) -> float | None:
        """The smallest held clearance (mm) of the sampled motion X (n, nx) at times T (n,) s, each sample over the
        window between its neighbours' times with half its motions' larger body-motion bound as margin, and the
        last one held over `after` (s) too (`MotionValidator.held_clearance`); obstacles: (static slots, None, 0)
        or (None, `Scene.motion_table`, time origin s). None when a time is not finite (nothing computed)."""
        X = self._configs(X)
        T = np.ascontiguousarray(T, dtype=float)
        if T.shape != (len(X),) or not len(X):
            raise ValueError("verify_motion: X (n, nx) and T (n,) with n >= 1 expected")
        S, table, origin = obstacles
        A = np.ascontiguousarray(S if table is None else table, dtype=float)
        M = len(A) // packing.WIDTH if table is None else len(A)
        pS, pT = (_ptr(A), 0) if table is None else (0, _ptr(A))
        lo, hi = (0.0, 0.0) if after is None else (float(after[0]), float(after[1]))
        out = np.empty(1)
        rc = self._verify_motion(len(X), _ptr(X), _ptr(T), after is not None, lo, hi, M, pS, pT, float(origin),
                                 float(inflate), _ptr(out))  # fmt: skip
        if rc == 3:
            return None
        self._check(rc, "motion verification")
        return float(out[0])

    def motion_bound(self, dX: Any) -> np.ndarray:
        """Body-motion bound (N,) mm of configuration changes dX (N, nx)."""
        dX = self._configs(dX)
        out = np.empty(len(dX))
        self._check(self._motion_bound(len(dX), _ptr(dX), _ptr(out)), "motion bound")
        return out

    def project(
        self, X: Any, target: Any, iterations: int, limits: ProjectionLimits, steps: ProjectionSteps
    ) -> tuple[np.ndarray, np.ndarray]:
        """Damped least-squares projection of configurations X (N, nx) onto tip = target (3,) mm, at most
        `iterations` steps each, every configuration stopping once its tip error is below `steps.tol` mm.
        Returns (new configurations (N, nx), tip errors (N,) mm)."""
        X = self._configs(X).copy()
        tgt = np.ascontiguousarray(target, dtype=float)
        err = np.full(len(X), np.inf)
        lim, st = limits, steps
        rc = self._project(
            len(X), _ptr(X), _ptr(tgt), int(iterations), _ptr(st.w_inv), st.damping, st.step, st.tol,
            len(lim.tmax), _ptr(lim.coupling), _ptr(lim.coupling_inv), _ptr(lim.tmax), lim.z_range[0],
            lim.z_range[1], _ptr(err),
        )  # fmt: skip
        self._check(rc, "IK projection")
        return X, err


@dataclass(frozen=True)
class ProjectionLimits:
    """The limits `ValidityKernel.project` projects into: coupling matrix and its inverse (2 n_seg square),
    the bending-disc radii tmax (n_seg,) rad and the z stroke (mm); contiguous float64 arrays."""

    coupling: np.ndarray
    coupling_inv: np.ndarray
    tmax: np.ndarray
    z_range: tuple[float, float]

    @classmethod
    def of(cls, robot: Any) -> ProjectionLimits:
        C = np.ascontiguousarray(robot.coupling_matrix(), dtype=float)
        tmax = np.ascontiguousarray([s.theta_max for s in robot.segments], dtype=float)
        z = (float(robot.z_range[0]), float(robot.z_range[1]))
        return cls(C, np.ascontiguousarray(np.linalg.inv(C)), tmax, z)


@dataclass(frozen=True)
class ProjectionSteps:
    """The Newton steps of `ValidityKernel.project`: W^-1 (nx, nx) of the body metric W = M^T M, the damping,
    the largest tip error removed per step (mm) and the tip tolerance (mm) a configuration stops at."""

    w_inv: np.ndarray
    damping: float
    step: float
    tol: float
