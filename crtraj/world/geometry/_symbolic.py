"""The primitives' signed distances as CasADi expressions, for NLPs (mm).

`casadi_distance(shape, x, origin, rotation, scale)` is the signed distance from a point x (3, 1) to the
shape whose frame sits at `origin` with `rotation` (by default the shape's own pose) and is scaled by
`scale`; any of them may be symbolic.

- sphere, half space: the exact distance (the sphere's is not differentiable at its centre only).
- capsule: the exact distance, continuously differentiable outside; the clamp along the axis makes its
  second derivative jump where the segment's ends project, and it is not differentiable on the axis.
- box and cylinder: a C-infinity LOWER bound of the exact distance, within `BOX_SMOOTH_ERROR * smooth`
  mm of it. The exact box distance is ``|max(q, 0)| + min(max_i q_i, 0)`` with ``q_i = |y_i| - h_i``; it
  grows with every q_i. Each non-smooth piece is replaced by a smooth one below it:
  ``|y_i| -> sqrt(y_i^2 + k^2) - k`` (at most k below), ``max(q, 0) -> softplus_k(q)`` and the norm then
  lowered by ``sqrt(n) k ln 2`` (softplus exceeds max by at most k ln 2), ``max_i q_i -> LSE_k(q) - k ln n``
  (at most k ln n below), and ``min(b, 0) -> -softplus_k(-b)`` (at most k ln 2 below), with k = `smooth`
  mm and n = 3 (box) or 2 (cylinder, in the coordinates (radial, axial)). The total shortfall is at most
  ``k ((sqrt(n) + 1) + sqrt(n) ln 2 + ln n + ln 2 + 1e-6)`` (the last term keeps the gradient finite deep
  inside, where every softplus rounds to zero), which for n = 3 is `BOX_SMOOTH_ERROR` k (about 5.72 k).
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca

from crtraj.core.errors import InputError
from crtraj.world.geometry._shapes import Box, Capsule, Cylinder, HalfSpace, Shape, Sphere

_EPS = 1.0e-6
# Largest shortfall of the smooth box (and cylinder) distance below the exact one, per mm of `smooth`.
BOX_SMOOTH_ERROR = (math.sqrt(3.0) + 1.0) + math.sqrt(3.0) * math.log(2.0) + math.log(3.0) + math.log(2.0) + _EPS


def _softplus(q: Any, k: float) -> Any:
    """k ln(1 + e^(q/k)), written so that it cannot overflow (the same smooth function)."""
    return ca.fmax(q, 0.0) + k * ca.log(1.0 + ca.exp(-ca.fabs(q) / k))


def _smooth_box(q: list[Any], k: float) -> Any:
    """The smooth lower bound of |max(q, 0)| + min(max_i q_i, 0) (module docstring)."""
    n = len(q)
    soft = [_softplus(qi, k) for qi in q]
    # + eps^2 under the root keeps the gradient finite where every softplus rounds to 0 (deep inside);
    # - eps after it keeps the result below sqrt(sum), so still a lower bound (eps is in BOX_SMOOTH_ERROR)
    eps = _EPS * k
    outside = ca.sqrt(sum(si * si for si in soft) + eps * eps) - eps - math.sqrt(n) * k * math.log(2.0)
    m = q[0]
    for qi in q[1:]:
        m = ca.fmax(m, qi)
    lse = m + k * ca.log(sum(ca.exp((qi - m) / k) for qi in q)) - k * math.log(n)
    return outside - _softplus(-lse, k)


def _lowered_abs(v: Any, k: float) -> Any:
    """sqrt(v^2 + k^2) - k: smooth, at most |v| and at least |v| - k."""
    return ca.sqrt(v * v + k * k) - k


def casadi_distance(
    shape: Shape,
    x: Any,
    origin: Any = None,
    rotation: Any = None,
    scale: Any = 1.0,
    smooth: float = 0.5,
) -> Any:
    """Signed distance (mm) from x (3, 1) to `shape` framed at `origin` (3,) mm, `rotation` (3, 3) and
    `scale`; origin and rotation default to the shape's pose. `smooth` (mm) is the box and cylinder
    smoothing length k (module docstring); other shapes are exact."""
    if not smooth > 0.0:
        raise InputError(f"smooth: must be > 0 mm, got {smooth:g}")
    o = ca.DM(shape.pose.position) if origin is None else origin
    r = ca.DM(shape.pose.matrix) if rotation is None else rotation
    y = ca.mtimes(ca.transpose(r), x - o)
    if isinstance(shape, Sphere):
        return ca.norm_2(y) - scale * shape.radius
    if isinstance(shape, HalfSpace):
        return ca.dot(ca.DM(shape.normal), y) - scale * shape.offset
    if isinstance(shape, Capsule):
        half = 0.5 * scale * shape.length
        c = ca.fmin(ca.fmax(y[2], -half), half)
        return ca.norm_2(ca.vertcat(y[0], y[1], y[2] - c)) - scale * shape.radius
    if isinstance(shape, Box):
        q = [_lowered_abs(y[i], smooth) - scale * shape.half_extents[i] for i in range(3)]
        return _smooth_box(q, smooth)
    if isinstance(shape, Cylinder):
        rho = ca.sqrt(y[0] * y[0] + y[1] * y[1] + smooth * smooth) - smooth
        q = [rho - scale * shape.radius, _lowered_abs(y[2], smooth) - 0.5 * scale * shape.length]
        return _smooth_box(q, smooth)
    raise InputError(f"shape: no CasADi distance for {type(shape).__name__}")
