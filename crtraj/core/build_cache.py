"""The build cache: compiled artifacts (shared libraries of generated C), built once and reused.

A compiled artifact is named by a `BuildKey`: a name and a JSON-able description of everything the
generated code depends on (the robot's canonical description, the options that shape the code, a
generator version). The cache adds the environment (CasADi version, Python, platform, the C compiler)
and hashes it all into the entry's folder name::

    <root>/<name>-<digest>/lib<name>-<sha>.so  the library (sha: start of its SHA-256)
    <root>/<name>-<digest>/manifest.json       key, environment, SHA-256 and size of the library

`BuildCache.library` returns the library of a key, building it when missing. A build happens in a
temporary folder under the root, which is renamed into place only when complete, so a crash or a
concurrent build never leaves a half-written entry under its final name. Before an entry is used its
manifest must name the same key and environment and its library must have the recorded SHA-256; a
corrupt or foreign entry is rebuilt, never loaded. `BuildCache.load` also rebuilds, once, an entry
whose library verifies but does not load.

The cache deletes only folders that carry crtraj's marker (`crtraj.core.fileio.mark_folder`: entries,
and its own ``.tmp-``/``.trash-`` folders), so a ``$CRTRAJ_CACHE_DIR`` pointed at a folder of the user's
never loses a file: whatever else sits where an entry belongs (a file, a folder of the user's) is
renamed aside (``.aside-<name>-<random>``, kept) and the entry rebuilt.

Location: ``$CRTRAJ_CACHE_DIR`` when set, else the user cache directory (``platformdirs``, e.g.
``~/.cache/crtraj`` on Linux). Compiler: ``$CRTRAJ_CC`` when set (``none`` disables compilation),
else the first of cc, gcc, clang on PATH. Without a compiler `library` returns None and the caller
stays on its interpreted path; the cache says so once (a warning of the ``crtraj`` logger).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import platformdirs

from crtraj import __version__
from crtraj.core.errors import InputError
from crtraj.core.fileio import atomic_write_json, is_marked, mark_folder, read_json, remove_marked, to_jsonable
from crtraj.core.interrupt import run_guarded

log = logging.getLogger(__name__)

# Layout version of an entry (manifest fields, file names, marker): a change makes every old entry foreign.
FORMAT = 2
MANIFEST = "manifest.json"
# The kinds of crtraj's marker (`mark_folder`) on a finished entry and on the cache's temporary folders.
ENTRY_KIND = "build-cache-entry"
TEMP_KIND = "build-cache-temp"
# A manifest is a few kB; anything larger is not one of ours.
_MAX_MANIFEST_BYTES = 1024 * 1024
# Hex digits of the key digest in an entry's folder name (96 bits: collisions are not a concern, and a
# colliding foreign entry would still be caught by the manifest check).
_DIGEST_CHARS = 24
# Longest a single compile may take before it is abandoned (s): generated validity code compiles in
# seconds; a hung compiler must not hang a command.
COMPILE_TIMEOUT = 600.0
# Optimisation flags of every build: no -march=native (a cache folder may be shared between machines of
# one platform), no fast-math and no fused multiply-adds (compiled and numpy arithmetic must agree, inf
# included: the edge checks redo numpy's sums in C, operation for operation).
CFLAGS = ("-O2", "-fPIC", "-shared", "-ffp-contract=off")
_LIB_SUFFIX = ".dylib" if sys.platform == "darwin" else ".dll" if sys.platform == "win32" else ".so"


@dataclass(frozen=True)
class BuildKey:
    """What one compiled artifact depends on, besides the environment.

    name: a short artifact name (letters, digits, ``_``; it names the folder and the library).
    spec: JSON-able description of the generated code's inputs (robot description, options, generator
    version); two keys with equal name and spec name the same artifact.
    """

    name: str
    spec: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.name or len(self.name) > 64 or not self.name.replace("_", "").isalnum():
            raise InputError(f"build key name: must be 1-64 letters, digits or '_', got {self.name!r}")

    def canonical(self) -> dict[str, Any]:
        """The key as plain JSON data (numpy arrays as lists), as stored in the manifest."""
        return {"name": self.name, "spec": json.loads(_canonical_json(self.spec))}


@dataclass(frozen=True)
class CacheEntry:
    """One entry of the cache: its folder, name, key digest, library size (bytes), whether it verifies, and
    its state in words: ``ok``, ``corrupt`` (rebuilt on next use), ``unreadable manifest: ...`` or
    ``not crtraj's`` (no marker: `BuildCache.clear` leaves it alone)."""

    path: Path
    name: str
    digest: str
    size: int
    valid: bool
    state: str = "ok"


def _canonical_json(obj: Any) -> str:
    """One text per value: sorted keys, no spaces, numpy converted (so equal keys hash equally)."""
    return json.dumps(to_jsonable(obj), sort_keys=True, separators=(",", ":"), allow_nan=False)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def default_root() -> Path:
    """The cache folder: ``$CRTRAJ_CACHE_DIR`` or the user cache directory of crtraj."""
    env = os.environ.get("CRTRAJ_CACHE_DIR")
    return Path(env) if env else Path(platformdirs.user_cache_dir("crtraj", appauthor=False))


def find_compiler() -> str | None:
    """The C compiler to build with: ``$CRTRAJ_CC`` (``none``/empty: none), else cc, gcc or clang on PATH."""
    env = os.environ.get("CRTRAJ_CC")
    if env is not None:
        if env.strip().lower() in ("", "none", "0", "off"):
            return None
        return shutil.which(env)
    return shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")


def compile_shared(compiler: str, sources: list[Path], out: Path, flags: tuple[str, ...] = ()) -> Path:
    """Compile C `sources` into the shared library `out`; RuntimeError with the compiler's last line on failure."""
    cmd = [compiler, *CFLAGS, *flags, "-o", str(out), *map(str, sources), "-lm"]
    try:
        proc = run_guarded(cmd, timeout=COMPILE_TIMEOUT)  # the compiler's own children die with this process too
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"C compiler {compiler}: no result after {COMPILE_TIMEOUT:.0f} s") from None
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise RuntimeError(f"C compiler {compiler} failed ({proc.returncode}): {last}")
    return out


class BuildCache:
    """Compiled libraries by key, in one cache folder (see the module docstring).

    root: the cache folder (default `default_root`). compiler: path of the C compiler; the default
    (``...``) looks it up with `find_compiler`; None builds nothing. notice: a text stream for the one-line
    no-compiler notice (default: a warning of the ``crtraj`` logger), once per instance.
    """

    def __init__(self, root: str | os.PathLike[str] | None = None, *, compiler: Any = ..., notice: Any = None) -> None:
        self.root = Path(root) if root is not None else default_root()
        self.compiler: str | None = find_compiler() if compiler is ... else compiler
        self._notice = notice
        self._noticed = False
        self._env: dict[str, Any] | None = None
        self.builds = 0  # libraries built by this instance (a statistic; tests read it)

    # ------------------------------------------------------------ environment
    def environment(self) -> dict[str, Any]:
        """What every artifact depends on besides its key: versions, platform and the compiler's identity."""
        if self._env is None:
            try:
                casadi_version = metadata.version("casadi")
            except metadata.PackageNotFoundError:
                casadi_version = "none"
            cc: dict[str, Any] | None = None
            if self.compiler is not None:
                real = os.path.realpath(self.compiler)
                st = os.stat(real)
                # the binary's identity (a compiler upgrade replaces it) without running it
                cc = {"path": real, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
            self._env = {
                "format": FORMAT,
                "crtraj": __version__,
                "casadi": casadi_version,
                "python": f"{sys.implementation.name}-{sys.version_info[0]}.{sys.version_info[1]}",
                "platform": f"{sys.platform}-{platform.machine()}",
                "compiler": cc,
                "cflags": list(CFLAGS),
            }
        return self._env

    def available(self) -> bool:
        """True when libraries can be built here; otherwise says so once (one stderr line) and returns False."""
        if self.compiler is not None:
            return True
        if not self._noticed:
            self._noticed = True
            msg = "no C compiler found (cc, gcc or clang; or CRTRAJ_CC=none): using the interpreted CasADi path"
            msg += " (correct, slower)"
            if self._notice is not None:
                print(f"crtraj: {msg}", file=self._notice)
            else:
                log.warning(msg)
        return False

    def digest(self, key: BuildKey) -> str:
        """The hex digest that names `key`'s entry in this environment."""
        text = _canonical_json({"key": key.canonical(), "env": self.environment()})
        return hashlib.sha256(text.encode("utf-8")).hexdigest()[:_DIGEST_CHARS]

    def entry_dir(self, key: BuildKey) -> Path:
        """The folder of `key`'s entry (it may not exist yet)."""
        return self.root / f"{key.name}-{self.digest(key)}"

    def library_name(self, key: BuildKey, sha256: str) -> str:
        """File name of `key`'s library of content hash `sha256` inside its entry folder."""
        return f"lib{key.name}-{sha256[:16]}{_LIB_SUFFIX}"

    # --------------------------------------------------------------- entries
    def _verify(self, entry: Path, key: BuildKey | None) -> Path | None:
        """The library of a complete, intact entry (for `key`, when given); None for a corrupt or foreign one."""
        try:
            man = read_json(entry / MANIFEST, _MAX_MANIFEST_BYTES)
        except (InputError, OSError):
            return None
        if not isinstance(man, dict) or man.get("format") != FORMAT:
            return None
        if key is not None and (
            man.get("key") != key.canonical()
            or man.get("env") != json.loads(_canonical_json(self.environment()))
            or man.get("digest") != self.digest(key)
        ):
            return None
        name = man.get("library")
        if not isinstance(name, str) or "/" in name or name.startswith("."):
            return None
        lib = entry / name
        try:
            if not lib.is_file() or lib.stat().st_size != man.get("size") or _sha256(lib) != man.get("sha256"):
                return None
        except OSError:
            return None
        return lib

    def lookup(self, key: BuildKey) -> Path | None:
        """The verified library of `key` if it is in the cache, else None (nothing is built or removed)."""
        entry = self.entry_dir(key)
        return self._verify(entry, key) if entry.is_dir() and not entry.is_symlink() else None

    def library(self, key: BuildKey, build: Callable[[Path, str], Path]) -> Path | None:
        """The library of `key`: from the cache when it verifies, else built now; None without a compiler.

        build(folder, compiler) writes the library into the temporary `folder` (holding only crtraj's
        marker; generate C there, then `compile_shared`) and returns its path. A corrupt entry is removed,
        anything else under the entry's name moved aside, and the entry rebuilt. A failing build raises
        (RuntimeError from `compile_shared`) and leaves the cache as it was.
        """
        entry = self.entry_dir(key)
        lib = self.lookup(key)
        if lib is not None:
            return lib
        if not self.available():
            return None
        assert self.compiler is not None
        self.root.mkdir(parents=True, exist_ok=True)
        if os.path.lexists(entry):
            self._clear_way(entry)
        tmp = self._temp_dir(f".tmp-{key.name}-")
        try:
            built = Path(build(tmp, self.compiler))
            if built.parent.resolve() != tmp.resolve() or not built.is_file():
                raise RuntimeError(f"build of {key.name}: no library written into its folder (got {built})")
            # the file name carries its content hash: a process that loaded an entry's library keeps the
            # mapping of that file, and dlopen of a rebuilt entry's (other) bytes must not find it by name
            final = tmp / self.library_name(key, _sha256(built))
            if built != final:
                built.replace(final)
            self._write_manifest(tmp, key, final)
            mark_folder(tmp, ENTRY_KIND)
            self.builds += 1
            try:
                os.rename(tmp, entry)
            except OSError:
                # another process finished the same entry first: use theirs if it verifies
                lib = self.lookup(key)
                if lib is None:
                    raise
                return lib
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
        return entry / final.name

    def load(self, key: BuildKey, build: Callable[[Path, str], Path], loader: Callable[[Path], Any]) -> Any:
        """``loader(library)`` of `key`'s library (see `library`); None without a compiler. A library that
        verifies but does not load (OSError or a missing symbol from ``loader``) is rebuilt once; when the
        rebuilt one fails too, RuntimeError names the entry."""
        lib = self.library(key, build)
        if lib is None:
            return None
        try:
            return loader(lib)
        except (OSError, AttributeError) as exc:
            log.warning("build cache entry %s does not load (%s); rebuilding it", lib.parent.name, exc)
            self._discard(lib.parent)
        lib = self.library(key, build)
        try:
            return loader(lib)
        except (OSError, AttributeError) as exc:
            raise RuntimeError(f"build cache entry {lib.parent}: the rebuilt library does not load ({exc})") from None

    def _write_manifest(self, folder: Path, key: BuildKey, lib: Path) -> None:
        manifest = {
            "format": FORMAT,
            "digest": self.digest(key),
            "key": key.canonical(),
            "env": self.environment(),
            "library": lib.name,
            "size": lib.stat().st_size,
            "sha256": _sha256(lib),
        }
        atomic_write_json(folder / MANIFEST, manifest)

    def _temp_dir(self, prefix: str) -> Path:
        """A new folder under the root that carries the cache's temporary marker (so `clear` may remove it)."""
        tmp = Path(tempfile.mkdtemp(prefix=prefix, dir=self.root))
        mark_folder(tmp, TEMP_KIND)
        return tmp

    def _clear_way(self, entry: Path) -> None:
        """Make room for `key`'s entry: a corrupt or foreign entry of crtraj's is removed; anything else
        there (a file, a link, a folder of the user's) is renamed aside, never deleted."""
        if is_marked(entry, ENTRY_KIND):
            self._discard(entry)
            return
        aside = self.root / f".aside-{entry.name}-{os.urandom(4).hex()}"
        with contextlib.suppress(FileNotFoundError):  # someone else moved it already
            os.rename(entry, aside)
            log.warning("build cache: %s is not a cache entry; moved it to %s and rebuilt the entry", entry, aside)

    def _discard(self, entry: Path) -> None:
        """Remove an entry of crtraj's (it carries the marker): moved aside in one rename, so no reader sees
        it half removed, then deleted. Anything without the marker is left alone."""
        trash = self._temp_dir(".trash-")
        try:
            remove_marked(entry, ENTRY_KIND, trash)
        finally:
            shutil.rmtree(trash, ignore_errors=True)

    def entries(self) -> list[CacheEntry]:
        """Every entry of the cache (the folders with a manifest or crtraj's entry marker), each verified and
        described (`CacheEntry.state`); an unreadable manifest (a FIFO, bad JSON) is listed as such."""
        if not self.root.is_dir():
            return []
        out = []
        for d in sorted(self.root.iterdir()):
            if d.name.startswith(".") or d.is_symlink() or not d.is_dir():
                continue
            marked = is_marked(d, ENTRY_KIND)
            if not marked and not os.path.lexists(d / MANIFEST):
                continue
            name, _, digest = d.name.rpartition("-")
            lib = self._verify(d, None)
            problem = None if lib is not None else _manifest_problem(d / MANIFEST)
            state = "ok" if lib is not None else problem or "corrupt"
            if not marked:
                state = "; ".join(x for x in (problem, "not crtraj's (no marker; left alone)") if x)
            out.append(CacheEntry(d, name, digest, lib.stat().st_size if lib else 0, lib is not None, state))
        return out

    def clear(self) -> int:
        """Remove every entry and leftover temporary folder of this cache; the number of entries removed.

        Only folders carrying crtraj's marker are removed (and empty ``.tmp-``/``.trash-`` folders a killed
        build left), so pointing CRTRAJ_CACHE_DIR at a folder with other files never deletes them.
        """
        n = 0
        for e in self.entries():
            if is_marked(e.path, ENTRY_KIND):
                self._discard(e.path)
                n += 1
        if self.root.is_dir():
            for d in self.root.iterdir():
                if d.name.startswith((".tmp-", ".trash-")) and not d.is_symlink() and d.is_dir():
                    if is_marked(d, TEMP_KIND):
                        shutil.rmtree(d, ignore_errors=True)
                    else:
                        with contextlib.suppress(OSError):  # only when empty
                            os.rmdir(d)
        return n


def _manifest_problem(manifest: Path) -> str | None:
    """Why an entry's manifest cannot be read (one short phrase), or None when it reads as JSON."""
    try:
        read_json(manifest, _MAX_MANIFEST_BYTES)
    except (InputError, OSError) as exc:
        text = str(exc.strerror if isinstance(exc, OSError) and exc.strerror else exc)
        return "unreadable manifest: " + text.replace(str(manifest), "").strip(" :")[:120]
    return None
