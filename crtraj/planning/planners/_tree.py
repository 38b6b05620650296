"""A search tree for the RRT family: nodes with a key (what neighbours are measured in),
a configuration, a time, a cost and a parent, plus nearest / radius queries on the keys."""

from __future__ import annotations

import numpy as np

from crtraj.planning.planners._nn import NearestNeighbors


class SearchTree:
    """Growing arrays of nodes. key: (dim,) point the nearest-neighbour queries use
    (tip position in mm for the task-space planners, the body-motion metric y for
    the configuration-space planner). x: configuration. t: time (s) the robot is
    there. cost: path cost from the root. parent: -1 for roots."""

    def __init__(self, key_dim: int, nx: int, capacity: int = 512) -> None:
        self.nn = NearestNeighbors(key_dim, capacity)
        self._x = np.empty((capacity, nx))
        self._t = np.empty(capacity)
        self._cost = np.empty(capacity)
        self._parent = np.empty(capacity, dtype=int)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def _grow(self) -> None:
        cap = 2 * len(self._t)
        for name in ("_x", "_t", "_cost", "_parent"):
            old = getattr(self, name)
            new = np.empty((cap, *old.shape[1:]), dtype=old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def add(self, key: np.ndarray, x: np.ndarray, t: float, cost: float, parent: int) -> int:
        """Append a node; returns its index."""
        if self._n == len(self._t):
            self._grow()
        i = self._n
        self._x[i] = x
        self._t[i] = t
        self._cost[i] = cost
        self._parent[i] = parent
        self._n += 1
        self.nn.add(key)
        return i

    def add_many(self, keys: np.ndarray, x: np.ndarray, t: np.ndarray, cost: np.ndarray, parent: np.ndarray) -> None:
        """Append the nodes (m of each argument's rows) in order, as `add` one at a time would."""
        m = len(x)
        while self._n + m > len(self._t):
            self._grow()
        sl = slice(self._n, self._n + m)
        self._x[sl], self._t[sl], self._cost[sl], self._parent[sl] = x, t, cost, parent
        self._n += m
        self.nn.add_many(keys)

    @property
    def keys(self) -> np.ndarray:
        return self.nn.points

    @property
    def x(self) -> np.ndarray:
        return self._x[: self._n]

    @property
    def t(self) -> np.ndarray:
        return self._t[: self._n]

    @property
    def cost(self) -> np.ndarray:
        return self._cost[: self._n]

    @property
    def parent(self) -> np.ndarray:
        return self._parent[: self._n]

    def set_parent(self, i: int, parent: int, cost: float, t: float) -> None:
        self._parent[i] = parent
        self._cost[i] = cost
        self._t[i] = t

    def set_cost_time(self, idx: np.ndarray, cost: np.ndarray, t: np.ndarray) -> None:
        self._cost[idx] = cost
        self._t[idx] = t

    def nearest(self, key: np.ndarray) -> tuple[int, float]:
        return self.nn.nearest(key)

    def within(self, key: np.ndarray, r: float) -> np.ndarray:
        return self.nn.within(key, r)

    def path_to(self, i: int) -> np.ndarray:
        """Node indices from the root to node i."""
        out = []
        while i >= 0:
            out.append(i)
            i = int(self._parent[i])
        return np.array(out[::-1], dtype=int)

    def subtree(self, i: int) -> np.ndarray:
        """Indices of node i and all its descendants, parents before children."""
        par = self.parent
        out = [i]
        frontier = np.array([i])
        while len(frontier):
            kids = np.flatnonzero(np.isin(par, frontier))
            out.extend(kids.tolist())
            frontier = kids
        return np.array(out, dtype=int)

    def edges(self) -> tuple[np.ndarray, np.ndarray]:
        """(parent indices, child indices) of every edge."""
        child = np.flatnonzero(self.parent >= 0)
        return self.parent[child], child
