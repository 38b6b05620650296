"""Piecewise cubics in plain numpy: cubic Hermite curves, natural-spline and PCHIP slopes, and B-splines.

Why not `scipy.interpolate`: importing it costs 0.5-0.9 s (it pulls in scipy.special, scipy.optimize and
parses hundreds of docstrings), which is most of a `crtraj plan` process's wall time, and every command is
a new process. These few closed forms are all crtraj needs. They follow SciPy's conventions (values
(N, ...) along axis 0, extrapolation with the end pieces, PCHIP's Fritsch-Butland slopes and end
conditions) and the tests check them against SciPy to round-off.

Units are the caller's: `t` in any unit of the parameter (s, mm of motion bound, ...), values in theirs,
slopes in value units per parameter unit.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BSplineCurve", "HermiteCubic", "natural_cubic", "pchip_slopes"]


def _knots(t: np.ndarray) -> np.ndarray:
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or len(t) < 2:
        raise ValueError(f"spline: need at least 2 knots in a 1-D array, got shape {t.shape}")
    if not np.all(np.diff(t) > 0.0):
        raise ValueError("spline: knots must be strictly increasing")
    return t


class HermiteCubic:
    """The piecewise cubic through `values` (N, ...) with `slopes` (N, ...) at the knots `t` (N,).

    ``curve(x, nu)`` is the nu-th derivative (0-3) at x (any shape); points outside [t0, tN-1] use the
    end pieces (as SciPy's ``CubicHermiteSpline`` with ``extrapolate=True``).
    """

    def __init__(self, t: np.ndarray, values: np.ndarray, slopes: np.ndarray) -> None:
        self.t = _knots(t)
        self.values = np.asarray(values, dtype=float)
        self.slopes = np.asarray(slopes, dtype=float)
        if self.values.shape[:1] != self.t.shape or self.slopes.shape != self.values.shape:
            raise ValueError(
                f"spline: {len(self.t)} knots need values and slopes of one shape ({len(self.t)}, ...), "
                f"got {self.values.shape} and {self.slopes.shape}"
            )

    def __call__(self, x: np.ndarray | float, nu: int = 0) -> np.ndarray:
        if nu not in (0, 1, 2, 3):
            raise ValueError(f"spline: derivative order nu must be 0-3, got {nu}")
        x = np.asarray(x, dtype=float)
        t = self.t
        i = np.clip(np.searchsorted(t, x, side="right") - 1, 0, len(t) - 2)
        h = t[i + 1] - t[i]
        u = (x - t[i]) / h
        # basis of (y0, h m0, y1, h m1) on u in [0, 1], differentiated nu times in x (a factor 1/h each)
        if nu == 0:
            b = (((2.0 * u - 3.0) * u) * u + 1.0, ((u - 2.0) * u + 1.0) * u, (3.0 - 2.0 * u) * u * u, (u - 1.0) * u * u)
        elif nu == 1:
            b = (6.0 * u * (u - 1.0), (3.0 * u - 4.0) * u + 1.0, 6.0 * u * (1.0 - u), (3.0 * u - 2.0) * u)
        elif nu == 2:
            b = (12.0 * u - 6.0, 6.0 * u - 4.0, 6.0 - 12.0 * u, 6.0 * u - 2.0)
        else:
            one = np.ones_like(u)
            b = (12.0 * one, 6.0 * one, -12.0 * one, 6.0 * one)
        extra = (1,) * (self.values.ndim - 1)
        h_ = h.reshape(h.shape + extra)
        b0, b1, b2, b3 = (np.reshape(c, np.shape(c) + extra) for c in b)
        y0, y1 = self.values[i], self.values[i + 1]
        m0, m1 = self.slopes[i] * h_, self.slopes[i + 1] * h_
        return (b0 * y0 + b1 * m0 + b2 * y1 + b3 * m1) / h_**nu


def natural_cubic(t: np.ndarray, values: np.ndarray) -> HermiteCubic:
    """The natural cubic spline (zero second derivative at both ends) through `values` (N, ...) at `t`
    (N,); with two knots, the straight line. Same curve as SciPy's ``CubicSpline(bc_type="natural")``."""
    t = _knots(t)
    y = np.asarray(values, dtype=float)
    if y.shape[:1] != t.shape:
        raise ValueError(f"spline: {len(t)} knots need values of shape ({len(t)}, ...), got {y.shape}")
    n = len(t)
    h = np.diff(t).reshape((-1,) + (1,) * (y.ndim - 1))
    delta = np.diff(y, axis=0) / h
    if n == 2:
        return HermiteCubic(t, y, np.concatenate([delta, delta]))
    # slopes m: h_i m_{i-1} + 2 (h_{i-1} + h_i) m_i + h_{i-1} m_{i+1} = 3 (h_i d_{i-1} + h_{i-1} d_i) inside,
    # 2 m_0 + m_1 = 3 d_0 and m_{n-2} + 2 m_{n-1} = 3 d_{n-2} at the natural ends: a diagonally
    # dominant tridiagonal system, solved by the Thomas algorithm without pivoting.
    sub = np.empty((n, *h.shape[1:]))
    diag = np.empty_like(sub)
    sup = np.empty_like(sub)
    rhs = np.empty((n, *y.shape[1:]))
    diag[0], sup[0], rhs[0] = 2.0, 1.0, 3.0 * delta[0]
    sub[1:-1] = h[1:]
    diag[1:-1] = 2.0 * (h[:-1] + h[1:])
    sup[1:-1] = h[:-1]
    rhs[1:-1] = 3.0 * (h[1:] * delta[:-1] + h[:-1] * delta[1:])
    sub[-1], diag[-1], rhs[-1] = 1.0, 2.0, 3.0 * delta[-1]
    cp = np.empty_like(sup)
    dp = np.empty_like(rhs)
    cp[0], dp[0] = sup[0] / diag[0], rhs[0] / diag[0]
    for k in range(1, n):
        den = diag[k] - sub[k] * cp[k - 1]
        cp[k] = sup[k] / den if k < n - 1 else 0.0
        dp[k] = (rhs[k] - sub[k] * dp[k - 1]) / den
    m = np.empty_like(rhs)
    m[-1] = dp[-1]
    for k in range(n - 2, -1, -1):
        m[k] = dp[k] - cp[k] * m[k + 1]
    return HermiteCubic(t, y, m)


def _pchip_end(h0: np.ndarray, h1: np.ndarray, m0: np.ndarray, m1: np.ndarray) -> np.ndarray:
    """End slope: the three-point (non-centred) estimate, made shape-preserving."""
    d = ((2.0 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    d = np.where(np.sign(d) != np.sign(m0), 0.0, d)
    overshoot = (np.sign(m0) != np.sign(m1)) & (np.abs(d) > 3.0 * np.abs(m0))
    return np.where(overshoot, 3.0 * m0, d)


def pchip_slopes(t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Slopes (N, ...) of the monotone piecewise cubic through `values` (N, ...) at `t` (N,): zero at
    local extrema and flat steps, elsewhere the weighted harmonic mean of the neighbouring chords
    (Fritsch-Butland), as SciPy's ``PchipInterpolator``; never overshoots a value."""
    t = _knots(t)
    y = np.asarray(values, dtype=float)
    if y.shape[:1] != t.shape:
        raise ValueError(f"spline: {len(t)} knots need values of shape ({len(t)}, ...), got {y.shape}")
    h = np.diff(t).reshape((-1,) + (1,) * (y.ndim - 1))
    m = np.diff(y, axis=0) / h
    if len(t) == 2:
        return np.concatenate([m, m])
    h0, h1 = h[:-1], h[1:]
    m0, m1 = m[:-1], m[1:]
    w1, w2 = 2.0 * h1 + h0, h1 + 2.0 * h0
    flat = (np.sign(m0) != np.sign(m1)) | (m0 == 0.0) | (m1 == 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        inner = np.where(flat, 0.0, (w1 + w2) / (w1 / m0 + w2 / m1))
    d = np.empty_like(y)
    d[1:-1] = inner
    d[0] = _pchip_end(h[0], h[1], m[0], m[1])
    d[-1] = _pchip_end(h[-1], h[-2], m[-1], m[-2])
    return d


class BSplineCurve:
    """The B-spline of degree k with knot vector `knots` (n + k + 1,) and coefficients `coeffs` (n, ...).

    ``curve(x)`` evaluates by de Boor's recursion, vectorised over x; outside the base interval
    [knots[k], knots[n]] the end pieces extend (as SciPy's ``BSpline`` with ``extrapolate=True``).
    """

    def __init__(self, knots: np.ndarray, coeffs: np.ndarray, k: int) -> None:
        self.knots = np.asarray(knots, dtype=float)
        self.coeffs = np.asarray(coeffs, dtype=float)
        self.k = int(k)
        n = len(self.coeffs)
        if self.k < 0 or self.knots.ndim != 1 or len(self.knots) != n + self.k + 1 or n < self.k + 1:
            raise ValueError(
                f"spline: degree {k} with {n} coefficients needs {n + k + 1} knots, got {self.knots.shape}"
            )
        if np.any(np.diff(self.knots) < 0.0) or not self.knots[n] > self.knots[self.k]:
            raise ValueError("spline: knots must be nondecreasing, with a base interval of positive length")

    def __call__(self, x: np.ndarray | float) -> np.ndarray:
        tk, c, k = self.knots, self.coeffs, self.k
        n = len(c)
        x = np.asarray(x, dtype=float)
        shape = x.shape
        x = x.reshape(-1)
        # the knot span of each x among the nonempty spans of the base interval: tk[i] <= x < tk[i + 1]
        spans = np.flatnonzero(tk[k + 1 : n + 1] > tk[k:n]) + k
        i = spans[np.clip(np.searchsorted(tk[spans], x, side="right") - 1, 0, len(spans) - 1)]
        extra = (1,) * (c.ndim - 1)
        d = [c[i - k + j] for j in range(k + 1)]
        for r in range(1, k + 1):
            for j in range(k, r - 1, -1):
                left = tk[i - k + j]
                den = tk[i + 1 + j - r] - left
                alpha = ((x - left) / den).reshape((-1, *extra))
                d[j] = (1.0 - alpha) * d[j - 1] + alpha * d[j]
        return d[k].reshape(shape + c.shape[1:])
