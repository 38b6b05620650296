"""Atomic file writes, JSON encoding of results, and bounded reading of input files.

A result that was already written must survive a later crash or bad input, so
every file crtraj writes goes to a temporary file in the same folder and is
renamed over the target only when complete.

Every file crtraj reads (problem and robot TOML, result JSON) goes through
`read_text`: it must be a regular file of at most a documented size
(`MAX_TOML_BYTES`, `MAX_JSON_BYTES`), UTF-8 text, and nested at most
`MAX_DEPTH` levels deep. Anything else is one `InputError` line naming the
file, never a traceback, a hang on a pipe or device, or a recursion error.
"""

from __future__ import annotations

import json
import math
import os
import stat
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.errors import InputError

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
    """Write `data` to `path` atomically (temp file + fsync + rename)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 `text` to `path` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def to_jsonable(obj: Any) -> Any:
    """Convert numpy arrays/scalars, tuples, paths and objects with ``to_dict`` for JSON.

    Non-finite floats (NaN, +-inf) become null: JSON has no such numbers.
    """
    if isinstance(obj, np.ndarray):
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


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write `obj` as indented JSON atomically."""
    return atomic_write_text(path, json.dumps(to_jsonable(obj), indent=1, allow_nan=False) + "\n")


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


def read_json(path: str | os.PathLike[str], max_bytes: int = MAX_JSON_BYTES) -> Any:
    """Read a JSON file of at most `max_bytes` bytes; raise `InputError` with the path on failure."""
    p = Path(path)
    text = read_text(p, max_bytes=max_bytes, kind="JSON")
    try:
        data = json.loads(text)
    except RecursionError:
        raise InputError(f"{p}: not valid JSON (nested deeper than {MAX_DEPTH} levels)") from None
    except MemoryError:
        raise InputError(f"{p}: too large to parse") from None
    except ValueError as exc:  # JSONDecodeError, and integers of more than 4300 digits
        raise InputError(f"{p}: not valid JSON ({_first_line(exc)})") from None
    check_depth(data, str(p))
    return data


def read_toml(path: str | os.PathLike[str], max_bytes: int = MAX_TOML_BYTES) -> dict[str, Any]:
    """Parse a TOML file of at most `max_bytes` bytes; one-line `InputError` on any bad file."""
    p = Path(path)
    text = read_text(p, max_bytes=max_bytes, kind="TOML")
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise InputError(f"{p}: not valid TOML (nested deeper than {MAX_DEPTH} levels)") from None
    except MemoryError:
        raise InputError(f"{p}: too large to parse") from None
    except ValueError as exc:  # TOMLDecodeError, and integers of more than 4300 digits
        raise InputError(f"{p}: not valid TOML ({_first_line(exc)})") from None
    check_depth(data, str(p))
    return data


def _first_line(exc: BaseException, width: int = 200) -> str:
    """A parser's message cut to one line of at most `width` characters."""
    text = " ".join(str(exc).split())
    return text if len(text) <= width else text[: width - 3] + "..."
