"""The compiled kernels and CasADi functions that a planner's validators share, built once each.

A `Kernels` object holds the one `BuildCache` of its owner (a planning context, the loop, a frame
verifier), the compiled validity kernel per check-point count and the interpreted CasADi clearance
and backbone functions per (kind, check points, obstacles, batch size). Validators of different
scenes built with the same `Kernels` reuse all of them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from crtraj.core.build_cache import BuildCache
from crtraj.model.kinematics import Model
from crtraj.planning.validity import _rod_body
from crtraj.planning.validity._compiled import MAX_COMPILED_POINTS, ValidityKernel
from crtraj.planning.validity._rod_kernel import RodKernel

log = logging.getLogger(__name__)

# (kind, check points, obstacle slots, batch size): "clearance" or "backbone"
FunctionKey = tuple[str, int, int, int]


class Kernels:
    """Compiled validity kernels and CasADi functions, each built once (see the module docstring).

    build_cache: where compiled libraries are kept (None: the default `BuildCache`, made when first
    needed). A test injects a cache in a temporary directory here.
    """

    def __init__(self, build_cache: BuildCache | None = None) -> None:
        self._build_cache = build_cache
        self._validity: dict[int, ValidityKernel | None] = {}
        self._functions: dict[FunctionKey, Any] = {}

    @property
    def build_cache(self) -> BuildCache:
        """The one build cache of this owner (so the no-compiler notice is given once)."""
        if self._build_cache is None:
            self._build_cache = BuildCache()
        return self._build_cache

    def validity_kernel(self, model: Model, check_points: int) -> ValidityKernel | None:
        """The compiled kernel for `model` at `check_points`, loaded (or built) once.

        None above `MAX_COMPILED_POINTS`, or when the build fails (logged once as a warning): the
        interpreted path gives the same result, only slower.
        """
        n = int(check_points)
        if n > MAX_COMPILED_POINTS:
            return None
        if n not in self._validity:
            try:
                kind = RodKernel if _rod_body.is_rod(model) else ValidityKernel
                self._validity[n] = kind.load(model, n, self.build_cache)
            except (RuntimeError, OSError) as exc:
                log.warning("compiled validity unavailable (%s): using the interpreted path", exc)
                self._validity[n] = None
        return self._validity[n]

    def function(self, key: FunctionKey, build: Callable[[], Any]) -> Any:
        """The CasADi function stored under `key`, built by `build()` the first time."""
        f = self._functions.get(key)
        if f is None:
            f = build()
            self._functions[key] = f
        return f
