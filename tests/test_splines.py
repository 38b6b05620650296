"""crtraj.core.splines against SciPy's interpolators (the independent reference) and closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import BSpline, CubicHermiteSpline, CubicSpline, PchipInterpolator

from crtraj.core.splines import BSplineCurve, HermiteCubic, natural_cubic, pchip_slopes


def _data(rng: np.random.Generator, n: int, shape: tuple[int, ...] = (3,)) -> tuple[np.ndarray, np.ndarray]:
    t = np.cumsum(rng.uniform(0.05, 2.0, n)) - 1.0
    return t, rng.normal(size=(n, *shape)) * 10.0


def _probe(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    # inside, on every knot, and beyond both ends (extrapolation with the end pieces)
    span = t[-1] - t[0]
    return np.concatenate([rng.uniform(t[0] - 0.2 * span, t[-1] + 0.2 * span, 200), t])


@pytest.mark.parametrize("n", [2, 3, 4, 9, 40])
def test_hermite_matches_scipy_with_derivatives(n):
    rng = np.random.default_rng(n)
    t, y = _data(rng, n)
    m = rng.normal(size=y.shape)
    x = _probe(t, rng)
    ours, ref = HermiteCubic(t, y, m), CubicHermiteSpline(t, y, m, axis=0)
    for nu in range(4):
        np.testing.assert_allclose(ours(x, nu), ref(x, nu), rtol=1e-11, atol=1e-9)
    # interpolation and slopes at the knots, exactly as given
    np.testing.assert_allclose(ours(t), y, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ours(t, 1), m, rtol=1e-12, atol=1e-10)
    assert ours(0.5).shape == (3,) and ours(np.zeros((4, 5))).shape == (4, 5, 3)


@pytest.mark.parametrize("n", [2, 3, 5, 30])
def test_natural_cubic_matches_scipy(n):
    rng = np.random.default_rng(10 + n)
    t, y = _data(rng, n, (4,))
    x = _probe(t, rng)
    ours, ref = natural_cubic(t, y), CubicSpline(t, y, bc_type="natural")
    for nu in range(3):
        np.testing.assert_allclose(ours(x, nu), ref(x, nu), rtol=1e-10, atol=1e-8)
    # natural: zero curvature at both ends; C2 at the interior knots (one-sided second derivatives agree)
    np.testing.assert_allclose(ours(t[[0, -1]], 2), 0.0, atol=1e-9)
    if n > 2:
        eps = 1e-7 * np.min(np.diff(t))
        np.testing.assert_allclose(ours(t[1:-1] - eps, 2), ours(t[1:-1] + eps, 2), rtol=1e-5, atol=1e-5)
    # 1-D values too
    np.testing.assert_allclose(natural_cubic(t, y[:, 0])(x), ref(x)[:, 0], rtol=1e-10, atol=1e-8)


@pytest.mark.parametrize("n", [2, 3, 7, 25])
def test_pchip_slopes_match_scipy(n):
    rng = np.random.default_rng(20 + n)
    t, y = _data(rng, n, (2,))
    y[n // 2] = y[n // 2 - 1]  # a flat step: slope 0 on both of its ends
    ref = PchipInterpolator(t, y, axis=0).derivative()(t)
    np.testing.assert_allclose(pchip_slopes(t, y), ref, rtol=1e-12, atol=1e-12)
    # monotone data stays monotone between the knots (never overshoots)
    ym = np.cumsum(rng.uniform(0.0, 3.0, n))
    curve = HermiteCubic(t, ym, pchip_slopes(t, ym))
    xs = np.linspace(t[0], t[-1], 2000)
    assert np.all(np.diff(curve(xs)) >= -1e-12)


@pytest.mark.parametrize("k", [1, 2, 3, 5])
def test_bspline_matches_scipy(k):
    rng = np.random.default_rng(30 + k)
    n = 12
    # clamped knots with a repeated interior knot, as the corner-rounding spline and worse
    inner = np.sort(rng.uniform(0.0, 1.0, n - k - 1))
    inner[3] = inner[2]
    knots = np.concatenate([np.zeros(k + 1), inner, np.ones(k + 1)])
    c = rng.normal(size=(n, 3))
    x = np.concatenate([rng.uniform(-0.1, 1.1, 300), knots])
    np.testing.assert_allclose(BSplineCurve(knots, c, k)(x), BSpline(knots, c, k)(x), rtol=1e-11, atol=1e-11)
    # clamped ends interpolate the first and last coefficients
    np.testing.assert_allclose(BSplineCurve(knots, c, k)(np.array([0.0, 1.0])), c[[0, -1]], atol=1e-12)


def test_bad_input_is_refused_with_a_reason():
    with pytest.raises(ValueError, match="strictly increasing"):
        HermiteCubic(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="at least 2 knots"):
        natural_cubic(np.array([0.0]), np.zeros(1))
    with pytest.raises(ValueError, match="needs 8 knots"):
        BSplineCurve(np.linspace(0, 1, 7), np.zeros((4, 2)), 3)
    with pytest.raises(ValueError, match="derivative order"):
        HermiteCubic(np.array([0.0, 1.0]), np.zeros(2), np.zeros(2))(0.5, 4)
