"""The C driver of the compiled validity kernel (`crtraj.planning.validity._compiled`): loops over batches of
configurations, obstacle slots and edge intervals around the CasADi-generated functions, the swept spheres of
moving obstacles and the edge checks' broad phase. Kept apart from the Python loader only for its length."""

# From this many obstacles on, the edge checks' broad phase also runs once before a motion's first level (one more
# sample per motion of two or more first intervals; below it that sample costs more than it saves).
EDGE_BROAD = 12

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
  const double* AB = P + 3 * CRTRAJ_NP;  /* crtraj_prep's chord vectors and squared lengths */
  const double* DEN = P + 6 * CRTRAJ_NP;
  double best = INFINITY;
  int i;
  for (i = 0; i < CRTRAJ_NP - 1; ++i) {
    const double* a = P + 3 * i;
    double abx = AB[3 * i], aby = AB[3 * i + 1], abz = AB[3 * i + 2];
    double acx = c[0] - a[0], acy = c[1] - a[1], acz = c[2] - a[2];
    double den = DEN[i];
    double u = fmin(fmax((acx * abx + acy * aby + acz * abz) / den, 0.0), 1.0);
    double dx = acx - abx * u, dy = acy - aby * u, dz = acz - abz * u;
    double d2 = dx * dx + dy * dy + dz * dz;
    if (d2 < best || d2 != d2) best = d2;  /* a NaN point makes the distance NaN: never "far away" */
    if (best != best) break;
  }
  return sqrt(best);
}

/* The chords of the points P (3 x CRTRAJ_NP) that crtraj_chord needs for every obstacle, computed once per
   configuration (the same operations, so the same numbers): after the points, the chord vectors b - a
   (3 x (CRTRAJ_NP - 1)), then their squared lengths (at least 1e-300). P holds 7 CRTRAJ_NP doubles. */
static void crtraj_prep(double* P) {
  double* AB = P + 3 * CRTRAJ_NP;
  double* DEN = P + 6 * CRTRAJ_NP;
  int i;
  for (i = 0; i < CRTRAJ_NP - 1; ++i) {
    const double* a = P + 3 * i;
    const double* b = a + 3;
    double abx = b[0] - a[0], aby = b[1] - a[1], abz = b[2] - a[2];
    AB[3 * i] = abx; AB[3 * i + 1] = aby; AB[3 * i + 2] = abz;
    DEN[i] = fmax(abx * abx + aby * aby + abz * abz, 1e-300);
  }
}

/* Clearance of one configuration x against K slots (padding skipped); P: room for its points and chords
   (7 CRTRAJ_NP doubles, crtraj_prep). */
static int crtraj_clear_one(crtraj_work* kb, const double* x, long long K, const double* s, double* P, double* out) {
  long long j;
  double best = INFINITY;
  int rc;
  kb->arg[0] = x; kb->res[0] = P;
  rc = crtraj_bb(kb->arg, kb->res, kb->iw, kb->w, 0);
  crtraj_prep(P);
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
  double P[7 * CRTRAJ_NP];
  if (crtraj_alloc(&kb, crtraj_bb_work)) { crtraj_free(&kb); return 1; }
  for (i = 0; i < N && !rc; ++i) rc = crtraj_clear_one(&kb, X + i * CRTRAJ_NX, K, S + i * stride, P, d + i);
  crtraj_free(&kb);
  return rc;
}

/* From this many obstacles on, a broad phase also runs before a motion's first level (when it has several
   intervals): one more configuration against every obstacle, so that the first level's intervals check only the
   obstacles that can decide them. */
#define CRTRAJ_EDGE_BROAD @EDGE_BROAD@

/* Grow the NB interval buffers to hold at least `need` entries each (contents kept). */
#define CRTRAJ_NB 14
static int crtraj_grow(double** buf, long long* cap, long long need) {
  int i;
  if (need <= *cap) return 0;
  *cap = 2 * need + 64;
  for (i = 0; i < CRTRAJ_NB; ++i) {
    double* p = (double*) realloc(buf[i], sizeof(double) * (size_t) *cap);
    if (!p) return 1;
    buf[i] = p;
  }
  return 0;
}

/* Grow an obstacle-index pool to at least `need` entries (contents kept). */
static int crtraj_grow_pool(long long** pool, long long* cap, long long need) {
  long long* p;
  if (need <= *cap) return 0;
  *cap = 2 * need + 64;
  p = (long long*) realloc(*pool, sizeof(long long) * (size_t) *cap);
  if (!p) return 1;
  *pool = p;
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
    double slo, shi, clo, chi, rlo = 0.0, rhi = 0.0, smin, smax, a[3], b[3], d[3];
    /* only the sine ranges the profile uses are computed (the others' values are never read); without
       breathing (B = 0) the radius term B * sin is +-0 for any finite sine, and A + (+-0) is A */
    if (code == 0.0) { smin = crtraj_clip01(pa / dur); smax = crtraj_clip01(pb / dur); }
    else if (code == 1.0) {
      crtraj_sin_range(0.5 * pi * pa / dur, 0.5 * pi * pb / dur, &slo, &shi);
      smin = slo; smax = shi;
    } else {
      crtraj_sin_range(pi * pa / dur + pi / 2, pi * pb / dur + pi / 2, &clo, &chi);
      smin = 0.5 * (1.0 - chi); smax = 0.5 * (1.0 - clo);
    }
    if (B != 0.0) crtraj_sin_range(w * tt0 + ph, w * tt1 + ph, &rlo, &rhi);
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
  double P[7 * CRTRAJ_NP];
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

/* Clearance of configuration x against the m obstacles idx[0..m) (padding skipped), as crtraj_clear_one
   computes it over all of them, and each one's own distance minus radius in d[0..m) (the obstacles after a
   NaN: NaN). A static scene: slots S; moving obstacles: the sphere of table T's row over [lo, hi] (one
   row of crtraj_swept, into sw). */
static int crtraj_clear_idx(crtraj_work* kb, const double* x, const long long* idx, long long m, const double* S,
                            const double* T, double origin, double lo, double hi, double* P, double* sw, double* d,
                            double* out) {
  long long q;
  double best = INFINITY;
  int rc;
  kb->arg[0] = x; kb->res[0] = P;
  rc = crtraj_bb(kb->arg, kb->res, kb->iw, kb->w, 0);
  crtraj_prep(P);
  for (q = 0; q < m; ++q) {
    const double* slot;
    if (best != best) { d[q] = NAN; continue; }
    if (T) { crtraj_swept(1, T + 12 * idx[q], origin, lo, hi, sw); slot = sw; }
    else slot = S + 5 * idx[q];
    if (slot[4] <= 0.0) { d[q] = INFINITY; continue; }  /* padding */
    d[q] = crtraj_chord(P, slot) - slot[3];
    if (d[q] < best || d[q] != d[q]) best = d[q];  /* NaN propagates: unknown is not clear */
  }
  *out = best;
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
   Out: fail[e] (certified fraction) and lower[e] (min c - h over certified intervals); *samples: clearances.
   prefix bit 1 (first): stop after the first motion certified whole (VAMP's early exit across a batch whose
   caller wants the first valid motion of an order): the motions after it get fail = -1 (not checked).
   prefix bit 2 (verdict, with bit 0 clear): a motion stops at its first unsafe interval, within its level too
   (early exit within a motion): fail < 1 still marks it unsafe, but need not be the fraction the whole level
   would give, and lower may be larger; a safe motion is checked exactly as without the bit.

   Broad phase (from `broad` obstacles on, 0: never): every interval hands its halves only the obstacles that
   can decide one of their samples. The halves' configurations lie within h (body motion) of the interval's
   middle one and their windows within its window (so their spheres within its sphere: a sub-window's capsule
   is part of the window's, on the same line), so obstacle j's clearance anywhere below is at least
   d_j - h; when that exceeds every half's h (h / 2, plus slack for rounding), j cannot decide a sample
   (c >= h certifies it whichever obstacle is nearest) and is dropped. The smallest dropped bound is the
   halves' floor: their clearance is taken as at most it, so `lower` stays a lower bound; fail is unchanged.
   With CRTRAJ_EDGE_BROAD obstacles or more and at least two first intervals, the same rule runs once before the
   first level, from the motion's middle configuration over its whole window (one more sample). */
#define ta buf[0]
#define tb buf[1]
#define mid buf[2]
#define ua buf[3]
#define ub buf[4]
#define flo buf[5]   /* per interval: floor of its dropped obstacles (mm) */
#define off buf[6]   /* per interval: its obstacle list in `pool` (offset, count) */
#define cnt buf[7]
#define uflo buf[8]  /* the next level's floors and lists */
#define uoff buf[9]
#define ucnt buf[10]
#define cflo buf[11] /* per interval of this level: the floor and list its halves would get */
#define coff buf[12]
#define ccnt buf[13]
static int crtraj_refine(long long E, const double* XA, const double* dX, const double* bound, const long long* n0,
                         double coarse, const double* TA, const double* dT, long long K, const double* S,
                         const double* T, double origin, double inflate, double finest, double enl, double tres,
                         int prefix, long long broad, double* fail, double* lower, long long* samples) {
  crtraj_work kb; long long e, i, q, n, cap = 0, pcap = 0, ncap = 0; int rc = 0;
  double P[7 * CRTRAJ_NP], x[CRTRAJ_NX], sw[5];
  double* buf[CRTRAJ_NB] = {NULL};
  double* d = (double*) malloc(sizeof(double) * (size_t) (K + 1));
  long long* pool = NULL;
  long long* npool = NULL;
  long long* lp;
  double* t;
  int use = broad > 0 && K >= broad;
  int first = prefix & 2;
  int verdict = (prefix & 4) && !(prefix & 1);
  prefix &= 1;
  *samples = 0;
  if (!d || crtraj_alloc(&kb, crtraj_bb_work) || crtraj_grow_pool(&pool, &pcap, K + 1)) {
    free(d); free(pool); crtraj_free(&kb); return 1;
  }
  for (e = 0; e < E && !rc; ++e) {
    const double* xa = XA + e * CRTRAJ_NX;
    const double* dx = dX + e * CRTRAJ_NX;
    double f = 1.0, low = INFINITY, t0 = T ? TA[e] : 0.0, span = T ? dT[e] : 0.0;
    /* n0 NULL: max(1, ceil(bound / coarse)) intervals, as numpy computes them (bounds checked finite) */
    n = n0 ? n0[e] : (long long) fmax(1.0, ceil(bound[e] / coarse));
    if (n < 1) { fail[e] = 0.0; lower[e] = -INFINITY; continue; }  /* no intervals: nothing certified */
    if (crtraj_grow(buf, &cap, 2 * n)) { rc = 1; break; }
    if (crtraj_grow_pool(&pool, &pcap, K + 1)) { rc = 1; break; }
    for (q = 0; q < K; ++q) pool[q] = q;  /* the first level: every obstacle */
    {
      double floor0 = INFINITY;
      long long kept = K;
      if (use && n >= 2 && K >= CRTRAJ_EDGE_BROAD) {
        /* the first level's broad phase: the middle configuration over the whole window. Every first-level
           middle lies within bound / 2 (body motion) of it and its window within the whole one, so obstacle
           q's clearance there is at least d_q - bound / 2; beyond every first-level h it decides no sample */
        double hmax = 0.5 * bound[e] / (double) n * (1.0 + 1e-6) + 1e-6, c0;
        int j;
        for (j = 0; j < CRTRAJ_NX; ++j) x[j] = xa[j] + 0.5 * dx[j];
        rc = crtraj_clear_idx(&kb, x, pool, K, S, T, origin, t0, t0 + span, P, sw, d, &c0);
        ++*samples;
        kept = 0;
        for (q = 0; q < K; ++q) {
          double lb = d[q] - inflate - 0.5 * bound[e] - 1e-6;
          if (lb >= hmax) { if (lb < floor0) floor0 = lb; }
          else pool[kept++] = q;  /* NaN keeps */
        }
      }
      for (i = 0; i < n; ++i) {
        ta[i] = (double) i / (double) n; tb[i] = (double) (i + 1) / (double) n;
        flo[i] = floor0; off[i] = 0.0; cnt[i] = (double) kept;
      }
    }
    while (n > 0 && !rc) {
      long long m = 0, np = 0, nd = n;
      if (crtraj_grow(buf, &cap, 2 * n)) { rc = 1; break; }  /* room for this level's children */
      /* the whole level first: the split rule sees this level's failures, as the numpy loop does */
      for (i = 0; i < n && !rc; ++i) {
        double tm = 0.5 * (ta[i] + tb[i]);
        double h = 0.5 * bound[e] * (tb[i] - ta[i]);
        double dt = span * (tb[i] - ta[i]);
        double c;
        const long long* lst = pool + (long long) off[i];
        long long ml = (long long) cnt[i];
        int j;
        for (j = 0; j < CRTRAJ_NX; ++j) x[j] = xa[j] + tm * dx[j];
        rc = crtraj_clear_idx(&kb, x, lst, ml, S, T, origin, t0 + ta[i] * span, t0 + tb[i] * span, P, sw, d, &c);
        c = c - inflate - 0.0;
        if (flo[i] < c) c = flo[i];  /* the obstacles dropped above are at least this far */
        ++*samples;
        mid[i] = -1.0;
        if (c >= h) { if (c - h < low) low = c - h; }
        else if (c + enl * dt < 0.0 || ((c < 0.0 || h <= finest) && dt <= tres)) {
          if (ta[i] < f) f = ta[i];
          if (verdict) { nd = i + 1; break; }  /* unsafe: the rest of the motion cannot change that */
        }
        else mid[i] = tm;  /* neither certified nor unsafe: split */
        if (mid[i] < 0.0) continue;
        cflo[i] = flo[i]; coff[i] = off[i]; ccnt[i] = cnt[i];  /* without the broad phase: the same list */
        if (use) {
          double thr = 0.5 * h * (1.0 + 1e-9) + 1e-6;
          if (crtraj_grow_pool(&npool, &ncap, np + ml + 1)) { rc = 1; break; }
          coff[i] = (double) np;
          for (q = 0; q < ml; ++q) {
            double lb = d[q] - inflate - h - 1e-6;
            if (lb >= thr) { if (lb < cflo[i]) cflo[i] = lb; }
            else npool[np++] = lst[q];  /* NaN keeps */
          }
          ccnt[i] = (double) np - coff[i];
        }
      }
      for (i = 0; i < nd; ++i) {
        if (mid[i] < 0.0 || (prefix ? !(ta[i] < f) : !(f >= 1.0))) continue;
        ua[m] = ta[i]; ub[m] = mid[i]; uflo[m] = cflo[i]; uoff[m] = coff[i]; ucnt[m] = ccnt[i]; ++m;
        ua[m] = mid[i]; ub[m] = tb[i]; uflo[m] = cflo[i]; uoff[m] = coff[i]; ucnt[m] = ccnt[i]; ++m;
      }
      t = ta; ta = ua; ua = t;
      t = tb; tb = ub; ub = t;
      t = flo; flo = uflo; uflo = t;
      t = off; off = uoff; uoff = t;
      t = cnt; cnt = ucnt; ucnt = t;
      if (use) { lp = pool; pool = npool; npool = lp; q = pcap; pcap = ncap; ncap = q; }
      n = m;
    }
    fail[e] = f; lower[e] = low;
    if (first && f >= 1.0 && !rc) {
      for (i = e + 1; i < E; ++i) { fail[i] = -1.0; lower[i] = -INFINITY; }
      break;
    }
  }
  for (i = 0; i < CRTRAJ_NB; ++i) free(buf[i]);
  free(d); free(pool); free(npool);
  crtraj_free(&kb);
  return rc;
}
#undef ta
#undef tb
#undef mid
#undef ua
#undef ub
#undef flo
#undef off
#undef cnt
#undef uflo
#undef uoff
#undef ucnt
#undef cflo
#undef coff
#undef ccnt

/* A static scene: every interval against the same K slots S. */
int crtraj_check_edges(long long E, const double* XA, const double* dX, const double* bound, const long long* n0,
                       long long K, const double* S, double inflate, double finest, int prefix, long long broad,
                       double* fail, double* lower, long long* samples) {
  return crtraj_refine(E, XA, dX, bound, n0, 0.0, NULL, NULL, K, S, NULL, 0.0, inflate, finest, 0.0, INFINITY, prefix,
                       broad, fail, lower, samples);
}

/* crtraj_check_edges with each motion's first interval count max(1, ceil(bound / coarse)) computed here, as the
   numpy caller would (one array less to build per call). Returns 3 without checking anything when a bound is not
   finite (the caller's numpy loop then says which). */
int crtraj_check_static(long long E, const double* XA, const double* dX, const double* bound, double coarse,
                        long long K, const double* S, double inflate, double finest, int prefix, long long broad,
                        double* fail, double* lower, long long* samples) {
  long long e;
  for (e = 0; e < E; ++e) if (!isfinite(bound[e])) return 3;
  return crtraj_refine(E, XA, dX, bound, NULL, coarse, NULL, NULL, K, S, NULL, 0.0, inflate, finest, 0.0, INFINITY,
                       prefix, broad, fail, lower, samples);
}

/* Moving, breathing obstacles (table T, M rows): every interval against the spheres of its time window, with
   the first interval counts computed here (as crtraj_check_static). Returns 3
   without checking anything when a bound, start time or duration is not finite. */
int crtraj_check_moving_auto(long long E, const double* XA, const double* dX, const double* bound, double coarse,
                             const double* TA, const double* dT, long long M, const double* T, double origin,
                             double inflate, double finest, double enl, double tres, int prefix, long long broad,
                             double* fail, double* lower, long long* samples) {
  long long e;
  for (e = 0; e < E; ++e) if (!isfinite(bound[e]) || !isfinite(TA[e]) || !isfinite(dT[e])) return 3;
  return crtraj_refine(E, XA, dX, bound, NULL, coarse, TA, dT, M, NULL, T, origin, inflate, finest, enl, tres, prefix,
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
/* Batched damped least-squares projection onto tip(x) = target (`SafeIK.project`), every configuration of X
   (N x CRTRAJ_NX, in place) on its own: per step the smallest body motion (metric W, Winv = W^-1, row-major)
   that removes the tip error e, capped at `step` mm, dx = W^-1 J^T (J W^-1 J^T + damping I)^-1 e, then back
   into the bending discs |C u|_k <= tmax_k (C, Cinv: the coupling matrix and its inverse, 2 nseg square,
   row-major) and the z stroke [zlo, zhi], as `ConfigSampler.project_limits` does. A configuration stops as
   soon as its tip error is below tol (mm) or after `iters` steps; err: its last tip error (mm). */
int crtraj_project(long long N, double* X, const double* target, long long iters, const double* Winv,
                   double damping, double step, double tol, long long nseg, const double* C, const double* Cinv,
                   const double* tmax, double zlo, double zhi, double* err) {
  crtraj_work k; long long i, it; int rc = 0, r, c, m, n2 = (int) (2 * nseg);
  double P[3], J[3 * CRTRAJ_NX], JW[3 * CRTRAJ_NX], A[9], e[3], y[3], ub[CRTRAJ_NX];
  if (n2 >= CRTRAJ_NX) return 2;
  if (crtraj_alloc(&k, crtraj_tipjac_work)) { crtraj_free(&k); return 1; }
  for (i = 0; i < N && !rc; ++i) {
    double* x = X + i * CRTRAJ_NX;
    for (it = 0; ; ++it) {
      double en, s, l11, l21, l31, l22, l32, l33, z1, z2, z3;
      k.arg[0] = x; k.res[0] = P; k.res[1] = J;  /* J: 3 x nx column-major, J[r + 3 c] */
      rc = crtraj_tipjac(k.arg, k.res, k.iw, k.w, 0);
      if (rc) break;
      for (r = 0; r < 3; ++r) e[r] = target[r] - P[r];
      en = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
      err[i] = en;
      if (it >= iters || en < tol || en != en) break;
      s = fmin(1.0, step / fmax(en, 1e-300));
      for (r = 0; r < 3; ++r) e[r] *= s;
      for (r = 0; r < 3; ++r)
        for (c = 0; c < CRTRAJ_NX; ++c) {
          double acc = 0.0;
          for (m = 0; m < CRTRAJ_NX; ++m) acc += J[r + 3 * m] * Winv[m * CRTRAJ_NX + c];
          JW[r * CRTRAJ_NX + c] = acc;
        }
      for (r = 0; r < 3; ++r)
        for (c = 0; c < 3; ++c) {
          double acc = (r == c) ? damping : 0.0;
          for (m = 0; m < CRTRAJ_NX; ++m) acc += JW[r * CRTRAJ_NX + m] * J[c + 3 * m];
          A[3 * r + c] = acc;
        }
      /* A is symmetric positive definite (damping > 0): Cholesky */
      l11 = sqrt(A[0]); l21 = A[3] / l11; l31 = A[6] / l11;
      l22 = sqrt(A[4] - l21 * l21); l32 = (A[7] - l31 * l21) / l22;
      l33 = sqrt(A[8] - l31 * l31 - l32 * l32);
      z1 = e[0] / l11; z2 = (e[1] - l21 * z1) / l22; z3 = (e[2] - l31 * z1 - l32 * z2) / l33;
      y[2] = z3 / l33; y[1] = (z2 - l32 * y[2]) / l22; y[0] = (z1 - l21 * y[1] - l31 * y[2]) / l11;
      for (c = 0; c < CRTRAJ_NX; ++c) x[c] += JW[c] * y[0] + JW[CRTRAJ_NX + c] * y[1] + JW[2 * CRTRAJ_NX + c] * y[2];
      for (r = 0; r < n2; ++r) {
        double acc = 0.0;
        for (m = 0; m < n2; ++m) acc += C[r * n2 + m] * x[m];
        ub[r] = acc;
      }
      for (r = 0; r < nseg; ++r) {
        double nr = sqrt(ub[2 * r] * ub[2 * r] + ub[2 * r + 1] * ub[2 * r + 1]);
        double f = fmin(1.0, tmax[r] / fmax(nr, 1e-300));
        ub[2 * r] *= f; ub[2 * r + 1] *= f;
      }
      for (r = 0; r < n2; ++r) {
        double acc = 0.0;
        for (m = 0; m < n2; ++m) acc += Cinv[r * n2 + m] * ub[m];
        x[r] = acc;
      }
      x[CRTRAJ_NX - 1] = fmin(fmax(x[CRTRAJ_NX - 1], zlo), zhi);
    }
  }
  crtraj_free(&k);
  return rc;
}
""".replace("@EDGE_BROAD@", str(EDGE_BROAD))
