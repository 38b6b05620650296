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
- ``crtraj_motion_bound(N, dX, B)``: the body-motion bound B(dx) (mm, `crtraj.planning.metric`; it agrees
  with numpy's to 1e-12, but the planners keep numpy's, whose rounding times every motion, so that both
  paths give identical plans);
- ``crtraj_check_edges(...)``: the adaptive certification of straight motions of
  `crtraj.planning.validity.MotionValidator.check_edges` for a static scene, the whole refinement loop
  in C with numpy's arithmetic, operation for operation (so it returns the same numbers);
- ``crtraj_check_edges_moving(...)``: the same among moving, breathing obstacles: every interval is
  checked against the spheres that contain each obstacle over its time window (`Scene.swept_spheres`,
  computed in C from `Scene.motion_table` with numpy's arithmetic: libm's sin, the same operation order,
  no contraction into fused multiply-adds), so it too returns the numpy loop's numbers bit for bit.

The library is built once per robot (its kinematic description), check-point count and generator
version through `crtraj.core.build_cache.BuildCache` and called with ctypes on numpy buffers
(`benchmarks/plan.py`, section 5, measures it against ``casadi.external``). Without a C compiler
`ValidityKernel.load` returns None and the callers keep the interpreted path.
"""

from __future__ import annotations

import ctypes
import hashlib
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache, BuildKey
from crtraj.model.codegen import codegen_builder
from crtraj.model.kinematics import Model
from crtraj.planning.metric import metric_matrix
from crtraj.world import packing

# Version of the generated code and driver: raising it makes every cached kernel foreign (rebuilt).
GENERATOR = 6
# Most check points a kernel is generated for: the generated FK grows with them (100 points: ~15 s of
# gcc); denser checks (reports, tests) stay on the interpreted path.
MAX_COMPILED_POINTS = 200
# Largest batch one driver call takes; callers split larger ones (bounds the driver's int arithmetic).
MAX_BATCH = 1 << 24

# The driver: loops in C over configurations (and obstacle slots) around the CasADi-generated functions,
# which each evaluate one configuration. Work arrays are sized once per call from the *_work functions.
_DRIVER = r"""
#include <stdlib.h>
#include <math.h>

typedef struct { casadi_int sz_arg, sz_res, sz_iw, sz_w; const casadi_real** arg; casadi_real** res;
                 casadi_int* iw; casadi_real* w; } crtraj_work;

static int crtraj_alloc(crtraj_work* k, int (*work)(casadi_int*, casadi_int*, casadi_int*, casadi_int*)) {
  work(&k->sz_arg, &k->sz_res, &k->sz_iw, &k->sz_w);
  k->arg = (const casadi_real**) malloc(sizeof(casadi_real*) * (k->sz_arg + 1));
  k->res = (casadi_real**) malloc(sizeof(casadi_real*) * (k->sz_res + 1));
  k->iw = (casadi_int*) malloc(sizeof(casadi_int) * (k->sz_iw + 1));
  k->w = (casadi_real*) malloc(sizeof(casadi_real) * (k->sz_w + 1));
  return (k->arg && k->res && k->iw && k->w) ? 0 : 1;
}

static void crtraj_free(crtraj_work* k) { free(k->arg); free(k->res); free(k->iw); free(k->w); }

int crtraj_points(long long N, const double* X, double* P) {
  crtraj_work k; long long i; int rc = 0;
  if (crtraj_alloc(&k, crtraj_bb_work)) { crtraj_free(&k); return 1; }
  for (i = 0; i < N && !rc; ++i) {
    k.arg[0] = X + i * CRTRAJ_NX; k.res[0] = P + i * 3 * CRTRAJ_NP;
    rc = crtraj_bb(k.arg, k.res, k.iw, k.w, 0);
  }
  crtraj_free(&k);
  return rc;
}

/* Smallest distance from c to the chord segments between consecutive points of P (3 x CRTRAJ_NP, column-major),
   in the operation order of the interpreted CasADi expression (state_validity); sqrt is monotone, so the
   square root of the smallest square is the smallest distance, bit for bit. */
static double crtraj_chord(const double* P, const double* c) {
  double best = INFINITY;
  int i;
  for (i = 0; i < CRTRAJ_NP - 1; ++i) {
    const double* a = P + 3 * i;
    const double* b = a + 3;
    double abx = b[0] - a[0], aby = b[1] - a[1], abz = b[2] - a[2];
    double acx = c[0] - a[0], acy = c[1] - a[1], acz = c[2] - a[2];
    double den = fmax(abx * abx + aby * aby + abz * abz, 1e-300);
    double u = fmin(fmax((acx * abx + acy * aby + acz * abz) / den, 0.0), 1.0);
    double dx = acx - abx * u, dy = acy - aby * u, dz = acz - abz * u;
    double d2 = dx * dx + dy * dy + dz * dz;
    if (d2 < best || d2 != d2) best = d2;  /* a NaN point makes the distance NaN: never "far away" */
    if (best != best) break;
  }
  return sqrt(best);
}

/* Clearance of one configuration x against K slots (padding skipped); P: room for its points. */
static int crtraj_clear_one(crtraj_work* kb, const double* x, long long K, const double* s, double* P, double* out) {
  long long j;
  double best = INFINITY;
  int rc;
  kb->arg[0] = x; kb->res[0] = P;
  rc = crtraj_bb(kb->arg, kb->res, kb->iw, kb->w, 0);
  for (j = 0; j < K; ++j) {
    const double* slot = s + 5 * j;
    double dist;
    if (slot[4] <= 0.0) continue;  /* padding */
    dist = crtraj_chord(P, slot) - slot[3];
    if (dist < best || dist != dist) best = dist;  /* NaN propagates: unknown is not clear */
    if (best != best) break;
  }
  *out = best;
  return rc;
}

int crtraj_clearance(long long N, const double* X, long long K, const double* S, long long stride, double* d) {
  crtraj_work kb; long long i; int rc = 0;
  double P[3 * CRTRAJ_NP];
  if (crtraj_alloc(&kb, crtraj_bb_work)) { crtraj_free(&kb); return 1; }
  for (i = 0; i < N && !rc; ++i) rc = crtraj_clear_one(&kb, X + i * CRTRAJ_NX, K, S + i * stride, P, d + i);
  crtraj_free(&kb);
  return rc;
}

/* Grow the five interval buffers to hold at least `need` entries each (contents kept). */
static int crtraj_grow(double** buf, long long* cap, long long need) {
  int i;
  if (need <= *cap) return 0;
  *cap = 2 * need + 64;
  for (i = 0; i < 5; ++i) {
    double* p = (double*) realloc(buf[i], sizeof(double) * (size_t) *cap);
    if (!p) return 1;
    buf[i] = p;
  }
  return 0;
}

/* numpy's sin_range (crtraj.world.obstacle), operation for operation: exact (min, max) of sin over [a, b]. */
static void crtraj_sin_range(double a, double b, double* lo, double* hi) {
  const double pi = 3.141592653589793, two_pi = 2.0 * 3.141592653589793, half_pi = 3.141592653589793 / 2;
  double lo_t = a < b ? a : b, hi_t = a < b ? b : a;
  double sa = sin(lo_t), sb = sin(hi_t);
  double crest = half_pi + two_pi * ceil((lo_t - half_pi) / two_pi);
  double trough = -pi / 2 + two_pi * ceil((lo_t + half_pi) / two_pi);
  *lo = sa < sb ? sa : sb;
  *hi = sa < sb ? sb : sa;
  if (crest <= hi_t) *hi = 1.0;
  if (trough <= hi_t) *lo = -1.0;
}

static double crtraj_clip01(double x) { return fmin(fmax(x, 0.0), 1.0); }

/* Scene.swept_spheres for the window [lo, hi] (s, before the scene's time origin is added) as packed slots:
   one row of obstacle table T (M x 12: c0 3, d 3, duration, profile code, A, B, w, phase) per obstacle. */
static void crtraj_swept(long long M, const double* T, double origin, double lo, double hi, double* S) {
  const double pi = 3.141592653589793;
  long long j;
  int k;
  double tt0 = lo + origin, tt1 = hi + origin;
  double pa = tt0 < tt1 ? tt0 : tt1, pb = tt0 < tt1 ? tt1 : tt0;
  for (j = 0; j < M; ++j) {
    const double* o = T + 12 * j;
    double dur = o[6], code = o[7], A = o[8], B = o[9], w = o[10], ph = o[11];
    double slo, shi, clo, chi, rlo, rhi, smin, smax, a[3], b[3], d[3];
    crtraj_sin_range(0.5 * pi * pa / dur, 0.5 * pi * pb / dur, &slo, &shi);
    crtraj_sin_range(pi * pa / dur + pi / 2, pi * pb / dur + pi / 2, &clo, &chi);
    if (code == 0.0) { smin = crtraj_clip01(pa / dur); smax = crtraj_clip01(pb / dur); }
    else if (code == 1.0) { smin = slo; smax = shi; }
    else { smin = 0.5 * (1.0 - chi); smax = 0.5 * (1.0 - clo); }
    crtraj_sin_range(w * tt0 + ph, w * tt1 + ph, &rlo, &rhi);
    for (k = 0; k < 3; ++k) {
      a[k] = o[k] + smin * o[3 + k];
      b[k] = o[k] + smax * o[3 + k];
      d[k] = b[k] - a[k];
      S[5 * j + k] = 0.5 * (a[k] + b[k]);
    }
    S[5 * j + 3] = (A + (B * rlo < B * rhi ? B * rhi : B * rlo)) + 0.5 * sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    S[5 * j + 4] = 1.0;
  }
}

/* Clearance of each configuration X[i] over its own time window [lo[i], hi[i]] (s, before the scene's time
   origin is added): against the spheres containing each of the M obstacles of table T over that window
   (crtraj_swept, as Scene.swept_spheres), so no window's spheres are computed outside. */
int crtraj_clearance_windows(long long N, const double* X, long long M, const double* T, double origin,
                             const double* lo, const double* hi, double* d) {
  crtraj_work kb; long long i; int rc = 0;
  double P[3 * CRTRAJ_NP];
  double* S = (double*) malloc(sizeof(double) * 5 * (size_t) (M > 0 ? M : 1));
  if (!S) return 1;
  if (crtraj_alloc(&kb, crtraj_bb_work)) { crtraj_free(&kb); free(S); return 1; }
  for (i = 0; i < N && !rc; ++i) {
    crtraj_swept(M, T, origin, lo[i], hi[i], S);
    rc = crtraj_clear_one(&kb, X + i * CRTRAJ_NX, M, S, P, d + i);
  }
  crtraj_free(&kb);
  free(S);
  return rc;
}

/* The adaptive edge check of MotionValidator.check_edges, edge by edge and level by level (breadth first, as
   the numpy loop refines), with the same arithmetic. Each edge e starts from n0[e] intervals; an interval
   [ta, tb] gets the clearance c (minus `inflate`) of its middle configuration over its time window
   [TA + ta dT, TA + tb dT]: against the K slots S (a static scene: T NULL, TA and dT unused) or against the
   spheres containing each of the K obstacles of table T over the window (crtraj_swept). It is certified when
   c >= h = 0.5 B (tb - ta); unsafe when c + enl dt < 0 (colliding at every instant of the window,
   dt = dT (tb - ta)) or when c < 0 or h <= finest, with dt <= tres; else halved (prefix: only while ta < fail;
   else only while nothing failed). A static scene has enl = 0 and tres = inf: unsafe when c < 0 or h <= finest.
   Out: fail[e] (certified fraction) and lower[e] (min c - h over certified intervals); *samples: clearances. */
#define ta buf[0]
#define tb buf[1]
#define mid buf[2]
#define ua buf[3]
#define ub buf[4]
static int crtraj_refine(long long E, const double* XA, const double* dX, const double* bound, const long long* n0,
                         const double* TA, const double* dT, long long K, const double* S, const double* T,
                         double origin, double inflate, double finest, double enl, double tres, int prefix,
                         double* fail, double* lower, long long* samples) {
  crtraj_work kb; long long e, i, n, cap = 0; int rc = 0;
  double P[3 * CRTRAJ_NP], x[CRTRAJ_NX];
  double* buf[5] = {NULL, NULL, NULL, NULL, NULL};  /* ta, tb, mid, ua, ub */
  double* swept = T ? (double*) malloc(sizeof(double) * (size_t) (5 * K + 1)) : NULL;
  double* t;
  *samples = 0;
  if ((T && !swept) || crtraj_alloc(&kb, crtraj_bb_work)) { free(swept); crtraj_free(&kb); return 1; }
  for (e = 0; e < E && !rc; ++e) {
    const double* xa = XA + e * CRTRAJ_NX;
    const double* dx = dX + e * CRTRAJ_NX;
    double f = 1.0, low = INFINITY, t0 = T ? TA[e] : 0.0, span = T ? dT[e] : 0.0;
    n = n0[e];
    if (n < 1) { fail[e] = 0.0; lower[e] = -INFINITY; continue; }  /* no intervals: nothing certified */
    if (crtraj_grow(buf, &cap, 2 * n)) { rc = 1; break; }
    for (i = 0; i < n; ++i) { ta[i] = (double) i / (double) n; tb[i] = (double) (i + 1) / (double) n; }
    while (n > 0 && !rc) {
      long long m = 0;
      if (crtraj_grow(buf, &cap, 2 * n)) { rc = 1; break; }  /* room for this level's children */
      /* the whole level first: the split rule sees this level's failures, as the numpy loop does */
      for (i = 0; i < n && !rc; ++i) {
        double tm = 0.5 * (ta[i] + tb[i]);
        double h = 0.5 * bound[e] * (tb[i] - ta[i]);
        double dt = span * (tb[i] - ta[i]);
        double c;
        int j;
        for (j = 0; j < CRTRAJ_NX; ++j) x[j] = xa[j] + tm * dx[j];
        if (T) crtraj_swept(K, T, origin, t0 + ta[i] * span, t0 + tb[i] * span, swept);
        rc = crtraj_clear_one(&kb, x, K, T ? swept : S, P, &c);
        c = c - inflate - 0.0;
        ++*samples;
        mid[i] = -1.0;
        if (c >= h) { if (c - h < low) low = c - h; }
        else if (c + enl * dt < 0.0 || ((c < 0.0 || h <= finest) && dt <= tres)) { if (ta[i] < f) f = ta[i]; }
        else mid[i] = tm;  /* neither certified nor unsafe: split */
      }
      for (i = 0; i < n; ++i) {
        if (mid[i] < 0.0 || (prefix ? !(ta[i] < f) : !(f >= 1.0))) continue;
        ua[m] = ta[i]; ub[m] = mid[i]; ++m;
        ua[m] = mid[i]; ub[m] = tb[i]; ++m;
      }
      t = ta; ta = ua; ua = t;
      t = tb; tb = ub; ub = t;
      n = m;
    }
    fail[e] = f; lower[e] = low;
  }
  for (i = 0; i < 5; ++i) free(buf[i]);
  free(swept);
  crtraj_free(&kb);
  return rc;
}
#undef ta
#undef tb
#undef mid
#undef ua
#undef ub

/* A static scene: every interval against the same K slots S. */
int crtraj_check_edges(long long E, const double* XA, const double* dX, const double* bound, const long long* n0,
                       long long K, const double* S, double inflate, double finest, int prefix,
                       double* fail, double* lower, long long* samples) {
  return crtraj_refine(E, XA, dX, bound, n0, NULL, NULL, K, S, NULL, 0.0, inflate, finest, 0.0, INFINITY, prefix,
                       fail, lower, samples);
}

/* Moving, breathing obstacles (table T, M rows): every interval against the spheres of its time window. */
int crtraj_check_edges_moving(long long E, const double* XA, const double* dX, const double* bound,
                              const long long* n0, const double* TA, const double* dT, long long M,
                              const double* T, double origin, double inflate, double finest, double enl,
                              double tres, int prefix, double* fail, double* lower, long long* samples) {
  return crtraj_refine(E, XA, dX, bound, n0, TA, dT, M, NULL, T, origin, inflate, finest, enl, tres, prefix,
                       fail, lower, samples);
}

int crtraj_tip_jac(long long N, const double* X, double* P, double* J) {
  crtraj_work k; long long i; int rc = 0;
  if (crtraj_alloc(&k, crtraj_tipjac_work)) { crtraj_free(&k); return 1; }
  for (i = 0; i < N && !rc; ++i) {
    k.arg[0] = X + i * CRTRAJ_NX; k.res[0] = P + 3 * i; k.res[1] = J + 3 * CRTRAJ_NX * i;
    rc = crtraj_tipjac(k.arg, k.res, k.iw, k.w, 0);
  }
  crtraj_free(&k);
  return rc;
}

int crtraj_motion_bound(long long N, const double* dX, double* B) {
  crtraj_work k; long long i; int rc = 0;
  if (crtraj_alloc(&k, crtraj_mb_work)) { crtraj_free(&k); return 1; }
  for (i = 0; i < N && !rc; ++i) {
    k.arg[0] = dX + i * CRTRAJ_NX; k.res[0] = B + i;
    rc = crtraj_mb(k.arg, k.res, k.iw, k.w, 0);
  }
  crtraj_free(&k);
  return rc;
}
"""


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
    driver = hashlib.sha256(_DRIVER.encode("utf-8")).hexdigest()
    spec = {"robot": robot, "check_points": int(check_points), "generator": GENERATOR, "driver": driver}
    return BuildKey("crtraj_validity", spec)


def kernel_functions(model: Model, check_points: int) -> list[ca.Function]:
    """The CasADi functions the kernel library is generated from (one configuration each)."""
    robot = model.robot
    metric = metric_matrix(robot)
    x = ca.SX.sym("x", robot.nx)
    bb = model.backbone_function(check_points)
    return [
        ca.Function("crtraj_bb", [x], [bb(x)]),
        ca.Function("crtraj_tipjac", [x], [model.tip(x), model.jac_tip(x)]),
        ca.Function("crtraj_mb", [x], [motion_bound_expr(x, metric, robot.n_segments)]),
    ]


_P = ctypes.c_void_p
_N = ctypes.c_longlong


class ValidityKernel:
    """A loaded kernel library for one robot and check-point count (see the module docstring).

    Built by `load`; the methods take and return numpy arrays (mm, rad). One kernel may be shared by
    threads: the driver keeps no state between calls.
    """

    def __init__(self, library: Path, nx: int, check_points: int) -> None:
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
        self._motion_bound.argtypes = [_N, _P, _P]
        self._check_edges = lib.crtraj_check_edges
        self._check_edges.argtypes = [_N, _P, _P, _P, _P, _N, _P, ctypes.c_double, ctypes.c_double, ctypes.c_int]
        self._check_edges.argtypes += [_P, _P, _P]
        self._check_moving = lib.crtraj_check_edges_moving
        self._check_moving.argtypes = [_N, _P, _P, _P, _P, _P, _P, _N, _P] + [ctypes.c_double] * 5
        self._check_moving.argtypes += [ctypes.c_int, _P, _P, _P]
        for f in (
            self._points,
            self._clearance,
            self._clearance_windows,
            self._tip_jac,
            self._motion_bound,
            self._check_edges,
            self._check_moving,
        ):
            f.restype = ctypes.c_int

    @classmethod
    def load(cls, model: Model, check_points: int, cache: BuildCache) -> ValidityKernel | None:
        """The kernel of `model` at `check_points`, from `cache` (built on a miss); None without a C compiler."""
        key = kernel_key(model, check_points)
        defines = f"\n#define CRTRAJ_NX {model.robot.nx}\n#define CRTRAJ_NP {int(check_points)}\n"
        build = codegen_builder(lambda: kernel_functions(model, check_points), key.name, defines + _DRIVER)
        return cache.load(key, build, lambda lib: cls(lib, model.robot.nx, check_points))

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
        self._check(self._points(len(X), X.ctypes.data, out.ctypes.data), "backbone points")
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
        self._check(self._clearance(len(X), X.ctypes.data, K, S.ctypes.data, stride, out.ctypes.data), "clearance")
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
        lo = np.ascontiguousarray(np.broadcast_to(lo, (N,)), dtype=float)
        hi = np.ascontiguousarray(np.broadcast_to(hi, (N,)), dtype=float)
        out = np.empty(N)
        args = (N, X.ctypes.data, len(T), T.ctypes.data, float(origin), lo.ctypes.data, hi.ctypes.data)
        self._check(self._clearance_windows(*args, out.ctypes.data), "clearance")
        return out

    def tip_jacobian(self, X: Any) -> tuple[np.ndarray, np.ndarray]:
        """Tip positions (N, 3) mm and Jacobians d tip / d x (N, 3, nx) of configurations X (N, nx)."""
        X = self._configs(X)
        P = np.empty((len(X), 3))
        Jt = np.empty((len(X), self.nx, 3))  # CasADi's column-major 3 x nx is a C-ordered (nx, 3)
        self._check(self._tip_jac(len(X), X.ctypes.data, P.ctypes.data, Jt.ctypes.data), "tip Jacobian")
        # contiguous (N, 3, nx), as the interpreted path returns it: numpy's batched products round
        # differently on strided views, and both paths must give the same plans bit for bit
        return P, np.ascontiguousarray(np.swapaxes(Jt, 1, 2))

    def check_edges(
        self,
        XA: np.ndarray,
        dX: np.ndarray,
        bound: np.ndarray,
        n0: np.ndarray,
        slots: np.ndarray,
        inflate: float,
        finest: float,
        prefix: bool,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """The static-scene adaptive edge check (`MotionValidator.check_edges`) in C.

        XA, dX (E, nx): motion starts and changes; bound (E,) mm: their body-motion bounds; n0 (E,): first
        intervals per motion; slots: the scene's packed obstacles; inflate (mm) subtracted from every
        clearance; finest (mm): the smallest interval's h. Returns (fail (E,), lower (E,) mm, samples).
        """
        S = np.ascontiguousarray(slots, dtype=float)
        if S.ndim != 1:
            raise ValueError(f"check_edges: flat slots (K*{packing.WIDTH},) expected, got {S.shape}")
        K = S.shape[0] // packing.WIDTH
        flags = (float(inflate), float(finest), int(bool(prefix)))
        return self._run_edges(self._check_edges, XA, dX, bound, n0, (K, S.ctypes.data, *flags))

    def check_edges_moving(
        self,
        XA: np.ndarray,
        dX: np.ndarray,
        bound: np.ndarray,
        n0: np.ndarray,
        TA: np.ndarray,
        dT: np.ndarray,
        table: np.ndarray,
        origin: float,
        inflate: float,
        finest: float,
        enlargement: float,
        time_resolution: float,
        prefix: bool,
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """The adaptive edge check among moving obstacles (`MotionValidator.check_edges`) in C.

        As `check_edges`, and: TA, dT (E,) s: each motion's start time and duration (relative to the
        scene's time origin `origin` s); table (M, 12): `Scene.motion_table`; enlargement (mm/s): how fast
        a window's swept sphere can outgrow any one instant's; time_resolution (s): the longest window an
        uncertified interval may be declared unsafe at without being split.
        """
        E = len(XA)
        TA = np.ascontiguousarray(np.broadcast_to(TA, (E,)), dtype=float)
        dT = np.ascontiguousarray(np.broadcast_to(dT, (E,)), dtype=float)
        T = np.ascontiguousarray(table, dtype=float)
        if T.ndim != 2 or T.shape[1] != 12:
            raise ValueError(f"check_edges_moving: an obstacle table (M, 12) expected, got {T.shape}")
        scalars = (float(origin), float(inflate), float(finest), float(enlargement), float(time_resolution))
        middle = (TA.ctypes.data, dT.ctypes.data, len(T), T.ctypes.data, *scalars, int(bool(prefix)))
        return self._run_edges(self._check_moving, XA, dX, bound, n0, middle)

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
        head = (E, XA.ctypes.data, dX.ctypes.data, bound.ctypes.data, n0.ctypes.data)
        rc = fn(*head, *middle, fail.ctypes.data, lower.ctypes.data, ctypes.addressof(samples))
        self._check(rc, "edge check")
        return fail, lower, int(samples.value)

    def motion_bound(self, dX: Any) -> np.ndarray:
        """Body-motion bound (N,) mm of configuration changes dX (N, nx)."""
        dX = self._configs(dX)
        out = np.empty(len(dX))
        self._check(self._motion_bound(len(dX), dX.ctypes.data, out.ctypes.data), "motion bound")
        return out
