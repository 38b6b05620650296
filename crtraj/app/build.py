"""Use case: build a robot's compiled artifacts ahead of time, list or clear the build cache (`crtraj build`).

Every command builds what it needs on first use and reuses it afterwards (`crtraj.core.build_cache`);
``crtraj build --robot FILE`` does those builds now, so the first plan or replan does not pay for them.
The validity kernels are built for the check-point counts crtraj's own defaults use (planner, closed
loop, device verification) and for every ``--check-points`` given.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

from crtraj.control.loop import LoopOptions
from crtraj.core.build_cache import BuildCache, CacheEntry
from crtraj.core.errors import InputError
from crtraj.hardware.verify import VerifyOptions
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.options import PlannerOptions
from crtraj.planning.validity import MAX_COMPILED_POINTS, ValidityKernel


@dataclass(frozen=True)
class Built:
    """One artifact `crtraj build` made or found: what it is, its library, and the time it took (s)."""

    what: str
    library: str
    seconds: float


def default_check_points() -> list[int]:
    """The check-point counts of crtraj's defaults: planner, closed-loop verification, device verification."""
    return sorted({PlannerOptions().check.points, LoopOptions().check_points, VerifyOptions().check_points})


def build_validity(model: Model, cache: BuildCache, check_points: list[int]) -> list[Built]:
    """The validity kernels of `model` at each count of `check_points`."""
    out = []
    for n in check_points:
        t1 = time.perf_counter()
        k = ValidityKernel.load(model, n, cache)
        if k is not None:
            out.append(Built(f"validity kernel, {n} check points", str(k.library), time.perf_counter() - t1))
    return out


# Every kind of artifact `crtraj build` makes: (model, cache, check point counts) -> what was built.
ARTIFACTS: tuple[Callable[[Model, BuildCache, list[int]], list[Built]], ...] = (build_validity,)


def _state_text(e: CacheEntry) -> str:
    """How `crtraj build --list` shows an entry's state."""
    if e.valid:
        return "ok"
    if e.state == "corrupt":
        return "CORRUPT (rebuilt on next use)"
    if e.state.startswith("unreadable "):
        return "UNREADABLE " + e.state.removeprefix("unreadable ")
    return e.state


def build_command(args: argparse.Namespace) -> int:
    """`crtraj build ...` (arguments from `crtraj.cli`); returns the exit code."""
    cache = BuildCache()
    if args.clear:
        n = cache.clear()
        print(f"removed {n} entries from {cache.root}")
        return 0
    if args.list:
        entries = cache.entries()
        print(f"build cache {cache.root}: {len(entries)} entries")
        for e in entries:
            print(f"  {e.path.name}  {e.size / 1024:.0f} kB  {_state_text(e)}")
        return 0
    points = sorted(set(default_check_points() + list(args.check_points or [])))
    bad = [n for n in points if not 2 <= n <= MAX_COMPILED_POINTS]
    if bad:
        raise InputError(f"--check-points: must be in [2, {MAX_COMPILED_POINTS}], got {bad[0]}")
    robot = load_robot(args.robot)
    if cache.compiler is None:  # said here, not by the cache's warning (which -q silences): it is the failure
        print(
            "crtraj: build failed: no C compiler found (cc, gcc or clang, or CRTRAJ_CC names none); install one "
            "(Debian: apt-get install gcc) or set CRTRAJ_CC to it",
            file=sys.stderr,
        )
        return 1
    model = Model(robot)
    try:
        built = [b for make in ARTIFACTS for b in make(model, cache, points)]
    except OSError as exc:
        raise InputError(f"build cache {cache.root}: cannot write there ({exc.strerror or exc})") from None
    except RuntimeError as exc:  # the C compiler failed: nothing was cached
        print(f"crtraj: build failed: {exc}", file=sys.stderr)
        return 1
    print(f"robot '{robot.name}': {len(built)} artifacts in {cache.root}")
    for b in built:
        print(f"  {b.what}: {b.library} ({b.seconds:.2f} s)")
    return 0
