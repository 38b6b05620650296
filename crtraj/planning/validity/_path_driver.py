"""The C functions of the compiled validity kernel (`crtraj.planning.validity._compiled`) that measure and shape a
finished path: its measured clearance (`MotionValidator.path_clearance`) and the smoothing's B-spline samples.
Appended to `crtraj.planning.validity._driver.DRIVER` (they use its helpers); kept apart only for its length."""

PATH_DRIVER = r"""
/* MotionValidator.path_clearance in one call: the K - 1 straight motions X[i] -> X[i + 1] (X: K x CRTRAJ_NX) over
   [Tm[i], Tm[i + 1]] (s, before the scene's time origin), each sampled at ns = max(1, ceil(bound[i] / res)) + 1
   configurations (both ends) at their own instants, as the numpy samples are; per motion, the smallest sample
   clearance minus `inflate` (mm) into pe[i]. Obstacles: K slots S (a static scene, T NULL) or the M rows of the
   table T (each sample against the obstacles' spheres at its instant). Exact broad phase: the first sample of
   a motion is checked against every obstacle; obstacle q's clearance anywhere on the motion is at least its
   clearance there minus the motion's body-motion bound and what the obstacle can move and grow meanwhile
   (enl mm/s times the duration), so an obstacle whose bound is not below that first sample's clearance never
   sets the minimum and the other samples skip it: the same minima, bit for bit. Returns 3 without computing
   anything when a value is not finite. */
int crtraj_path_clearance(long long K, const double* X, const double* Tm, const double* bound, double res,
                          long long M, const double* S, const double* T, double origin, double inflate, double enl,
                          double* pe, long long* samples) {
  crtraj_work kb; long long e, k, q, ns, kept = M; int rc = 0, j;
  double P[7 * CRTRAJ_NP], x[CRTRAJ_NX], sw[5];
  double* d = (double*) malloc(sizeof(double) * (size_t) (M + 1));
  long long* all = (long long*) malloc(sizeof(long long) * (size_t) (M + 1));
  long long* idx = (long long*) malloc(sizeof(long long) * (size_t) (M + 1));
  *samples = 0;
  for (e = 0; e + 1 < K; ++e)
    if (!isfinite(bound[e]) || !isfinite(Tm[e]) || !isfinite(Tm[e + 1])) { free(d); free(all); free(idx); return 3; }
  if (!d || !all || !idx || crtraj_alloc(&kb, crtraj_bb_work)) {
    free(d); free(all); free(idx); crtraj_free(&kb); return 1;
  }
  for (q = 0; q < M; ++q) all[q] = q;
  for (e = 0; e + 1 < K && !rc; ++e) {
    const double* xa = X + e * CRTRAJ_NX;
    const double* xb = xa + CRTRAJ_NX;
    double ta = Tm[e], dt = Tm[e + 1] - Tm[e], m = INFINITY, c0 = 0.0, slack = 0.0;
    ns = (long long) fmax(1.0, ceil(bound[e] / res));
    for (k = 0; k <= ns && !rc; ++k) {
      double tau = (double) k / (double) ns, t = ta + tau * dt, c;
      for (j = 0; j < CRTRAJ_NX; ++j) x[j] = xa[j] + tau * (xb[j] - xa[j]);
      if (k == 0) {
        rc = crtraj_clear_idx(&kb, x, all, M, S, T, origin, t, t, P, sw, d, &c);
        c0 = c - inflate;
        slack = bound[e] + enl * fabs(dt) + 1e-6;
        kept = 0;
        for (q = 0; q < M; ++q)
          if (!(d[q] - inflate - slack >= c0)) idx[kept++] = q;  /* NaN keeps */
      } else {
        rc = crtraj_clear_idx(&kb, x, idx, kept, S, T, origin, t, t, P, sw, d, &c);
      }
      ++*samples;
      c = c - inflate - 0.0;
      if (c < m || c != c) m = c;
      if (m != m) break;
    }
    pe[e] = m;
  }
  free(d); free(all); free(idx);
  crtraj_free(&kb);
  return rc;
}


/* A B-spline curve of degree k (knots tk, nt of them; coefficients C, nc x dim, row-major) at the N parameters x,
   into out (N x dim): crtraj.core.splines.BSplineCurve.__call__ operation for operation (the knot span among the
   nonempty spans of the base interval, clipped to the first and last; de Boor's recursion with the same
   products and sums), so the same numbers. */
int crtraj_bspline(long long N, const double* x, long long nt, const double* tk, long long nc, long long dim,
                   const double* C, long long k, double* out) {
  long long p, lo = k, hi, s, cnt, i, j, r, q;
  double* d;
  if (k < 0 || nt != nc + k + 1 || dim < 1) return 2;
  d = (double*) malloc(sizeof(double) * (size_t) ((k + 1) * dim));
  if (!d) return 1;
  hi = nc;  /* the base interval's spans are k .. nc - 1 */
  for (p = 0; p < N; ++p) {
    double xp = x[p];
    /* searchsorted(tk[spans], x, "right") - 1 among the nonempty spans, clipped: the last span starting at or
       before x, else the first */
    long long first = -1, last = -1;
    cnt = 0;
    i = -1;
    for (s = lo; s < hi; ++s) {
      if (!(tk[s + 1] > tk[s])) continue;
      if (first < 0) first = s;
      last = s;
      if (tk[s] <= xp) { i = s; ++cnt; }
    }
    if (first < 0) { free(d); return 2; }
    if (xp != xp) i = last;  /* numpy sorts NaN last */
    else if (cnt == 0) i = first;
    for (j = 0; j <= k; ++j)
      for (q = 0; q < dim; ++q) d[j * dim + q] = C[(i - k + j) * dim + q];
    for (r = 1; r <= k; ++r)
      for (j = k; j >= r; --j) {
        double left = tk[i - k + j];
        double den = tk[i + 1 + j - r] - left;
        double alpha = (xp - left) / den;
        for (q = 0; q < dim; ++q) d[j * dim + q] = (1.0 - alpha) * d[(j - 1) * dim + q] + alpha * d[j * dim + q];
      }
    for (q = 0; q < dim; ++q) out[p * dim + q] = d[k * dim + q];
  }
  free(d);
  return 0;
}
"""
