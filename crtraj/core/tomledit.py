"""Comment-preserving edits of TOML text: replace the values of some keys and nothing else.

`set_values` finds each key's value span in the original text (after its table header, ``[a.b]`` or the
k-th ``[[a.b]]``) and replaces only that span, so every comment, blank line, key order and number format
of the file stays as it was. A key missing from an existing table is added after that table's last
line; a missing table is appended at the end. The result is re-parsed (`tomllib`) and compared with
the original: exactly the requested values must have changed, to exactly the requested values, or
`InputError` is raised and nothing is written by the caller.

Key paths are tuples of table names, array-of-tables indices (0-based) and the key:
``("robot", "segment", 1, "length")`` is ``length`` in the second ``[[robot.segment]]``. Keys and
table names must be bare keys (letters, digits, ``_``, ``-``); a file that defines a table through
dotted keys or an inline table is refused by the re-parse check rather than edited wrongly.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Mapping
from typing import Any

from crtraj.core.errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

Path = tuple[Any, ...]

_KEY = re.compile(r"[ \t]*([A-Za-z0-9_-]+)[ \t]*=[ \t]*")
_HEADER = re.compile(r"[ \t]*(\[\[?)[ \t]*([A-Za-z0-9_.\- \t]+?)[ \t]*(\]\]?)[ \t]*(#.*)?$")


def toml_literal(v: Any) -> str:
    """The TOML text of a bool, int, float (always with a point or exponent), string or list of them."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise InputError(f"toml: cannot write the non-finite number {v}")
        s = repr(v)
        return s if any(ch in s for ch in ".en") else s + ".0"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_literal(x) for x in v) + "]"
    raise InputError(f"toml: cannot write a {type(v).__name__}")


def _value_end(text: str, i: int) -> int:
    """End offset of the TOML value starting at text[i] (exclusive; trailing spaces and comment excluded)."""
    if text.startswith(('"""', "'''"), i):
        q = text[i : i + 3]
        j = i + 3
        while True:
            j = text.find(q, j)
            if j < 0:
                raise InputError("toml: unterminated multi-line string")
            if q == '"""' and _escaped(text, j):
                j += 1
                continue
            end = j + 3
            while text.startswith(q[0], end):  # up to two quotes may close the string's content
                end += 1
            return end
    ch = text[i] if i < len(text) else ""
    if ch in "\"'":
        j = i + 1
        while j < len(text) and text[j] != "\n":
            if text[j] == ch and not (ch == '"' and _escaped(text, j)):
                return j + 1
            j += 1
        raise InputError("toml: unterminated string")
    if ch in "[{":
        depth, j = 0, i
        while j < len(text):
            c = text[j]
            if c in "\"'":
                j = _value_end(text, j)
                continue
            if c == "#":
                nl = text.find("\n", j)
                j = len(text) if nl < 0 else nl
                continue
            if c in "[{":
                depth += 1
            elif c in "]}":
                depth -= 1
                if depth == 0:
                    return j + 1
            j += 1
        raise InputError("toml: unterminated array or inline table")
    nl = text.find("\n", i)
    line_end = len(text) if nl < 0 else nl
    hash_ = text.find("#", i, line_end)
    end = line_end if hash_ < 0 else hash_
    while end > i and text[end - 1] in " \t\r":
        end -= 1
    return end


def _escaped(text: str, j: int) -> bool:
    """Whether the quote at text[j] is escaped (an odd number of backslashes before it)."""
    k = j - 1
    while k >= 0 and text[k] == "\\":
        k -= 1
    return (j - 1 - k) % 2 == 1


def _scan(text: str) -> tuple[dict[Path, tuple[int, int]], dict[Path, int]]:
    """(value spans of every key path, end offset of every table's last line) of a TOML text."""
    spans: dict[Path, tuple[int, int]] = {}
    table_end: dict[Path, int] = {(): 0}
    counts: dict[Path, int] = {}
    table: Path = ()
    i = 0
    while i < len(text):
        nl = text.find("\n", i)
        line_end = len(text) if nl < 0 else nl
        line = text[i:line_end]
        h = _HEADER.match(line) if line.lstrip().startswith("[") else None
        if h is not None:
            names = tuple(p.strip() for p in h.group(2).split("."))
            if h.group(1) == "[[":
                idx = counts.get(names, 0)
                counts[names] = idx + 1
                table = (*_with_indices(names[:-1], counts), names[-1], idx)
            else:
                table = _with_indices(names, counts)
            table_end[table] = line_end
            i = line_end + 1
            continue
        k = _KEY.match(line)
        if k is not None:
            start = i + k.end()
            end = _value_end(text, start)
            spans[(*table, k.group(1))] = (start, end)
            nl2 = text.find("\n", end)
            line_end = len(text) if nl2 < 0 else nl2
            table_end[table] = line_end
        elif line.strip() and not line.strip().startswith("#"):
            table_end[table] = line_end
        i = line_end + 1
    return spans, table_end


def _with_indices(names: tuple[str, ...], counts: dict[Path, int]) -> Path:
    """A table path with the current index inserted after every array-of-tables prefix."""
    out: list[Any] = []
    for j in range(len(names)):
        out.append(names[j])
        n = counts.get(names[: j + 1])
        if n is not None:
            out.append(n - 1)
    return tuple(out)


def _header(table: Path) -> str:
    if any(not isinstance(p, str) for p in table):
        raise InputError(f"toml: cannot add a key to a missing array table {_dotted(table)}")
    return "[" + ".".join(table) + "]"


def _dotted(path: Path) -> str:
    return ".".join(str(p) if isinstance(p, str) else f"[{p}]" for p in path).replace(".[", "[")


def set_values(text: str, changes: Mapping[Path, Any], comment: str = "") -> str:
    """`text` with the values at the key paths of `changes` set (see the module docstring).

    comment: appended (as ``# comment``) to lines that are added, never to edited ones.
    """
    spans, table_end = _scan(text)
    edits: list[tuple[int, int, str]] = []
    added: dict[Path, list[str]] = {}
    tail = f"  # {comment}" if comment else ""
    for path, value in changes.items():
        lit = toml_literal(value)
        if path in spans:
            a, b = spans[path]
            edits.append((a, b, lit))
        else:
            added.setdefault(path[:-1], []).append(f"{path[-1]} = {lit}{tail}")
    new_tables: list[str] = []
    for table, lines in added.items():
        if table in table_end:
            at = table_end[table]
            edits.append((at, at, "\n" + "\n".join(lines)))
        else:
            new_tables.append("\n" + _header(table) + "\n" + "\n".join(lines) + "\n")
    out = text
    for a, b, s in sorted(edits, key=lambda e: e[0], reverse=True):
        out = out[:a] + s + out[b:]
    if new_tables:
        out = out.rstrip("\n") + "\n" + "".join(new_tables)
    _verify(text, out, changes)
    return out


def _flatten(data: Any, prefix: Path = ()) -> dict[Path, Any]:
    out: dict[Path, Any] = {}
    if isinstance(data, dict):
        for k, v in data.items():
            out.update(_flatten(v, (*prefix, k)))
    elif isinstance(data, list) and data and all(isinstance(x, dict) for x in data):
        for i, v in enumerate(data):
            out.update(_flatten(v, (*prefix, i)))
    else:
        out[prefix] = data
    return out


def _verify(before: str, after: str, changes: Mapping[Path, Any]) -> None:
    """Re-parse both texts: exactly the requested values changed, to exactly what was asked."""
    try:
        old = _flatten(tomllib.loads(before))
        new = _flatten(tomllib.loads(after))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"toml: the edited file does not parse ({exc}); it was not written") from None
    want = {tuple(p): _plain(v) for p, v in changes.items()}
    for path in set(old) | set(new):
        if path in want:
            continue
        if old.get(path, _MISSING) != new.get(path, _MISSING):
            raise InputError(f"toml: editing changed {_dotted(path)}, which was not asked; the file was not written")
    for path, v in want.items():
        if new.get(path, _MISSING) != v:
            raise InputError(f"toml: {_dotted(path)} did not take its new value; the file was not written")


_MISSING = object()


def _plain(v: Any) -> Any:
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    if isinstance(v, list):
        return [_plain(x) for x in v]
    return v
