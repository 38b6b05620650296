"""CasADi functions compiled to C once, cached, and called through ctypes on preallocated numpy buffers.

`compiled_library(name, functions)` generates the C of `functions` (a whole ``sqpmethod`` solver with
its QP solver included, when the QP solver is code-generatable: qrqp, or daqp linked statically from
CasADi's own copy), compiles it once into the build cache (`crtraj.core.build_cache`, keyed by the
SHA-256 of the generated source plus the cache's environment: CasADi, Python, platform, compiler) and
returns the library (None without a C compiler, said once on stderr).

CasADi's generated C exposes, per function ``name``: ``name(arg, res, iw, w, mem)``, its work sizes
(``name_work``), the sparsity of every input and output (``name_sparsity_in/out``) and a memory
checkout. `CompiledFunction` reads those once, allocates every buffer once and then evaluates the
function with one foreign call: no CasADi object, no DM conversion and no dictionary per call (a call
through ``casadi.external`` costs tens of microseconds in conversions; this one a few).

Inputs and outputs are the functions' nonzeros in CasADi's column-major order (dense vectors and
matrices as CasADi stores them). The caller owns thread safety: one instance serves one thread.
"""

from __future__ import annotations

import ctypes
import hashlib
from collections.abc import Sequence
from pathlib import Path

import casadi as ca
import numpy as np

from crtraj.core.build_cache import BuildCache, BuildKey, compile_shared

# Live `CompiledFunction`s of one function at a time (memory slots compiled into the library).
MAX_INSTANCES = 64
# QP solvers whose CasADi interface generates C (daqp: linked from CasADi's static library)
CODEGEN_QP = ("daqp", "qrqp", "hpipm")

_INT = ctypes.c_longlong  # casadi_int (long long in CasADi's generated code)


def _nnz(sp: ctypes._Pointer) -> tuple[int, int, int]:
    """(rows, columns, nonzeros) of a sparsity pattern in CasADi's compact form."""
    nrow, ncol = int(sp[0]), int(sp[1])
    if int(sp[2]) == 1 and ncol >= 1 and _dense_flag(sp, ncol):
        return nrow, ncol, nrow * ncol
    return nrow, ncol, int(sp[2 + ncol])


def _dense_flag(sp: ctypes._Pointer, ncol: int) -> bool:
    # a general pattern's column index starts at 0; CasADi writes a dense one as (nrow, ncol, 1)
    return int(sp[2]) == 1


class CompiledFunction:
    """The generated C function `name` in the shared library `library` (a path).

    `n_in`, `n_out`; `shape_in[i]`/`shape_out[i]` (rows, columns) and `nnz_in`/`nnz_out`.
    `__call__(*inputs)` copies each input (None: CasADi's default, zeros for most functions) into
    its buffer, evaluates, and returns the output buffers (views reused by the next call: copy what
    you keep). RuntimeError when the function reports an evaluation error (its return code).
    """

    def __init__(self, library: str | Path, name: str) -> None:
        self.name = name
        self._lib = ctypes.CDLL(str(library))
        lib = self._lib
        fn = getattr(lib, name)
        fn.restype = ctypes.c_int
        fn.argtypes = [ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_void_p), ctypes.c_void_p]
        fn.argtypes += [ctypes.c_void_p, ctypes.c_int]
        self._fn = fn
        for suffix, res, args in (
            ("_n_in", _INT, []),
            ("_n_out", _INT, []),
            ("_sparsity_in", ctypes.POINTER(_INT), [_INT]),
            ("_sparsity_out", ctypes.POINTER(_INT), [_INT]),
            ("_work", ctypes.c_int, [ctypes.POINTER(_INT)] * 4),
            ("_checkout", ctypes.c_int, []),
            ("_release", None, [ctypes.c_int]),
            ("_incref", None, []),
            ("_decref", None, []),
        ):
            f = getattr(lib, name + suffix)
            f.restype = res
            f.argtypes = args
        self.n_in = int(getattr(lib, name + "_n_in")())
        self.n_out = int(getattr(lib, name + "_n_out")())
        shapes_in = [_nnz(getattr(lib, name + "_sparsity_in")(i)) for i in range(self.n_in)]
        shapes_out = [_nnz(getattr(lib, name + "_sparsity_out")(i)) for i in range(self.n_out)]
        self.shape_in = [(r, c) for r, c, _ in shapes_in]
        self.shape_out = [(r, c) for r, c, _ in shapes_out]
        self.nnz_in = [n for _, _, n in shapes_in]
        self.nnz_out = [n for _, _, n in shapes_out]
        sz = [_INT() for _ in range(4)]
        if getattr(lib, name + "_work")(*[ctypes.byref(s) for s in sz]):
            raise RuntimeError(f"{name}: the compiled library reports no work sizes")
        sz_arg, sz_res, sz_iw, sz_w = (max(int(s.value), 1) for s in sz)
        getattr(lib, name + "_incref")()
        self._mem = int(getattr(lib, name + "_checkout")())
        if self._mem < 0:
            getattr(lib, name + "_decref")()
            del self._mem
            raise RuntimeError(f"{name}: more than {MAX_INSTANCES} live instances of the compiled function")
        self._in = [np.zeros(n) for n in self.nnz_in]
        self._out = [np.zeros(n) for n in self.nnz_out]
        self._iw = np.zeros(sz_iw, dtype=np.int64)
        self._w = np.zeros(sz_w)
        # pointer tables as plain addresses: setting an entry from an int costs far less than a ctypes pointer
        self._arg = (ctypes.c_void_p * max(sz_arg, self.n_in))()
        self._res = (ctypes.c_void_p * max(sz_res, self.n_out))()
        self._in_addr = [a.ctypes.data for a in self._in]
        self._out_ptrs = [a.ctypes.data for a in self._out]
        self._iw_ptr = self._iw.ctypes.data
        self._w_ptr = self._w.ctypes.data

    def __call__(self, *inputs: np.ndarray | Sequence[float] | None) -> list[np.ndarray]:
        if len(inputs) > self.n_in:
            raise ValueError(f"{self.name}: {self.n_in} inputs, got {len(inputs)}")
        arg = self._arg
        for i in range(self.n_in):
            v = inputs[i] if i < len(inputs) else None
            if v is None:
                arg[i] = None  # CasADi's generated code reads a null input as zeros
            elif type(v) is np.ndarray and v.dtype == np.float64 and v.ndim == 1 and v.size == self.nnz_in[i]:
                arg[i] = v.ctypes.data if v.flags.c_contiguous else self._copy(i, v)
            else:
                arg[i] = self._copy(i, np.ravel(np.asarray(v, dtype=float), order="F"))
        res = self._res
        for i, ptr in enumerate(self._out_ptrs):
            res[i] = ptr  # generated code may use the pointer table as scratch: reset it every call
        if self._fn(arg, res, self._iw_ptr, self._w_ptr, self._mem):
            raise RuntimeError(f"{self.name}: evaluation failed in the compiled code")
        return self._out

    def _copy(self, i: int, v: np.ndarray) -> int:
        """Copy input i into its own buffer (shape checked); the buffer's address."""
        if v.size != self.nnz_in[i]:
            raise ValueError(f"{self.name}: input {i} needs {self.nnz_in[i]} numbers, got {v.size}")
        self._in[i][:] = v
        return self._in_addr[i]

    def __del__(self) -> None:
        lib = getattr(self, "_lib", None)
        if lib is not None and hasattr(self, "_mem"):
            getattr(lib, self.name + "_release")(self._mem)
            getattr(lib, self.name + "_decref")()


def _casadi_dir() -> Path:
    return Path(ca.__file__).resolve().parent


def _qp_build(qpsol: str) -> tuple[tuple[str, ...], list[Path]]:
    """(compiler flags, extra link inputs) for the QP solver's generated interface."""
    root = _casadi_dir()
    if qpsol == "hpipm":
        # HPIPM and BLASFEO as the shared libraries CasADi ships, found at run time by the rpath
        inc = root / "include"
        return (f"-I{inc}", f"-I{inc / 'hpipm'}", f"-I{inc / 'blasfeo'}", f"-Wl,-rpath,{root}"), [
            root / "libhpipm.so",
            root / "libblasfeo.so",
        ]
    if qpsol != "daqp":
        return (), []
    return (f"-I{root / 'include'}", f"-I{root / 'include' / 'daqp'}"), [root / "libdaqpstat.a"]


def compiled_library(
    name: str, functions: Sequence[ca.Function], qpsol: str = "", cache: BuildCache | None = None
) -> tuple[Path | None, str]:
    """(shared library of `functions` from the build cache, one line saying what happened); (None, why)
    without a C compiler (the cache then says so once on stderr).

    The C is generated every time (tenths of a second) and its SHA-256 is the cache key, so a change of
    robot, options or obstacle count gives a new entry and an unchanged one is reused. A failing compile
    raises RuntimeError naming the compiler's last line.
    """
    cache = BuildCache() if cache is None else cache
    gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    for f in functions:
        gen.add(f)
    text = gen.dump()
    flags, libs = _qp_build(qpsol)
    # room for many live instances of one library (each checks out its own memory slot; the default is 1)
    flags = (f"-DCASADI_MAX_NUM_THREADS={MAX_INSTANCES}", *flags)
    spec = {"c_sha256": hashlib.sha256(text.encode("utf-8")).hexdigest(), "flags": list(flags), "libs": qpsol}
    key = BuildKey(name, spec)
    hit = cache.lookup(key)
    if hit is not None:
        return hit, f"compiled C ({hit.parent.name}, cached)"

    def build(folder: Path, compiler: str) -> Path:
        src = folder / f"{name}.c"
        src.write_text(text, encoding="utf-8")
        return compile_shared(compiler, [src, *libs], folder / f"lib{name}.so", flags)

    lib = cache.library(key, build)
    if lib is None:
        return None, "no C compiler found (cc, gcc, clang; or CRTRAJ_CC=none): using the interpreted solver"
    return lib, f"compiled C ({lib.parent.name}, built now)"
