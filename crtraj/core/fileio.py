"""Atomic file and folder writes, output-path checks and JSON encoding of results.

A result that was already written must survive a later crash, a kill or bad
input, so every file crtraj writes goes to a temporary file in the same folder
and is renamed over the target only when complete (`atomic_write_bytes`,
`StagedFile`). A run that writes several files (run.json, run.npz, run.png,
run.html) writes them into a temporary sibling folder that replaces the old
folder in one step (`StagedDir`): readers see the old set or the new set,
never a mix.

Nothing is committed after a stop was requested (Ctrl-C, SIGTERM: every commit first calls
`crtraj.core.interrupt.check`), and every temporary file or folder is known (`crtraj.core.interrupt.temporaries`)
until it is renamed or removed, so the command's last act removes whatever an interruption left.

Test hook: with the environment variables ``CRTRAJ_PAUSE_AT=<point>`` and
``CRTRAJ_PAUSE_SIGNAL=<file>`` set, the writer creates <file> when it reaches
<point> and then waits forever, so a test can kill it there without racing a
timer. Points: ``file-partial`` (half of a temporary file written),
``file-written`` (temporary file complete, not yet renamed), ``file-renamed``
(the file replaced, nothing after it done yet), ``dir-staged``
(new folder complete, not yet swapped in), ``dir-aside`` (only without an
atomic exchange: old folder renamed aside, new one not yet in) and
``dir-swapped`` (new folder in place, old one not yet removed).

Every file crtraj reads (problem and robot TOML, result JSON) goes through
`read_text`: it must be a regular file of at most a documented size
(`MAX_TOML_BYTES`, `MAX_JSON_BYTES`), UTF-8 text, and nested at most
`MAX_DEPTH` levels deep. Anything else is one `InputError` line naming the
file, never a traceback, a hang on a pipe or device, or a recursion error.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import json
import math
import os
import shutil
import stat
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.interrupt import check as check_interrupt
from crtraj.core.interrupt import shielded, temporaries

_RENAME_EXCHANGE = 2  # linux/fs.h: swap two paths atomically (renameat2, Linux >= 3.15)
_AT_FDCWD = -100


def checkpoint(point: str) -> None:
    """The kill-test hook (see the module docstring); a no-op unless CRTRAJ_PAUSE_AT names `point`."""
    if os.environ.get("CRTRAJ_PAUSE_AT") != point:
        return
    signal_file = os.environ.get("CRTRAJ_PAUSE_SIGNAL")
    if signal_file:
        Path(signal_file).write_text(f"{os.getpid()} {point}\n", encoding="utf-8")
    threading.Event().wait()  # until killed


def _fsync_dir(path: Path) -> None:
    """Make a rename in `path` durable (directories cannot be fsynced on every platform: best effort)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _umask() -> int | None:
    """The process umask, read without changing it (os.umask would race with other threads)."""
    try:
        for line in Path("/proc/self/status").read_text(encoding="ascii").splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return None


def _usual_mode(path: Path, directory: bool = False) -> None:
    """Give a temporary file or folder (created 0600 / 0700) the mode a plain open() or mkdir() would."""
    mask = _umask()
    if mask is not None:
        os.chmod(path, (0o777 if directory else 0o666) & ~mask)


def _write_synced(fh: Any, data: bytes) -> None:
    half = len(data) // 2
    fh.write(data[:half])
    fh.flush()
    checkpoint("file-partial")
    fh.write(data[half:])
    fh.flush()
    os.fsync(fh.fileno())


if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# Problem and robot files are hand-written tables: a few kB. 4 MiB leaves
# room for generated scenes without letting a wrong file exhaust memory.
MAX_TOML_BYTES = 4 * 1024 * 1024
# Result JSON (plan, replan, bench): a long replan run with backbone points
# per waypoint is a few MB; 256 MiB bounds the memory a parse can take.
MAX_JSON_BYTES = 256 * 1024 * 1024
# Deepest nesting of tables/arrays in any input file. crtraj's schemas go 4
# levels deep (tree.edges: list of pairs of points); parsers recurse per level.
MAX_DEPTH = 32


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write `data` to `path` atomically (temp file in the same folder + fsync + rename)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    temporaries.add(Path(tmp))
    try:
        _usual_mode(Path(tmp))
        with os.fdopen(fd, "wb") as fh:
            _write_synced(fh, data)
        checkpoint("file-written")
        check_interrupt()  # a stopped command replaces nothing
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    finally:
        temporaries.discard(Path(tmp))
    _fsync_dir(target.parent)
    checkpoint("file-renamed")
    return target


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 `text` to `path` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def to_jsonable(obj: Any) -> Any:
    """Convert numpy arrays/scalars, tuples, paths and objects with ``to_dict`` for JSON.

    Non-finite floats (NaN, +-inf) become null: JSON has no such numbers.
    """
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind in "biu" or (obj.dtype.kind == "f" and np.isfinite(obj).all()):
            return obj.tolist()  # plain numbers already: no per-element pass (result arrays are large)
        return to_jsonable(obj.tolist())
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "to_dict"):
        return to_jsonable(obj.to_dict())
    return obj


def json_document(data: Any) -> str:
    """Plain JSON data (`to_jsonable` output) as JSON text: a dict with one top-level key per line, each
    value compact. Readable at the top, and written by the C encoder (``indent`` would select the
    pure-Python one, which took seconds for a plan's thousands of waypoints)."""
    if not isinstance(data, dict) or not data:
        return json.dumps(data, allow_nan=False) + "\n"
    lines = [f"{json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in data.items()]
    return "{\n" + ",\n".join(lines) + "\n}\n"


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write `obj` as JSON (`json_document`) atomically."""
    return atomic_write_text(path, json_document(to_jsonable(obj)))


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


class StagedFile:
    """A temporary file beside `target` that replaces it only on `commit()`.

    Write to `path` (any way: it is a plain file); `commit()` fsyncs it and
    renames it over the target. Leaving the ``with`` block without a commit
    (an error, a refused run) removes it, so the target is never truncated.
    """

    def __init__(self, target: str | os.PathLike[str]) -> None:
        self.target = Path(target)
        self.target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.target.name}.", suffix=".tmp", dir=self.target.parent)
        os.close(fd)
        self.path = Path(tmp)
        temporaries.add(self.path)
        _usual_mode(self.path)
        self.committed = False

    def write(self, data: bytes) -> None:
        """Fill the staged file with `data` (replacing what it held)."""
        with open(self.path, "wb") as fh:
            _write_synced(fh, data)

    def commit(self) -> Path:
        """Make the staged file the target (atomic rename); returns the target."""
        _fsync_file(self.path)
        checkpoint("file-written")
        check_interrupt()  # a stopped command replaces nothing
        os.replace(self.path, self.target)
        temporaries.discard(self.path)
        _fsync_dir(self.target.parent)
        self.committed = True
        checkpoint("file-renamed")
        return self.target

    def discard(self) -> None:
        if not self.committed:
            self.path.unlink(missing_ok=True)
            temporaries.discard(self.path)

    def __enter__(self) -> StagedFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.discard()


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one atomic step (Linux renameat2 RENAME_EXCHANGE); False where unsupported."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):  # kernel or file system without exchange
        return False
    raise OSError(err, os.strerror(err), str(b))


def _asides(target: Path) -> list[Path]:
    return sorted(target.parent.glob(f".{target.name}.old-*"), key=lambda p: p.stat().st_mtime)


def recover_dir(target: str | os.PathLike[str]) -> None:
    """Undo a folder swap interrupted between its two renames (only where no atomic exchange exists):
    when `target` is missing and its previous version was set aside, put it back."""
    t = Path(target)
    if not t.exists():
        asides = _asides(t)
        if asides:
            os.rename(asides[-1], t)


class StagedDir:
    """A temporary folder beside `target` that replaces it as a whole on `commit()`.

    Write every file of the set into `path`; `commit()` fsyncs them and swaps
    the folder into place in one atomic step (renameat2 RENAME_EXCHANGE; else
    the old folder is renamed aside, the new one in, and `recover_dir` undoes
    an interruption between the two), then removes the old folder. `replaceable`:
    the only file names an existing target may hold (a folder with anything
    else in it is never replaced: it is not a crtraj output). marker: the kind
    of crtraj folder this is (`mark_folder`); the staged folder carries the
    marker and an existing target that carries it is replaced whatever it holds.
    Leaving the ``with`` block without a commit removes the staged folder.
    """

    def __init__(self, target: str | os.PathLike[str], replaceable: frozenset[str], marker: str | None = None) -> None:
        t = Path(target)
        self.target = t.resolve() if t.is_symlink() else t
        self.replaceable = replaceable
        self.marker = marker
        self.target.parent.mkdir(parents=True, exist_ok=True)
        recover_dir(self.target)
        self.path = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.", suffix=".tmp", dir=self.target.parent))
        temporaries.add(self.path)
        _usual_mode(self.path, directory=True)
        if marker is not None:
            mark_folder(self.path, marker)
        self.committed = False

    def commit(self, target: str | os.PathLike[str] | None = None) -> Path:
        """Swap the staged folder in as `target` (default: the target given at construction; it must
        be a sibling of it, e.g. ``replan.failed``); returns the path."""
        dest = self.target if target is None else Path(target)
        if dest.parent.resolve() != self.path.parent.resolve():
            raise ValueError(f"{dest}: must be in {self.path.parent}")
        for p in self.path.rglob("*"):
            if p.is_file():
                _fsync_file(p)
        _fsync_dir(self.path)
        checkpoint("dir-staged")
        check_interrupt()  # a stopped command replaces nothing
        with shielded():  # begun, the swap is finished: a signal now stops the command after it
            self._swap(dest)
        return dest

    def _swap(self, dest: Path) -> None:
        recover_dir(dest)
        if dest.exists():
            check_output_dir(dest, str(dest), self.replaceable, self.marker)
            if _exchange(self.path, dest):
                old = self.path  # now holds the previous folder
                _fsync_dir(dest.parent)
            else:
                old = dest.parent / f".{dest.name}.old-{os.getpid()}-{os.urandom(4).hex()}"
                os.rename(dest, old)
                checkpoint("dir-aside")
                os.rename(self.path, dest)
                _fsync_dir(dest.parent)
            self.committed = True
            checkpoint("dir-swapped")
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(self.path, dest)
            _fsync_dir(dest.parent)
            self.committed = True
        temporaries.discard(self.path)

    def discard(self) -> None:
        if not self.committed:
            shutil.rmtree(self.path, ignore_errors=True)
            temporaries.discard(self.path)

    def __enter__(self) -> StagedDir:
        return self

    def __exit__(self, *exc: object) -> None:
        self.discard()


# ------------------------------------------------------- crtraj's own folders
# A folder crtraj may delete or replace carries this file, written by crtraj: {"crtraj_folder": kind,
# "version": MARKER_VERSION}. Anything else (a user's folder that happens to hold a manifest.json) is kept.
MARKER = ".crtraj-folder.json"
MARKER_VERSION = 1
_MAX_MARKER_BYTES = 4096


def mark_folder(folder: str | os.PathLike[str], kind: str) -> Path:
    """Write crtraj's marker into `folder`: crtraj made it, as a `kind` (e.g. ``build-cache-entry``)."""
    return atomic_write_json(Path(folder) / MARKER, {"crtraj_folder": kind, "version": MARKER_VERSION})


def is_marked(folder: str | os.PathLike[str], kind: str) -> bool:
    """True when `folder` is a folder (not a link to one) whose marker crtraj wrote for `kind`, with this
    marker version; a missing, unreadable, foreign or other-version marker is False."""
    p = Path(folder)
    try:
        if p.is_symlink() or not p.is_dir():
            return False
        doc = read_json(p / MARKER, _MAX_MARKER_BYTES)
    except (InputError, OSError):
        return False
    return isinstance(doc, dict) and doc.get("crtraj_folder") == kind and doc.get("version") == MARKER_VERSION


def remove_marked(folder: str | os.PathLike[str], kind: str, trash: str | os.PathLike[str]) -> bool:
    """Delete `folder` only when it carries crtraj's marker of `kind`: renamed into the folder `trash`
    first (one step, so no reader sees it half removed), then removed; whether it was deleted."""
    p = Path(folder)
    if not is_marked(p, kind):
        return False
    aside = Path(trash) / p.name
    try:
        os.rename(p, aside)
    except OSError:  # someone else moved or replaced it already
        return False
    shutil.rmtree(aside, ignore_errors=True)
    return True


# ------------------------------------------------------- output path checks
def _writable_ancestor(p: Path, what: str) -> None:
    """The nearest existing ancestor of `p` must be a folder we can create files in (probed, so the
    answer is right for root and read-only file systems too)."""
    a = p.parent
    while not (a.exists() or a.is_symlink()) and a != a.parent:
        a = a.parent
    if not a.is_dir():
        raise InputError(f"{what}: cannot write {p}: {a} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".crtraj-probe.", dir=a)
    except OSError as exc:
        raise InputError(f"{what}: cannot write {p}: {a}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(probe)


def check_output_file(path: str | os.PathLike[str], what: str) -> Path:
    """Refuse, before any work, an output file that cannot be written; one line naming `what`
    (e.g. ``--out``)."""
    p = Path(path)
    try:
        if p.is_dir():
            raise InputError(f"{what}: {p} is a folder; give a file name")
        _writable_ancestor(p, what)
    except OSError as exc:
        raise InputError(f"{what}: cannot write {p}: {exc.strerror or exc}") from None
    return p


def check_output_dir(
    path: str | os.PathLike[str], what: str, replaceable: frozenset[str], marker: str | None = None
) -> Path:
    """Refuse, before any work, an output folder that cannot be written or that holds files other
    than `replaceable` and carries no crtraj `marker` of that kind (it would be replaced as a whole);
    one line naming `what`."""
    p = Path(path)
    try:
        if p.exists() and not p.is_dir():
            raise InputError(f"{what}: {p} exists and is not a folder")
        if p.is_dir() and not (marker is not None and is_marked(p, marker)):
            foreign = sorted(n for n in os.listdir(p) if n not in replaceable)
            if foreign:
                shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
                raise InputError(
                    f"{what}: {p} holds files crtraj did not write ({shown}); it is replaced as a whole, "
                    "so give a new folder"
                )
        _writable_ancestor(p, what)
    except OSError as exc:
        raise InputError(f"{what}: cannot write {p}: {exc.strerror or exc}") from None
    return p


def _same_file(a: Path, b: Path) -> bool:
    """True when a and b name one file: the same inode when both exist, else the same resolved path."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
        return a.resolve() == b.resolve()
    except (OSError, RuntimeError, ValueError):
        return False


def check_outputs_not_inputs(
    outputs: dict[str, str | os.PathLike[str] | None], inputs: dict[str, str | os.PathLike[str] | None]
) -> None:
    """The one rule for every command: an output may never be one of the command's inputs, nor another output.

    outputs, inputs: {flag or field name (e.g. ``--out``, ``--log``): path or None (not given)}. A folder output
    also may not contain an input (it is replaced as a whole). Raises `InputError` with one line naming both flags.
    """
    outs = [(k, Path(v)) for k, v in outputs.items() if v is not None]
    ins = [(k, Path(v)) for k, v in inputs.items() if v is not None]
    for i, (name, out) in enumerate(outs):
        for other, src in ins + outs[:i]:
            if _same_file(out, src):
                raise InputError(f"{name}: {out} is also {other}; give an output that is not one of the inputs")
            if out.is_dir() and other in inputs:
                try:
                    src.resolve().relative_to(out.resolve())
                except ValueError:
                    continue
                raise InputError(f"{name}: {out} holds {other} ({src}); it would be replaced, give another folder")


def failed_sibling(path: str | os.PathLike[str]) -> Path:
    """Where a failed result goes when `path` holds a successful one: ``p.json`` -> ``p.failed.json``,
    ``out/replan`` -> ``out/replan.failed``."""
    p = Path(path)
    if p.suffix and p.stem:
        return p.with_name(f"{p.stem}.failed{p.suffix}")
    return p.with_name(f"{p.name}.failed")


def is_successful_result(path: str | os.PathLike[str]) -> bool:
    """True when `path` (a result JSON, or a folder with run.json) holds a crtraj result with success true."""
    p = Path(path)
    if p.is_dir():
        p = p / "run.json"
    try:
        doc = json.loads(p.read_bytes())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and doc.get("success") is True


def read_text(path: str | os.PathLike[str], *, max_bytes: int, kind: str) -> str:
    """The UTF-8 text of a regular file of at most `max_bytes` bytes.

    kind names the expected format in messages ("TOML", "JSON"). Raises
    `InputError` naming the file for a missing file, a folder, a pipe or
    device (which could block forever), an oversized file and text that is
    not UTF-8 (a UTF-8 byte-order mark is accepted and dropped).
    """
    p = Path(path)
    try:
        # stat before open: opening a FIFO for reading blocks until a writer comes
        _check_regular(p, os.stat(p), max_bytes, kind)
        with p.open("rb") as fh:
            _check_regular(p, os.fstat(fh.fileno()), max_bytes, kind)  # the same file, now that it is open
            data = fh.read(max_bytes + 1)  # the size may change after fstat
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder, expected a {kind} file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    except ValueError:  # a NUL byte in the name
        raise InputError(f"{p!r}: not a valid file name") from None
    if len(data) > max_bytes:
        raise InputError(f"{p}: larger than the {max_bytes} bytes a {kind} input may have")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise InputError(f"{p}: not UTF-8 text (it looks like UTF-16); save it as UTF-8")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{p}: not UTF-8 text (byte {exc.start} is 0x{data[exc.start]:02x}); not a {kind} file?"
        ) from None


def _check_regular(p: Path, st: os.stat_result, max_bytes: int, kind: str) -> None:
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{p}: is a folder, expected a {kind} file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{p}: not a regular file, expected a {kind} file")
    if st.st_size > max_bytes:
        raise InputError(f"{p}: {st.st_size} bytes, larger than the {max_bytes} bytes a {kind} input may have")


def check_depth(data: Any, name: str, max_depth: int = MAX_DEPTH) -> None:
    """Raise `InputError` when lists/dicts in `data` nest deeper than `max_depth` levels.

    Iterative, so it works on data too deep for recursive code, which is
    exactly what it protects (encoders, validators, numpy conversion).
    """
    stack: list[tuple[Any, int]] = [(data, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        if depth >= max_depth:
            raise InputError(f"{name}: nested deeper than {max_depth} levels")
        stack.extend((c, depth + 1) for c in children if isinstance(c, (dict, list)))


def _parse(path: str | os.PathLike[str], max_bytes: int, kind: str, loads: Any) -> Any:
    """Read a bounded `kind` file and parse it with `loads`; one-line `InputError` naming the file on failure.

    The parser's own errors are caught only around the parse: RecursionError (deep nesting), MemoryError, and
    ValueError (a syntax error, or an integer of more than 4300 digits).
    """
    p = Path(path)
    text = read_text(p, max_bytes=max_bytes, kind=kind)
    try:
        data = loads(text)
    except RecursionError:
        raise InputError(f"{p}: not valid {kind} (nested deeper than {MAX_DEPTH} levels)") from None
    except MemoryError:
        raise InputError(f"{p}: too large to parse") from None
    except ValueError as exc:
        raise InputError(f"{p}: not valid {kind} ({_first_line(exc)})") from None
    check_depth(data, str(p))
    return data


def read_json(path: str | os.PathLike[str], max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Read a JSON file of at most `max_bytes` bytes; raise `InputError` with the path on failure."""
    return _parse(path, max_bytes, "JSON", json.loads)


def read_toml(path: str | os.PathLike[str], max_bytes: int = MAX_TOML_BYTES) -> dict[str, Any]:
    """Parse a TOML file of at most `max_bytes` bytes; one-line `InputError` on any bad file."""
    return _parse(path, max_bytes, "TOML", tomllib.loads)


def _first_line(exc: BaseException, width: int = 200) -> str:
    """A parser's message cut to one line of at most `width` characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= width else text[: width - 3] + "..."
