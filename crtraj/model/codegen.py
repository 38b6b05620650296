"""CasADi functions compiled through the build cache: generate C, compile once, load the cached library.

`codegen_builder(functions, name)` is the build step `crtraj.core.build_cache.BuildCache.library`
runs on a miss: CasADi writes the functions' C into the temporary entry folder and the C compiler
turns it into a shared library. `load_functions` returns them again as ``casadi.external`` Functions
(same names, inputs and outputs as the originals), so callers evaluate the compiled code through the
same CasADi interface. `compiled_functions` does both: cached, or built, or None without a compiler.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable, Sequence
from pathlib import Path

import casadi as ca

from crtraj.core.build_cache import BuildCache, BuildKey, compile_shared


def codegen_builder(
    make: Callable[[], Sequence[ca.Function]], name: str, extra_c: str = "", flags: tuple[str, ...] = ()
) -> Callable[[Path, str], Path]:
    """The build step of a cache entry: C of the functions `make()` returns, followed by `extra_c` (a
    hand-written driver calling them, say), generated into the folder and compiled to lib<name>.so
    (`flags` after the cache's own, so ``("-O0",)`` overrides its optimisation level; they must be part of the
    entry's key).

    `make` runs only when the step runs (a cache miss), so a hit never builds the CasADi graphs.
    """

    def build(folder: Path, compiler: str) -> Path:
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        for f in make():
            gen.add(f)
        src = folder / f"{name}.c"
        src.write_text(gen.dump() + extra_c, encoding="utf-8")
        return compile_shared(compiler, [src], folder / f"lib{name}.so", flags)

    return build


def load_functions(library: Path, names: Sequence[str]) -> dict[str, ca.Function]:
    """The functions `names` of a compiled library, as ``casadi.external`` Functions.

    A library that does not load (not a shared object, truncated, a missing function) raises OSError with
    a short reason: the error `BuildCache.load` rebuilds on (CasADi's own is a many-line RuntimeError).
    """
    ctypes.CDLL(str(library))  # OSError with dlopen's one-line reason ("<path>: invalid ELF header") first
    try:
        return {n: ca.external(n, str(library)) for n in names}
    except RuntimeError as exc:
        raise OSError(f"{library.name}: {_reason(exc)}") from None


def _reason(exc: BaseException) -> str:
    """The last non-empty line of an error's first paragraph, at most 200 characters (CasADi's errors
    carry a source location and a search-path listing around the reason)."""
    lines = [ln.strip() for ln in str(exc).split("\n\n")[0].splitlines() if ln.strip()]
    return (lines[-1] if lines else type(exc).__name__)[:200]


def compiled_functions(
    cache: BuildCache,
    key: BuildKey,
    names: Sequence[str],
    make: Callable[[], Sequence[ca.Function]],
    flags: tuple[str, ...] = (),
) -> dict[str, ca.Function] | None:
    """The functions `names` of `key`, loaded from the cache (built from `make()` on a miss); None without
    a compiler.

    `make` builds the CasADi graphs; it runs only when the library must be built, never on a hit, so a
    cached start-up does not pay for the symbolic construction. A cached library that passes the hash
    check but does not load is rebuilt once (`BuildCache.load`); when the rebuilt one does not load either,
    RuntimeError says so in one line.
    """

    def checked() -> Sequence[ca.Function]:
        funcs = list(make())
        got = sorted(f.name() for f in funcs)
        if got != sorted(names):
            raise RuntimeError(f"build of {key.name}: made functions {got}, expected {sorted(names)}")
        return funcs

    return cache.load(key, codegen_builder(checked, key.name, flags=flags), lambda lib: load_functions(lib, names))
