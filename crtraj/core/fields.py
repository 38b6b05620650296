"""Typed, validated reading of TOML tables, with errors that name the field.

Every option dataclass in crtraj reads its section through `Table`, so unknown
keys, wrong types, NaN and out-of-range values all fail the same way: one
`InputError` line such as ``robot.segment[1].length: must be > 0, got -3``.

Every number read from a file is bounded, so no value can overflow or make
work explode downstream: floats are finite and at most `MAX_MAGNITUDE` in
absolute value unless a field sets a tighter `limit` (lengths and coordinates
`MAX_LENGTH` mm, times `MAX_TIME` s), and every integer field states its own
upper bound (`Table.int` has no default for `le`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from crtraj.core.errors import InputError

_MISSING = object()

# Largest |value| of any number read from a file, whatever its unit: far above
# any physical quantity crtraj uses, far below float overflow (1e308).
MAX_MAGNITUDE = 1.0e9
# Largest |length| or |coordinate| (mm): a kilometre.
MAX_LENGTH = 1.0e6
# Largest time or duration (s): about 11.6 days.
MAX_TIME = 1.0e6
# Largest timestamp read from a log or capture file (s): wall-clock times since the epoch fit.
MAX_STAMP = 1.0e11
# Seeds are 32-bit unsigned integers.
MAX_SEED = 2**32 - 1


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class Table:
    """A view of one TOML table that records which keys were read.

    Call `finish()` after reading: any key that was not read is an unknown key
    and raises, so typos never pass silently.
    """

    def __init__(self, data: Mapping[str, Any] | None, path: str) -> None:
        if data is None:
            data = {}
        if not isinstance(data, Mapping):
            raise InputError(f"{path}: expected a table, got {type(data).__name__}")
        self._data = dict(data)
        self.path = path
        self._read: set[str] = set()

    def _name(self, key: str) -> str:
        key = _key_text(key)
        return f"{self.path}.{key}" if self.path else key

    def error(self, key: str, msg: str) -> InputError:
        """An `InputError` naming `key` of this table."""
        return InputError(f"{self._name(key)}: {msg}")

    def has(self, key: str) -> bool:
        return key in self._data

    def keys(self) -> list[str]:
        return list(self._data)

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        self._read.add(key)
        if key not in self._data:
            if default is _MISSING:
                raise InputError(f"{self._name(key)}: missing (required)")
            return default
        return self._data[key]

    def float(
        self,
        key: str,
        default: Any = _MISSING,
        *,
        gt: float | None = None,
        ge: float | None = None,
        lt: float | None = None,
        le: float | None = None,
        limit: float = MAX_MAGNITUDE,
    ) -> float:
        """A finite number with ``|value| <= limit`` and the given bounds."""
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        return check_float(v, self._name(key), gt=gt, ge=ge, lt=lt, le=le, limit=limit)

    def int(self, key: str, default: Any = _MISSING, *, ge: int | None = None, le: int) -> int:
        """An integer in ``[ge, le]``; `le` is required so that every size-like field is bounded."""
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        if not isinstance(v, int) or isinstance(v, bool):
            raise InputError(f"{self._name(key)}: expected an integer, got {_short(v)}")
        if ge is not None and v < ge:
            raise InputError(f"{self._name(key)}: must be >= {ge}, got {v}")
        if v > le:
            raise InputError(f"{self._name(key)}: must be <= {le}, got {_short(v)}")
        return v

    def bool(self, key: str, default: Any = _MISSING) -> bool:
        v = self.raw(key, default)
        if not isinstance(v, bool):
            raise InputError(f"{self._name(key)}: expected true or false, got {_short(v)}")
        return v

    def str(
        self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None, max_len: int = 10_000
    ) -> str:
        """A string of at most `max_len` characters (one of `choices` when given)."""
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        if not isinstance(v, str):
            raise InputError(f"{self._name(key)}: expected a string, got {_short(v)}")
        if len(v) > max_len:
            raise InputError(f"{self._name(key)}: longer than {max_len} characters ({len(v)})")
        if choices is not None and v not in choices:
            raise InputError(f"{self._name(key)}: must be one of {', '.join(choices)}; got {_short(v)}")
        return v

    def vec(
        self, key: str, n: int | None = None, default: Any = _MISSING, *, limit: float = MAX_MAGNITUDE
    ) -> tuple[float, ...]:
        """A list of finite numbers (`n` of them when given), each with ``|x| <= limit``."""
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        return check_vec(v, self._name(key), n, limit=limit)

    def table(self, key: str) -> Table:
        """The sub-table `key`, empty when absent."""
        return Table(self.raw(key, {}), self._name(key))

    def tables(self, key: str, *, most: int) -> list[Table]:
        """An array of at most `most` tables (``[[key]]``), empty when absent."""
        v = self.raw(key, [])
        if isinstance(v, Mapping) or not isinstance(v, list):
            raise InputError(f"{self._name(key)}: expected an array of tables ([[{_key_text(key)}]])")
        if len(v) > most:
            raise InputError(f"{self._name(key)}: at most {most} entries, got {len(v)}")
        return [Table(item, f"{self._name(key)}[{i}]") for i, item in enumerate(v)]

    def finish(self) -> None:
        """Raise for the first key that was never read (an unknown key)."""
        unknown = [k for k in self._data if k not in self._read]
        if unknown:
            known = sorted(self._read)
            hint = f" (known keys: {', '.join(known)})" if known else ""
            raise InputError(f"{self._name(unknown[0])}: unknown key{hint}")


def check_float(
    v: Any,
    name: str,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    limit: float = MAX_MAGNITUDE,
) -> float:
    """Validate one finite number with ``|v| <= limit``; raise `InputError` naming `name`."""
    if not _is_number(v):
        raise InputError(f"{name}: expected a number, got {_short(v)}")
    try:
        f = float(v)
    except OverflowError:  # an int beyond float range
        raise InputError(f"{name}: must be within +-{limit:g}, got {_short(v)}") from None
    if not math.isfinite(f):
        raise InputError(f"{name}: must be finite, got {f}")
    if abs(f) > limit:
        raise InputError(f"{name}: must be within +-{limit:g}, got {f:g}")
    if gt is not None and not f > gt:
        raise InputError(f"{name}: must be > {gt:g}, got {f:g}")
    if ge is not None and not f >= ge:
        raise InputError(f"{name}: must be >= {ge:g}, got {f:g}")
    if lt is not None and not f < lt:
        raise InputError(f"{name}: must be < {lt:g}, got {f:g}")
    if le is not None and not f <= le:
        raise InputError(f"{name}: must be <= {le:g}, got {f:g}")
    return f


def read_number(v: Any, name: str, *, limit: float = MAX_MAGNITUDE) -> float:
    """The one reader of a number from JSON, JSON lines or CSV: a JSON number, or a CSV cell's text.

    Integers of any size, values beyond ``+-limit`` (1e300), NaN, infinity, booleans and text that is not
    an ASCII decimal number (``float`` also takes other scripts' digits, ``"1_0"`` and ``" nan "``) are
    refused with one `InputError` line naming `name`.
    """
    if isinstance(v, str):
        text = v.strip()
        if not text or not text.isascii() or "_" in text or len(text) > 100:
            raise InputError(f"{name}: expected a number, got {_short(v)}")
        try:
            v = float(text)
        except ValueError:
            raise InputError(f"{name}: expected a number, got {_short(v)}") from None
    return check_float(v, name, limit=limit)


def read_int(v: Any, name: str, *, ge: int = 0, le: int) -> int:
    """An integer from JSON, CSV or a flag's text, ``ge <= v <= le``: ASCII decimal digits only (``int``
    takes other scripts' digits and ``_``, and ``str.isdigit`` is true for superscripts that ``int``
    refuses); one `InputError` line naming `name` otherwise."""
    if isinstance(v, str):
        text = v.strip()
        body = text[1:] if text[:1] in "+-" else text
        if not (body.isascii() and body.isdecimal()) or len(body) > 30:
            raise InputError(f"{name}: expected an integer, got {_short(v)}")
        v = int(text)
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"{name}: expected an integer, got {_short(v)}")
    if not ge <= v <= le:
        raise InputError(f"{name}: must be in {ge}..{le}, got {_short(v)}")
    return v


def check_vec(v: Any, name: str, n: int | None = None, *, limit: float = MAX_MAGNITUDE) -> tuple[float, ...]:
    """Validate a list of finite numbers (of length `n` when given), each with ``|x| <= limit``."""
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if not isinstance(v, (list, tuple)):
        raise InputError(f"{name}: expected a list of numbers, got {_short(v)}")
    if n is not None and len(v) != n:
        raise InputError(f"{name}: expected {n} numbers, got {len(v)}")
    return tuple(check_float(x, f"{name}[{i}]", limit=limit) for i, x in enumerate(v))


def check_array(v: Any, name: str, shape: tuple[int | None, ...], *, limit: float = MAX_MAGNITUDE) -> np.ndarray:
    """Convert to a finite float64 array of `shape` (None = any length) with every ``|x| <= limit``."""
    if not _only_numbers(v):  # numpy would turn "12" into 12.0 and true into 1.0
        raise InputError(f"{name}: expected numbers of shape {_shape_text(shape)}")
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{name}: expected numbers of shape {_shape_text(shape)}") from None
    if a.ndim != len(shape) or any(s is not None and s != a.shape[i] for i, s in enumerate(shape)):
        raise InputError(f"{name}: expected shape {_shape_text(shape)}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or infinity")
    if a.size and float(np.max(np.abs(a))) > limit:
        raise InputError(f"{name}: values must be within +-{limit:g}, got {float(np.max(np.abs(a))):g}")
    return a


def check_name(v: Any, name: str, max_len: int = 100) -> str:
    """A name that becomes part of file names: 1..max_len printable characters, no path separator,
    no leading dot."""
    if not isinstance(v, str):
        raise InputError(f"{name}: expected a string, got {_short(v)}")
    if not v or len(v) > max_len:
        raise InputError(f"{name}: must be 1 to {max_len} characters, got {len(v)}")
    if not v.isprintable() or any(c in v for c in "/\\:") or v.startswith("."):
        raise InputError(f"{name}: {_short(v)} cannot be part of a file name (no / \\ : or leading dot)")
    return v


def _only_numbers(v: Any) -> bool:
    """True when `v` is a number or (nested) lists of numbers only: no bool, str, None or dict.

    Iterative, so that deeply nested input cannot exhaust the stack.
    """
    if isinstance(v, np.ndarray):
        return v.dtype.kind in "fiu"
    stack = [v]
    while stack:
        item = stack.pop()
        if isinstance(item, (list, tuple)):
            stack.extend(item)
        elif isinstance(item, np.ndarray):
            if item.dtype.kind not in "fiu":
                return False
        elif isinstance(item, bool) or not isinstance(item, (int, float, np.integer, np.floating)):
            return False
    return True


def _key_text(key: Any, width: int = 60) -> str:
    """A key as it can appear in a one-line message: quoted when it holds odd characters, cut when long."""
    text = str(key)
    if not text.isprintable() or not text or len(text) > width:
        text = _short(text, width)
    return text


def _short(v: Any, width: int = 60) -> str:
    """`repr` of a bad value, cut to `width` characters so that an error stays one short line."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > 10**30:
        return f"an integer of {len(str(abs(v)))} digits"
    text = repr(v)
    text = text.replace("\n", " ").replace("\r", " ")
    return text if len(text) <= width else text[: width - 3] + "..."


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
