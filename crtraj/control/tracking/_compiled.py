"""The tracking simulation of one control step in C (what `crtraj.control.loop.ClosedLoop._track` does in numpy).

Every replanning step simulates the tracking controller (`TrackingController.step`, configuration mode) and
the first-order servos (`ServoModel`) over the step's control periods, toward the straight move x0 -> x1, and
samples the actual motion densely for the verification (each period's samples no further apart than half the
check resolution, by the body-motion bound `BodyMetric.motion_bound`). In numpy that is about 70 us a period of
small-vector overhead; this routine does the same arithmetic in one C call. It is plain C with the sizes and
matrices passed at run time (no generated code), built once into the build cache (`crtraj.core.build_cache`,
keyed by its source) and loaded through ctypes. Results agree with the numpy path to rounding (sums of products
in another order; `tests/test_compiled_tracking.py`), not bit for bit. Units: mm, rad, s.
"""

from __future__ import annotations

import ctypes
import hashlib
from pathlib import Path

import numpy as np

from crtraj.control.tracking._controller import TrackingController
from crtraj.core.build_cache import BuildCache, BuildKey, compile_shared

# The most samples one step may produce (periods x samples per period): a larger request is refused (the
# caller falls back to numpy), so the C never writes past its buffers.
MAX_SAMPLES = 200_000

_SOURCE = r"""
#include <math.h>

/* y = A x with A (r x c) row-major */
static void mv(long long r, long long c, const double* A, const double* x, double* y) {
  long long i, j;
  for (i = 0; i < r; ++i) {
    double s = 0.0;
    for (j = 0; j < c; ++j) s += A[i * c + j] * x[j];
    y[i] = s;
  }
}

/* x = Binv (q - q0) */
static void config(long long nx, long long nq, const double* q0, const double* Binv, const double* q,
                   double* dq, double* x) {
  long long k;
  for (k = 0; k < nq; ++k) dq[k] = q[k] - q0[k];
  mv(nx, nq, Binv, dq, x);
}

/* Body-motion bound of dx: sum over segments of |(M dx) block| plus |dz| (BodyMetric.motion_bound). */
static double bound(long long nx, long long ns, const double* M, const double* dx, double* dy) {
  long long k;
  double b = 0.0;
  mv(nx, nx, M, dx, dy);
  for (k = 0; k < ns; ++k) b += sqrt(dy[2 * k] * dy[2 * k] + dy[2 * k + 1] * dy[2 * k + 1]);
  return b + fabs(dy[nx - 1]);
}

/* dims: nx, nq, m (rate-limited actuators, 0: none), ng (linear limit rows), ns (segments).
   P: q0 (nq), Binv (nx x nq), Jq (nq x nx), Kx (nx x nx), Kc (nx x nx), lead (nx), rate_room (nq),
      decay (nq), tau (nq), Jr (m x nx), vroom (m), aroom (m), amax (m), G (ng x nx), hv (ng),
      C (ns x 2 x nx), tmax2 (ns), M (nx x nx), zlo, zhi.
   n periods of h s (a step of dt s) from time t; x0, x1 (nx) the step's straight reference; q, qc (nq)
   actual and commanded actuators and inc (nx) the last increment, updated in place. cmds (n x nq) the
   set-points; T, X (cap, cap x nx) the samples (the first is the state at t); *count their number. Returns 0,
   or 2 when the samples would not fit (nothing is trusted then). work: room for 12 nx + 4 nq + 4 m + 2 ng
   doubles. */
int crtraj_track(const long long* dims, const double* P, long long n, double h, double dt, double t,
                 double resolution,
                 const double* x0, const double* x1, double* q, double* qc, double* inc, long long cap,
                 double* cmds, double* T, double* X, long long* count, double* work) {
  const long long nx = dims[0], nq = dims[1], m = dims[2], ng = dims[3], ns = dims[4];
  const double *q0 = P, *Binv = q0 + nq, *Jq = Binv + nx * nq, *Kx = Jq + nq * nx, *Kc = Kx + nx * nx;
  const double *lead = Kc + nx * nx, *rroom = lead + nx, *decay = rroom + nq, *tau = decay + nq;
  const double *Jr = tau + nq, *vroom = Jr + m * nx, *aroom = vroom + m, *amax = aroom + m;
  const double *G = amax + m, *hv = G + ng * nx, *C = hv + ng, *tmax2 = C + ns * 2 * nx, *M = tmax2 + ns;
  const double zlo = M[nx * nx], zhi = M[nx * nx + 1];
  double *xm = work, *xc = xm + nx, *e = xc + nx, *ec = e + nx, *ff = ec + nx, *v = ff + nx, *vb = v + nx;
  double *tmp = vb + nx, *tmp2 = tmp + nx, *xe = tmp2 + nx, *dx = xe + nx, *dy = dx + nx;
  double *dq = dy + nx, *qcmd = dq + nq, *qend = qcmd + nq, *qs = qend + nq;
  double *sr = qs + nq, *rr = sr + m, *fr = rr + m, *cr = fr + m, *g0 = cr + m, *gv = g0 + ng;
  long long j, i, k, s, c = 0;

  config(nx, nq, q0, Binv, q, dq, xm);
  if (cap < 1) return 2;
  T[0] = t;
  for (i = 0; i < nx; ++i) X[i] = xm[i];
  c = 1;
  for (j = 0; j < n; ++j) {
    double worst = 0.0, alpha = 1.0, frac = (double) (j + 1) / (double) n, span;
    long long nsm;
    config(nx, nq, q0, Binv, q, dq, xm);
    config(nx, nq, q0, Binv, qc, dq, xc);
    for (i = 0; i < nx; ++i) {
      double xr = x0[i] + frac * (x1[i] - x0[i]);
      e[i] = xr - xm[i];
      ec[i] = e[i] + xm[i] - xc[i];
      ff[i] = (x1[i] - x0[i]) / dt * h;
      ec[i] = ec[i] + lead[i] * ff[i];
    }
    mv(nx, nx, Kx, e, tmp);
    mv(nx, nx, Kc, ec, tmp2);
    for (i = 0; i < nx; ++i) v[i] = tmp[i] + tmp2[i] + ff[i];
    /* rate limits: one scale for the whole increment */
    mv(nq, nx, Jq, v, dq);
    for (k = 0; k < nq; ++k) { double o = fabs(dq[k]) / rroom[k]; if (o > worst) worst = o; }
    if (m) {
      mv(m, nx, Jr, v, sr);
      for (k = 0; k < m; ++k) { double o = fabs(sr[k]) / vroom[k]; if (o > worst) worst = o; }
    }
    if (worst > 1.0) for (i = 0; i < nx; ++i) v[i] = v[i] * (1.0 / worst);
    if (m) {
      /* braking: no actuator closes on its target faster than it can still stop there */
      double wb = 0.0;
      int any = 0;
      mv(m, nx, Jr, v, sr);
      mv(m, nx, Jr, ec, rr);
      mv(m, nx, Jr, ff, fr);
      for (k = 0; k < m; ++k) {
        if (sr[k] * rr[k] > 0.0) {
          double cap_k = fabs(fr[k]) + sqrt(2.0 * amax[k] * fabs(rr[k])) * h + aroom[k];
          double o = fabs(sr[k]) / cap_k;
          if (!any || o > wb) wb = o;
          any = 1;
        }
      }
      if (any && wb > 1.0) for (i = 0; i < nx; ++i) v[i] = v[i] / wb;
      /* acceleration limits: move from the last increment toward v only as far as they allow */
      for (i = 0; i < nx; ++i) tmp[i] = v[i] - inc[i];
      mv(m, nx, Jr, tmp, cr);
      wb = 0.0;
      for (k = 0; k < m; ++k) { double o = fabs(cr[k]) / aroom[k]; if (k == 0 || o > wb) wb = o; }
      if (wb > 1.0) { double sc = 1.0 / wb; for (i = 0; i < nx; ++i) v[i] = inc[i] + sc * (v[i] - inc[i]); }
    }
    /* actuation limits (TrackingController._limit): z clipped alone, the bending scaled by one factor */
    {
      double z0 = xc[nx - 1], z1 = z0 + v[nx - 1];
      double lo_ = zlo < z0 ? zlo : z0, hi_ = zhi > z0 ? zhi : z0;
      double zn = z1 < lo_ ? lo_ : z1;
      zn = zn > hi_ ? hi_ : zn;
      if (zn != z1) v[nx - 1] = zn - z0;
      for (i = 0; i < nx; ++i) vb[i] = v[i];
      vb[nx - 1] = 0.0;
      mv(ng, nx, G, xc, g0);
      mv(ng, nx, G, vb, gv);
      for (k = 0; k < ng; ++k) {
        if (gv[k] > 0.0) {
          double g = g0[k] - hv[k], room = g <= 0.0 ? -g : 0.0, r = room / gv[k];
          if (r < alpha) alpha = r;
        }
      }
      for (k = 0; k < ns; ++k) {
        const double* Ck = C + k * 2 * nx;
        double a0, a1, b0, b1, a, b, cc, reach;
        mv(2, nx, Ck, vb, tmp);
        a0 = tmp[0]; a1 = tmp[1];
        mv(2, nx, Ck, xc, tmp);
        b0 = tmp[0]; b1 = tmp[1];
        a = a0 * a0 + a1 * a1;
        if (a == 0.0) continue;
        b = a0 * b0 + a1 * b1;
        cc = b0 * b0 + b1 * b1 - tmax2[k];
        if (cc <= 0.0) reach = (-b + sqrt(b * b - a * cc)) / a;
        else { reach = -2.0 * b / a; if (reach < 0.0) reach = 0.0; }
        if (reach < alpha) alpha = reach;
      }
      if (alpha < 0.0) alpha = 0.0;
      if (alpha < 1.0) for (i = 0; i < nx - 1; ++i) v[i] *= alpha;
    }
    mv(nq, nx, Jq, v, dq);
    for (k = 0; k < nq; ++k) {
      qcmd[k] = qc[k] + dq[k];
      qend[k] = qcmd[k] + decay[k] * (q[k] - qcmd[k]);
    }
    config(nx, nq, q0, Binv, qend, dq, xe);
    for (i = 0; i < nx; ++i) dx[i] = xe[i] - xm[i];
    span = bound(nx, ns, M, dx, dy);
    nsm = (long long) ceil(2.0 * span / resolution);
    if (nsm < 1) nsm = 1;
    if (c + nsm > cap) return 2;
    for (s = 1; s <= nsm; ++s) {
      double ts = h * (double) s / (double) nsm;
      for (k = 0; k < nq; ++k) qs[k] = qcmd[k] + exp(-ts / tau[k]) * (q[k] - qcmd[k]);
      T[c] = t + (double) j * h + ts;
      config(nx, nq, q0, Binv, qs, dq, X + c * nx);
      ++c;
    }
    for (k = 0; k < nq; ++k) { q[k] = qend[k]; qc[k] = qcmd[k]; cmds[j * nq + k] = qcmd[k]; }
    for (i = 0; i < nx; ++i) inc[i] = v[i];
  }
  *count = c;
  return 0;
}
"""

_P = ctypes.c_void_p
_N = ctypes.c_longlong
_D = ctypes.c_double


def tracking_key() -> BuildKey:
    """The cache key of the tracking library: its source's SHA-256 (it has no other inputs)."""
    return BuildKey("crtraj_tracking", {"source_sha256": hashlib.sha256(_SOURCE.encode("utf-8")).hexdigest()})


def _build(folder: Path, compiler: str) -> Path:
    src = folder / "crtraj_tracking.c"
    src.write_text(_SOURCE, encoding="utf-8")
    return compile_shared(compiler, [src], folder / "libcrtraj_tracking.so")


class CompiledTracking:
    """One control step's tracking simulation in C for one controller, servo model and body metric.

    ctl: the loop's `TrackingController` (configuration mode). h: the control period (s). metric_matrix:
    `BodyMetric.metric_matrix` (nx, nx). Use `load` (None without a C compiler or in tip mode), then `step`.
    """

    def __init__(self, library: Path, ctl: TrackingController, h: float, metric_matrix: np.ndarray) -> None:
        lib = ctypes.CDLL(str(library))
        self._fn = lib.crtraj_track
        self._fn.restype = ctypes.c_int
        self._fn.argtypes = [_P, _P, _N, _D, _D, _D, _D, _P, _P, _P, _P, _P, _N, _P, _P, _P, _P, _P]
        self.h = float(h)
        nx, nq = ctl.nx, ctl.nq
        k = ctl.step_constants(self.h)
        order = ("q0", "Binv", "J_q", "Kx", "Kc", "lead", "rate_room", "decay", "tau", "jacobian", "vmax_room")
        order += ("amax_room", "amax", "G", "h", "C", "tmax2")
        parts = [k[name] for name in order] + [metric_matrix, k["z_range"]]
        self._P = np.ascontiguousarray(np.concatenate([np.ravel(np.asarray(a, dtype=float)) for a in parts]))
        m, ng = len(k["amax"]), len(k["h"])
        self._dims = np.array([nx, nq, m, ng, ctl.robot.n_segments], dtype=np.int64)
        self.nx, self.nq = nx, nq
        self._work = np.zeros(12 * nx + 4 * nq + 4 * m + 2 * ng + 8)
        # the addresses of the arrays kept for the object's life, taken once (each `.ctypes.data` costs about 1 us)
        self._dims_ptr, self._P_ptr, self._work_ptr = (
            self._dims.ctypes.data,
            self._P.ctypes.data,
            self._work.ctypes.data,
        )

    @classmethod
    def load(
        cls, ctl: TrackingController, h: float, metric_matrix: np.ndarray, cache: BuildCache
    ) -> CompiledTracking | None:
        """The compiled tracking step of `ctl` for period h (s), from `cache` (built on a miss); None without a
        C compiler, or when the controller works in tip mode (its tip Jacobian is not in this routine)."""
        if ctl.options.mode != "configuration":
            return None
        lib = cache.library(tracking_key(), _build)
        return None if lib is None else cls(lib, ctl, h, metric_matrix)

    def step(
        self,
        q: np.ndarray,
        qc: np.ndarray,
        x0: np.ndarray,
        x1: np.ndarray,
        t: float,
        inc: np.ndarray,
        n: int,
        dt: float,
        resolution: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """n periods (of a step of dt s) toward the straight move x0 -> x1 from time t (s), from actual and
        commanded actuators q, qc (nq, mm) and the last increment inc (nx): (q at the end, set-point at the end,
        sample times (S,), sample configurations (S, nx), set-points (n, nq)), as `_track` returns them; None
        when the samples would exceed `MAX_SAMPLES` (the caller simulates in numpy)."""
        x0 = np.ascontiguousarray(x0, dtype=float)
        x1 = np.ascontiguousarray(x1, dtype=float)
        # samples: 1 + per period ceil(2 span / resolution), unknown before the call; one retry with the most
        # the routine may write when the first guess is short
        for cap in (1 + n * 64, MAX_SAMPLES):
            T = np.empty(cap)
            X = np.empty((cap, self.nx))
            cmds = np.empty((n, self.nq))
            count = ctypes.c_longlong(0)
            # fresh copies each try (the routine writes them; a retry starts from the caller's state again)
            qq, qqc, ii = np.array(q, dtype=float), np.array(qc, dtype=float), np.array(inc, dtype=float)
            rc = self._fn(
                self._dims_ptr,
                self._P_ptr,
                int(n),
                self.h,
                float(dt),
                float(t),
                float(resolution),
                x0.ctypes.data,
                x1.ctypes.data,
                qq.ctypes.data,
                qqc.ctypes.data,
                ii.ctypes.data,
                cap,
                cmds.ctypes.data,
                T.ctypes.data,
                X.ctypes.data,
                ctypes.addressof(count),
                self._work_ptr,
            )
            if rc == 0:
                c = int(count.value)
                return qq, qqc, T[:c], X[:c], cmds
            if rc != 2:
                raise RuntimeError(f"compiled tracking step failed (code {rc})")
        return None
