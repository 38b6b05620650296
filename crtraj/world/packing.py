"""How obstacles enter a solver: one fixed-size parameter vector of sphere slots.

Every CasADi NLP in crtraj (steer, safe IK, the horizon replanner) is built
once for at most ``max_obstacles`` spheres; the spheres of the moment enter as
a parameter vector of `WIDTH` numbers per slot:

    slot i = [cx, cy, cz, r, active]        (mm, mm, mm, mm, 1 or 0)

``r`` is the radius of the sphere the solver keeps its points outside of.
Whether that radius is already inflated by D_sf and the body radius is the
consumer's choice and is said where it packs (the steer and IK NLPs add the
inflation inside the NLP from a parameter; the horizon replanner packs the
inflated radius, see `crtraj.world.margin`). Slots past the real obstacles are
padding: centre `PAD_CENTER`, radius 0, active 0. A solver that ignores the
active flag still sees a constraint that holds by 1e6 mm and a penalty
``((R + D_sf + body) / d)^2`` below 1e-10, so padding is inert either way.

NLPs are built for a multiple of `SLOTS` obstacles (`slot_count`), so a scene
that gains an obstacle rarely forces a rebuild.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from crtraj.core.errors import InputError

# Numbers per slot, and where each field sits in a slot.
WIDTH = 5
CENTER = slice(0, 3)
RADIUS = 3
ACTIVE = 4
# Padding slots sit this far up the z axis (mm) with radius 0 and active 0.
PAD_CENTER = (0.0, 0.0, 1.0e6)
# NLPs are built for multiples of this many obstacle slots.
SLOTS = 8


def slot_count(n_obstacles: int) -> int:
    """Slots to build an NLP with for `n_obstacles` obstacles: the next multiple of `SLOTS` (at least `SLOTS`)."""
    return SLOTS * max(1, math.ceil(n_obstacles / SLOTS))


def check_capacity(max_obstacles: Any, n_obstacles: int, who: str = "the solver") -> int:
    """Validate a slot count and that `n_obstacles` fit; return the count as int. One-line `InputError` otherwise."""
    if isinstance(max_obstacles, bool) or not isinstance(max_obstacles, (int, np.integer)) or max_obstacles < 0:
        raise InputError(f"max_obstacles: must be an integer >= 0, got {max_obstacles!r}")
    if n_obstacles > max_obstacles:
        raise InputError(
            f"scene.obstacle: {n_obstacles} obstacles but {who} was built for at most {max_obstacles}; "
            "rebuild it with a larger max_obstacles"
        )
    return int(max_obstacles)


def pack(centers: Any, radii: Any, max_obstacles: int, who: str = "the solver") -> np.ndarray:
    """Spheres as slots: centres (..., m, 3) mm and radii (..., m) mm -> (..., WIDTH * max_obstacles).

    The leading dimensions (for example one row per horizon step) are kept;
    slots m..max_obstacles-1 are padding. `who` names the solver in the
    too-many-obstacles error.
    """
    c = np.asarray(centers, dtype=float)
    r = np.asarray(radii, dtype=float)
    m = c.shape[-2]
    M = check_capacity(max_obstacles, m, who)
    slots = np.zeros((*c.shape[:-2], M, WIDTH))
    slots[..., :, CENTER] = PAD_CENTER
    slots[..., :m, CENTER] = c
    slots[..., :m, RADIUS] = r
    slots[..., :m, ACTIVE] = 1.0
    return slots.reshape(*c.shape[:-2], WIDTH * M)


def padding(max_obstacles: int) -> np.ndarray:
    """A packed vector (WIDTH * max_obstacles,) with every slot padding (no obstacles)."""
    return pack(np.zeros((0, 3)), np.zeros(0), max_obstacles)


def unpack(packed: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centres (..., K, 3) mm, radii (..., K) mm, active (..., K)) from packed (..., WIDTH * K)."""
    v = np.asarray(packed, dtype=float)
    v = v.reshape(*v.shape[:-1], -1, WIDTH)
    return v[..., CENTER], v[..., RADIUS], v[..., ACTIVE]


def slot(packed: Any, i: int) -> tuple[Any, Any, Any]:
    """(centre (3), radius, active) of slot i of a packed vector; works on CasADi symbols and numpy alike."""
    base = WIDTH * i
    return packed[base + CENTER.start : base + CENTER.stop], packed[base + RADIUS], packed[base + ACTIVE]


def active_flags(packed: Any) -> np.ndarray:
    """The active flags (K,) of a flat packed vector, as booleans."""
    return np.asarray(packed, dtype=float)[ACTIVE::WIDTH] > 0
