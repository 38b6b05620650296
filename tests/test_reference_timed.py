"""`TimedReference.at` and `locate` (the loop asks them every step) against the plain formulas they stand for: a
mask over every segment, a copy of its rows, np.clip (random paths, hypothesis; equal bit for bit)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.control.loop._reference import TimedReference

M = np.array([[1.0, 0.2, 0.0], [0.0, 1.5, 0.3], [0.1, 0.0, 2.0]])


def _metric(X: np.ndarray) -> np.ndarray:
    return np.asarray(X, dtype=float) @ M.T


def _seconds(dX: np.ndarray) -> np.ndarray:
    return np.abs(dX).sum(axis=1)  # zero for a repeated configuration: zero-length segments occur


def _locate_plain(ref: TimedReference, x: np.ndarray, s_hint: float, back: float, ahead: float) -> float:
    """The projection as the loop computed it before: every segment masked, then np.clip."""
    if ref.end == 0.0:
        return 0.0
    y = _metric(x[None])[0]
    lo, hi = s_hint - back, s_hint + ahead
    segs = np.flatnonzero((ref.s[1:] >= lo) & (ref.s[:-1] <= hi))
    if not len(segs):
        segs = np.arange(len(ref.X) - 1)
    Y = _metric(ref.X)
    A, AB = Y[segs], (Y[1:] - Y[:-1])[segs]
    den = np.maximum((AB * AB).sum(axis=1), 1e-300)
    u = np.clip(((y - A) * AB).sum(axis=1) / den, 0.0, 1.0)
    w = A + u[:, None] * AB - y
    j = int(np.sqrt((w * w).sum(axis=1)).argmin())
    i = segs[j]
    return float(np.clip(ref.s[i] + u[j] * (ref.s[i + 1] - ref.s[i]), lo, hi))


def _at_plain(ref: TimedReference, s: np.ndarray) -> np.ndarray:
    s = np.clip(np.asarray(s, dtype=float), 0.0, ref.end)
    i = np.minimum(np.searchsorted(ref.s, s, side="right") - 1, len(ref.X) - 2)
    seg = ref.s[i + 1] - ref.s[i]
    u = np.divide(s - ref.s[i], seg, out=np.zeros_like(s), where=seg > 0)
    return ref.X[i] + u[..., None] * (ref.X[i + 1] - ref.X[i])


@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(2, 60),
    st.floats(-2.0, 30.0),
    st.floats(0.0, 3.0),
    st.floats(0.0, 3.0),
    st.booleans(),
)
def test_locate_and_at_equal_the_plain_formulas(seed, k, hint, back, ahead, repeats):
    rng = np.random.default_rng(seed)
    X = np.cumsum(rng.normal(size=(k, 3)), axis=0)
    if repeats:  # repeated configurations: zero-length segments
        X = np.repeat(X, rng.integers(1, 3, size=k), axis=0)
    ref = TimedReference(X, _seconds, _metric)
    for _ in range(5):
        x = X[rng.integers(len(X))] + rng.normal(scale=0.5, size=3)
        got = ref.locate(x, hint, back, ahead)
        assert got == _locate_plain(ref, x, hint, back, ahead)
        assert isinstance(got, float)
    s = hint + 0.1 * np.arange(1, 11)
    np.testing.assert_array_equal(ref.at(s), _at_plain(ref, s))
    np.testing.assert_array_equal(ref.at(np.array([-1.0, ref.end + 1.0])), X[[0, -1]])
