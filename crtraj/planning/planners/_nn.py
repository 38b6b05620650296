"""Incremental nearest-neighbour index for growing search trees.

Up to `tree_min` points a query is one vectorised scan of all of them (a few
microseconds for a thousand points, and no KD-tree to build). Beyond, scipy's
KD-tree, which is static, holds the older points and is rebuilt when the
recent-points buffer grows as large as a fixed fraction of the tree (amortised
O(log n) per insert), while queries combine a KD-tree query with one
vectorised scan of the small buffer. No per-point Python loops.
"""

from __future__ import annotations

import numpy as np

from crtraj.core.lazy import lazy_module

# SciPy's spatial package costs about 0.5 s to import; an index needs it only once it holds `tree_min`
# points, which a c-space query rarely reaches.
spatial = lazy_module("scipy.spatial")


class NearestNeighbors:
    """Points (any dimension, Euclidean) added one at a time; nearest / radius queries.

    Indices are insertion order, starting at 0.
    """

    def __init__(self, dim: int, capacity: int = 1024, min_buffer: int = 64, tree_min: int = 1024) -> None:
        self.dim = int(dim)
        self._data = np.empty((max(16, capacity), self.dim))
        self._n = 0
        self._tree: spatial.cKDTree | None = None
        self._n_tree = 0  # points [0, _n_tree) are in the KD-tree
        self._min_buffer = int(min_buffer)
        self._tree_min = int(tree_min)

    @property
    def indexed(self) -> int:
        """How many of the points are in the KD-tree (the rest are searched linearly in a small buffer)."""
        return self._n_tree

    def __len__(self) -> int:
        return self._n

    @property
    def points(self) -> np.ndarray:
        """(n, dim) view of all points."""
        return self._data[: self._n]

    def add(self, p: np.ndarray) -> int:
        """Insert one point; return its index."""
        if self._n == len(self._data):
            grown = np.empty((2 * len(self._data), self.dim))
            grown[: self._n] = self._data[: self._n]
            self._data = grown
        self._data[self._n] = p
        self._n += 1
        if self._n >= self._tree_min and self._n - self._n_tree > max(self._min_buffer, self._n_tree // 2):
            self._tree = spatial.cKDTree(self._data[: self._n].copy())
            self._n_tree = self._n
        return self._n - 1

    def add_many(self, P: np.ndarray) -> None:
        """Insert the rows of P (m, dim) in order, as `add` one at a time would."""
        P = np.asarray(P, dtype=float).reshape(-1, self.dim)
        if self._n + len(P) >= self._tree_min:  # the KD-tree's rebuild points: one at a time
            for p in P:
                self.add(p)
            return
        while self._n + len(P) > len(self._data):
            grown = np.empty((2 * len(self._data), self.dim))
            grown[: self._n] = self._data[: self._n]
            self._data = grown
        self._data[self._n : self._n + len(P)] = P
        self._n += len(P)

    def nearest(self, q: np.ndarray) -> tuple[int, float]:
        """Index and distance of the point nearest to q."""
        if self._n == 0:
            raise IndexError("nearest: the index is empty")
        best_i, best_d = -1, np.inf
        if self._tree is not None:
            d, i = self._tree.query(q)
            best_i, best_d = int(i), float(d)
        if self._n > self._n_tree:
            buf = self._data[self._n_tree : self._n]
            d2 = np.einsum("ij,ij->i", buf - q, buf - q)
            j = int(np.argmin(d2))
            if d2[j] < best_d * best_d:
                best_i, best_d = self._n_tree + j, float(np.sqrt(d2[j]))
        return best_i, best_d

    def within(self, q: np.ndarray, r: float) -> np.ndarray:
        """Indices (sorted) of all points within distance r of q."""
        parts = []
        if self._tree is not None:
            parts.append(np.asarray(self._tree.query_ball_point(q, r), dtype=int))
        if self._n > self._n_tree:
            buf = self._data[self._n_tree : self._n]
            d2 = np.einsum("ij,ij->i", buf - q, buf - q)
            parts.append(self._n_tree + np.flatnonzero(d2 <= r * r))
        if not parts:
            return np.zeros(0, dtype=int)
        return np.sort(np.concatenate(parts))
