"""Comment-preserving edits of TOML text: replace the values of some keys and nothing else.

`set_values` parses the text with `tomlkit` (which keeps every comment, blank line, key order, table
style and number format), sets each key path's value, and writes it back. A key missing from an existing
table is added to it (inline and dotted-key tables included); a missing table is appended at the end.
A file with CRLF line endings keeps them, added lines included. The result is re-parsed (`tomllib`) and
compared with the original: exactly the requested values must have changed, to exactly the requested
values, or `InputError` is raised and nothing is written by the caller.

Key paths are tuples of table names, array-of-tables indices (0-based) and the key:
``("robot", "segment", 1, "length")`` is ``length`` in the second ``[[robot.segment]]``. Values: bool,
int, float (finite), str (encodable as UTF-8; control characters are escaped) and lists of them.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from typing import Any

import tomlkit
from tomlkit.exceptions import TOMLKitError
from tomlkit.items import AoT, InlineTable

from crtraj.core.errors import InputError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

Path = tuple[Any, ...]


def set_values(text: str, changes: Mapping[Path, Any], comment: str = "") -> str:
    """`text` with the values at the key paths of `changes` set (see the module docstring).

    comment: appended (as ``# comment``) to keys that are added, never to edited ones.
    """
    crlf = "\r\n" in text and text.count("\r\n") == text.count("\n")
    source = text.replace("\r\n", "\n") if crlf else text
    try:
        doc = tomlkit.parse(source)
    except (TOMLKitError, ValueError) as exc:
        raise InputError(f"toml: the file does not parse ({_first_line(exc)}); it was not written") from None
    for path, value in changes.items():
        _set(doc, tuple(path), _plain(value, path), comment)
    try:
        out = tomlkit.dumps(doc)
    except (TOMLKitError, ValueError) as exc:
        raise InputError(f"toml: cannot write the edited file ({_first_line(exc)}); it was not written") from None
    if crlf:
        out = out.replace("\r\n", "\n").replace("\n", "\r\n")
    _verify(text, out, changes)
    return out


def _set(doc: Any, path: Path, value: Any, comment: str) -> None:
    """Set `value` at `path` in the tomlkit document, creating a missing key or table."""
    if not path or not isinstance(path[-1], str):
        raise InputError(f"toml: a key path must end in a key name, got {_dotted(path)}")
    node = doc
    for i, part in enumerate(path[:-1]):
        node = _child(node, part, path[: i + 1])
    key = path[-1]
    if key in node:
        node[key] = value  # tomlkit keeps the old item's comment and spacing
        return
    item = tomlkit.item(value)
    if comment and not isinstance(node, InlineTable):
        item.comment(comment)
    node[key] = item


def _child(node: Any, part: Any, where: Path) -> Any:
    """The table or array-of-tables element `part` of `node` (a missing named table is created)."""
    if isinstance(part, int) and not isinstance(part, bool):
        if not isinstance(node, (list, AoT)) or not 0 <= part < len(node):
            raise InputError(f"toml: cannot add a key to a missing array table {_dotted(where)}")
        return node[part]
    if not isinstance(part, str):
        raise InputError(f"toml: key path parts are names or indices, got {part!r}")
    if part not in node:
        node[part] = tomlkit.table()
    child = node[part]
    if not isinstance(child, (dict, list)):
        raise InputError(f"toml: {_dotted(where)} is a value, not a table")
    return child


def _plain(v: Any, path: Path) -> Any:
    """`v` as the plain TOML value it will be written as; `InputError` for what TOML or UTF-8 cannot hold."""
    if isinstance(v, (bool, int)):
        return v
    if isinstance(v, float):
        if not math.isfinite(v):
            raise InputError(f"toml: {_dotted(path)}: cannot write the non-finite number {v}")
        return v
    if isinstance(v, str):
        try:
            v.encode("utf-8")
        except UnicodeEncodeError:
            raise InputError(f"toml: {_dotted(path)}: the text cannot be written as UTF-8: {v[:40]!r}") from None
        return v
    if isinstance(v, (list, tuple)):
        return [_plain(x, path) for x in v]
    raise InputError(f"toml: {_dotted(path)}: cannot write a {type(v).__name__}")


def _dotted(path: Path) -> str:
    return ".".join(str(p) if isinstance(p, str) else f"[{p}]" for p in path).replace(".[", "[")


def _first_line(exc: BaseException, width: int = 200) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= width else text[: width - 3] + "..."


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
    want = {tuple(p): _plain(v, tuple(p)) for p, v in changes.items()}
    for path in set(old) | set(new):
        if path in want:
            continue
        if old.get(path, _MISSING) != new.get(path, _MISSING):
            raise InputError(f"toml: editing changed {_dotted(path)}, which was not asked; the file was not written")
    for path, v in want.items():
        if new.get(path, _MISSING) != v:
            raise InputError(f"toml: {_dotted(path)} did not take its new value; the file was not written")


_MISSING = object()
