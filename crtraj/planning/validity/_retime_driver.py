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
