"""The C driver of the compiled validity kernel (`crtraj.planning.compiled_validity`): loops over batches of
configurations, obstacle slots and edge intervals around the CasADi-generated functions, the swept spheres of
moving obstacles and the edge checks' broad phase. Kept apart from the Python loader only for its length."""

# The driver: loops in C over configurations (and obstacle slots) around the CasADi-generated functions,
# which each evaluate one configuration. Work arrays are sized once per call from the *_work functions.
DRIVER = r"""
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

/* The broad phase of one edge x(s) = xa + s dx, s in [0, 1], over the time window [t0, t0 + span]: the clearance
   d_j (minus `inflate`) of every obstacle j at the edge's start xa, against its sphere over the whole window (its
   fixed slot in a static scene). No body point moves more than B = bound along the edge, and every interval's
   window sphere lies inside the whole window's (the capsule of a sub-window is part of the window's, on the same
   line), so d_j - B bounds obstacle j's clearance at every sample of the edge from below. An obstacle whose bound
   is at least the first level's largest h (plus slack for rounding) can never be the one that decides a sample
   (c >= h certifies it whichever obstacle is nearest), so it is dropped from the narrow phase; the smallest
   dropped bound is returned in *floor (every sample's clearance is taken as at most it, keeping `lower` a lower
   bound). The kept slots (static) or table rows (moving) are copied to `kept`, their count to *Ke. NaN keeps. */
static int crtraj_broad(crtraj_work* kb, const double* xa, double B, long long n, long long K, const double* S,
                        const double* T, double origin, double t0, double span, double inflate, double* P,
                        double* swept, double* kept, long long* Ke, double* floor) {
  long long j, m = 0;
  int k, rc, w = T ? 12 : 5;
  const double* s = S;
  double thr = 0.5 * B / (double) n * (1.0 + 1e-9) + 1e-6;
  kb->arg[0] = xa; kb->res[0] = P;
  rc = crtraj_bb(kb->arg, kb->res, kb->iw, kb->w, 0);
  if (T) { crtraj_swept(K, T, origin, t0, t0 + span, swept); s = swept; }
  *floor = INFINITY;
  for (j = 0; j < K; ++j) {
    const double* slot = s + 5 * j;
    const double* row = (T ? T + 12 * j : S + 5 * j);
    double lb;
    if (slot[4] <= 0.0) continue;  /* padding */
    lb = crtraj_chord(P, slot) - slot[3] - inflate - B - 1e-6;
    if (!rc && lb >= thr) { if (lb < *floor) *floor = lb; continue; }
    for (k = 0; k < w; ++k) kept[w * m + k] = row[k];
    ++m;
  }
  *Ke = m;
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
                         long long broad, double* fail, double* lower, long long* samples) {
  crtraj_work kb; long long e, i, n, cap = 0; int rc = 0;
  double P[3 * CRTRAJ_NP], x[CRTRAJ_NX];
  double* buf[5] = {NULL, NULL, NULL, NULL, NULL};  /* ta, tb, mid, ua, ub */
  double* swept = T ? (double*) malloc(sizeof(double) * (size_t) (5 * K + 1)) : NULL;
  /* the broad phase's kept obstacles of one edge: slots (static) or table rows (moving) */
  double* kept = (double*) malloc(sizeof(double) * (size_t) ((T ? 12 : 5) * K + 1));
  double* t;
  *samples = 0;
  if ((T && !swept) || !kept || crtraj_alloc(&kb, crtraj_bb_work)) {
    free(swept); free(kept); crtraj_free(&kb); return 1;
  }
  for (e = 0; e < E && !rc; ++e) {
    const double* xa = XA + e * CRTRAJ_NX;
    const double* dx = dX + e * CRTRAJ_NX;
    double f = 1.0, low = INFINITY, t0 = T ? TA[e] : 0.0, span = T ? dT[e] : 0.0, floor = INFINITY;
    long long Ke = K;
    const double* Se = S;
    const double* Te = T;
    n = n0[e];
    if (n < 1) { fail[e] = 0.0; lower[e] = -INFINITY; continue; }  /* no intervals: nothing certified */
    if (broad > 0 && K >= broad) {
      rc = crtraj_broad(&kb, xa, bound[e], n, K, S, T, origin, t0, span, inflate, P, swept, kept, &Ke, &floor);
      if (T) Te = kept; else Se = kept;
    }
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
        if (T) crtraj_swept(Ke, Te, origin, t0 + ta[i] * span, t0 + tb[i] * span, swept);
        rc = crtraj_clear_one(&kb, x, Ke, T ? swept : Se, P, &c);
        c = c - inflate - 0.0;
        if (floor < c) c = floor;  /* the obstacles the broad phase dropped are at least this far */
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
  free(kept);
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
                       long long K, const double* S, double inflate, double finest, int prefix, long long broad,
                       double* fail, double* lower, long long* samples) {
  return crtraj_refine(E, XA, dX, bound, n0, NULL, NULL, K, S, NULL, 0.0, inflate, finest, 0.0, INFINITY, prefix,
                       broad, fail, lower, samples);
}

/* Moving, breathing obstacles (table T, M rows): every interval against the spheres of its time window. */
int crtraj_check_edges_moving(long long E, const double* XA, const double* dX, const double* bound,
                              const long long* n0, const double* TA, const double* dT, long long M,
                              const double* T, double origin, double inflate, double finest, double enl,
                              double tres, int prefix, long long broad, double* fail, double* lower,
                              long long* samples) {
  return crtraj_refine(E, XA, dX, bound, n0, TA, dT, M, NULL, T, origin, inflate, finest, enl, tres, prefix,
                       broad, fail, lower, samples);
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
