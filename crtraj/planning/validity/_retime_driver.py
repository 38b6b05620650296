"""The C function of the compiled validity kernel (`crtraj.planning.validity.ValidityKernel`) that times a smoothed
curve: the phase-plane pass of `crtraj.planning.retime` and the law's knot times in one call. Appended to the
kernel's driver; kept apart only for its length."""

RETIME_DRIVER = r"""
/* crtraj.planning.retime._phase_pass and the knot times of retime._sample_law in one call, operation for operation
   (so the same numbers). n grid points, n - 1 intervals of lengths ds (mm of body-motion bound), m limit rows per
   interval; cap (n): the speed caps on x = (ds/dt)^2; num, den ((n - 1) x m, row-major): x_{k+1} <= (x_k + num) /
   den forward and x_k <= (x_{k+1} + num) / den backward, rows in order, the smaller kept as numpy's loop keeps it.
   Out: sd (n), ds/dt = sqrt(max(x, 0)) at the grid points (x at rest, 0, at both ends), and T (n), the law's
   time (s) at each grid point: T_0 = 0, T_{k+1} = T_k + 2 ds_k / (sd_k + sd_{k+1}) (constant ds2/dt2 between
   grid points). Returns 2 when n < 2 or m < 1. */
int crtraj_phase_law(long long n, long long m, const double* cap, const double* num, const double* den,
                     const double* ds, double* sd, double* T) {
  long long k, j;
  if (n < 2 || m < 1) return 2;
  for (k = 0; k < n; ++k) sd[k] = cap[k];
  sd[0] = 0.0;
  sd[n - 1] = 0.0;
  for (k = 0; k + 1 < n; ++k) {  /* forward: accelerate as hard as allowed */
    const double* u = num + k * m;
    const double* d = den + k * m;
    double xk = sd[k], best = sd[k + 1];
    for (j = 0; j < m; ++j) { double r = (xk + u[j]) / d[j]; if (r < best) best = r; }
    sd[k + 1] = best;
  }
  for (k = n - 2; k >= 0; --k) {  /* backward: brake in time to every later cap */
    const double* u = num + k * m;
    const double* d = den + k * m;
    double xk1 = sd[k + 1], best = sd[k];
    for (j = 0; j < m; ++j) { double r = (xk1 + u[j]) / d[j]; if (r < best) best = r; }
    sd[k] = best;
  }
  for (k = 0; k < n; ++k) sd[k] = sqrt(sd[k] < 0.0 ? 0.0 : sd[k]);  /* numpy's maximum(x, 0): NaN stays NaN */
  T[0] = 0.0;
  for (k = 0; k + 1 < n; ++k) T[k + 1] = T[k] + 2.0 * ds[k] / (sd[k] + sd[k + 1]);
  return 0;
}
"""

CURVE_DRIVER = r"""
/* crtraj.core.splines.natural_cubic's slopes, operation for operation (so the same numbers): n >= 3 knots t (n,)
   strictly increasing, values y (n x d, row-major). Out: m (n x d), the slopes of the natural cubic spline (the
   Thomas algorithm on its tridiagonal system). Returns 2 when n < 3 or d < 1, 1 when out of memory. */
int crtraj_natural_slopes(long long n, long long d, const double* t, const double* y, double* m) {
  long long k, j;
  double *cp, *dp, *delta;
  if (n < 3 || d < 1) return 2;
  cp = (double*)malloc(sizeof(double) * (size_t)n);
  dp = (double*)malloc(sizeof(double) * (size_t)(n * d));
  delta = (double*)malloc(sizeof(double) * (size_t)((n - 1) * d));
  if (!cp || !dp || !delta) { free(cp); free(dp); free(delta); return 1; }
  for (k = 0; k + 1 < n; ++k) {
    double h = t[k + 1] - t[k];
    for (j = 0; j < d; ++j) delta[k * d + j] = (y[(k + 1) * d + j] - y[k * d + j]) / h;
  }
  cp[0] = 1.0 / 2.0;  /* sup[0] / diag[0] */
  for (j = 0; j < d; ++j) dp[j] = (3.0 * delta[j]) / 2.0;
  for (k = 1; k < n; ++k) {
    double sub, diag, sup, den;
    int last = (k == n - 1);
    if (last) { sub = 1.0; diag = 2.0; sup = 0.0; }
    else {
      double h0 = t[k] - t[k - 1], h1 = t[k + 1] - t[k];
      sub = h1; diag = 2.0 * (h0 + h1); sup = h0;
    }
    den = diag - sub * cp[k - 1];
    cp[k] = last ? 0.0 : sup / den;
    for (j = 0; j < d; ++j) {
      double rhs;
      if (last) rhs = 3.0 * delta[(k - 1) * d + j];
      else {
        double h0 = t[k] - t[k - 1], h1 = t[k + 1] - t[k];
        rhs = 3.0 * (h1 * delta[(k - 1) * d + j] + h0 * delta[k * d + j]);
      }
      dp[k * d + j] = (rhs - sub * dp[(k - 1) * d + j]) / den;
    }
  }
  for (j = 0; j < d; ++j) m[(n - 1) * d + j] = dp[(n - 1) * d + j];
  for (k = n - 2; k >= 0; --k)
    for (j = 0; j < d; ++j) m[k * d + j] = dp[k * d + j] - cp[k] * m[(k + 1) * d + j];
  free(cp); free(dp); free(delta);
  return 0;
}

/* crtraj.core.splines.HermiteCubic.__call__ for derivative orders nu 0-2, operation for operation: n >= 2 knots t,
   values y and slopes s (n x d); N parameters x. Out: (N x d) the nu-th derivative at x (the end pieces beyond the
   knots; NaN lands past the last knot as numpy's searchsorted puts it). Returns 2 on a bad n, d or nu. */
int crtraj_hermite(long long n, long long d, const double* t, const double* y, const double* s, long long N,
                   const double* x, int nu, double* out) {
  long long q, j;
  if (n < 2 || d < 1 || nu < 0 || nu > 2) return 2;
  for (q = 0; q < N; ++q) {
    long long lo = 0, hi = n, i;
    double xq = x[q], h, u, b0, b1, b2, b3, hn;
    while (lo < hi) { long long mid = lo + (hi - lo) / 2; if (xq < t[mid]) hi = mid; else lo = mid + 1; }
    i = lo - 1;
    if (i < 0) i = 0;
    if (i > n - 2) i = n - 2;
    h = t[i + 1] - t[i];
    u = (xq - t[i]) / h;
    if (nu == 0) {
      b0 = ((2.0 * u - 3.0) * u) * u + 1.0; b1 = ((u - 2.0) * u + 1.0) * u;
      b2 = ((3.0 - 2.0 * u) * u) * u; b3 = ((u - 1.0) * u) * u; hn = 1.0;
    } else if (nu == 1) {
      b0 = (6.0 * u) * (u - 1.0); b1 = (3.0 * u - 4.0) * u + 1.0;
      b2 = (6.0 * u) * (1.0 - u); b3 = (3.0 * u - 2.0) * u; hn = h;
    } else {
      b0 = 12.0 * u - 6.0; b1 = 6.0 * u - 4.0; b2 = 6.0 - 12.0 * u; b3 = 6.0 * u - 2.0; hn = h * h;
    }
    for (j = 0; j < d; ++j) {
      double m0 = s[i * d + j] * h, m1 = s[(i + 1) * d + j] * h;
      out[q * d + j] = (((b0 * y[i * d + j] + b1 * m0) + b2 * y[(i + 1) * d + j]) + b3 * m1) / hn;
    }
  }
  return 0;
}
"""

VERIFY_DRIVER = r"""
/* The closed loop's dense verification of a step's move (crtraj.control.loop SceneChecks.verify) in one call: the
   n sampled configurations X (n x CRTRAJ_NX) at times Tm (n,) s, sample i held over [Tm[i-1], Tm[i+1]] (the ends
   over their own instant and the neighbour's) with the margin half the larger body-motion bound of its two motions
   (mm), and with `after` one more sample, the last configuration held over [a_lo, a_hi]. Obstacles: K static slots
   S (T NULL) or the M rows of the table T (each window's swept spheres, as crtraj_clearance_windows). Out: the
   smallest clearance minus inflate minus the margin (mm); NaN propagates. Returns 3 when a time is not finite. */
int crtraj_verify_motion(long long n, const double* X, const double* Tm, int after, double a_lo, double a_hi,
                         long long M, const double* S, const double* T, double origin, double inflate, double* out) {
  crtraj_work kb = {0}, km = {0}; long long i, m = n + (after ? 1 : 0); int rc = 0, j, bad;
  double P[7 * CRTRAJ_NP], dx[CRTRAJ_NX], b_prev = 0.0, b_next = 0.0, best = INFINITY;
  double* sw = (double*) malloc(sizeof(double) * 5 * (size_t) (M > 0 ? M : 1));
  *out = NAN;
  if (n < 1) { free(sw); return 2; }
  for (i = 0; i < n; ++i) if (!isfinite(Tm[i])) { free(sw); return 3; }
  if (after && (!isfinite(a_lo) || !isfinite(a_hi))) { free(sw); return 3; }
  bad = !sw;
  bad |= crtraj_alloc(&kb, crtraj_bb_work);
  bad |= crtraj_alloc(&km, crtraj_mb_work);
  if (bad) { free(sw); crtraj_free(&kb); crtraj_free(&km); return 1; }
  for (i = 0; i < m && !rc; ++i) {
    const double* x = X + (i < n ? i : n - 1) * CRTRAJ_NX;
    double lo, hi, half = 0.0, c, v;
    if (i < n) {
      b_prev = b_next;
      if (i + 1 < n) {
        for (j = 0; j < CRTRAJ_NX; ++j) dx[j] = x[CRTRAJ_NX + j] - x[j];
        km.arg[0] = dx; km.res[0] = &b_next;
        rc = crtraj_mb(km.arg, km.res, km.iw, km.w, 0);
      }
      if (n > 1) {
        double a = i == 0 ? b_next : b_prev, b = i == n - 1 ? b_prev : b_next;
        half = (a != a || b != b) ? NAN : (a >= b ? a : b);
        half *= 0.5;
      }
      lo = i == 0 ? Tm[0] : Tm[i - 1];
      hi = i == n - 1 ? Tm[n - 1] : Tm[i + 1];
    } else {
      lo = a_lo;
      hi = a_hi;
    }
    if (rc) break;
    if (T) { crtraj_swept(M, T, origin, lo, hi, sw); rc = crtraj_clear_one(&kb, x, M, sw, P, &c); }
    else rc = crtraj_clear_one(&kb, x, M, S, P, &c);
    v = (c - inflate) - half;
    if (v < best || v != v) best = v;
    if (best != best) break;
  }
  *out = best;
  free(sw); crtraj_free(&kb); crtraj_free(&km);
  return rc;
}
"""
