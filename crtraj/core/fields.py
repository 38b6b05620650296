"""Typed, validated reading of TOML tables, with errors that name the field.

Every option dataclass in crtraj reads its section through `Table`, so unknown
keys, wrong types, NaN and out-of-range values all fail the same way: one
`InputError` line such as ``robot.segment[1].length: must be > 0, got -3``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from crtraj.core.errors import InputError

_MISSING = object()


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
    ) -> float:
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        return check_float(v, self._name(key), gt=gt, ge=ge, lt=lt, le=le)

    def int(self, key: str, default: Any = _MISSING, *, ge: int | None = None, le: int | None = None) -> int:
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        if not isinstance(v, int) or isinstance(v, bool):
            raise InputError(f"{self._name(key)}: expected an integer, got {v!r}")
        if ge is not None and v < ge:
            raise InputError(f"{self._name(key)}: must be >= {ge}, got {v}")
        if le is not None and v > le:
            raise InputError(f"{self._name(key)}: must be <= {le}, got {v}")
        return v

    def bool(self, key: str, default: Any = _MISSING) -> bool:
        v = self.raw(key, default)
        if not isinstance(v, bool):
            raise InputError(f"{self._name(key)}: expected true or false, got {v!r}")
        return v

    def str(self, key: str, default: Any = _MISSING, *, choices: Sequence[str] | None = None) -> str:
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        if not isinstance(v, str):
            raise InputError(f"{self._name(key)}: expected a string, got {v!r}")
        if choices is not None and v not in choices:
            raise InputError(f"{self._name(key)}: must be one of {', '.join(choices)}; got {v!r}")
        return v

    def vec(self, key: str, n: int | None = None, default: Any = _MISSING) -> tuple[float, ...]:
        v = self.raw(key, default)
        if v is None and default is None:
            return None  # type: ignore[return-value]
        return check_vec(v, self._name(key), n)

    def table(self, key: str) -> Table:
        """The sub-table `key`, empty when absent."""
        return Table(self.raw(key, {}), self._name(key))

    def tables(self, key: str) -> list[Table]:
        """An array of tables (``[[key]]``), empty when absent."""
        v = self.raw(key, [])
        if isinstance(v, Mapping) or not isinstance(v, list):
            raise InputError(f"{self._name(key)}: expected an array of tables ([[{key}]])")
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
) -> float:
    """Validate one finite number; raise `InputError` naming `name`."""
    if not _is_number(v):
        raise InputError(f"{name}: expected a number, got {v!r}")
    f = float(v)
    if not math.isfinite(f):
        raise InputError(f"{name}: must be finite, got {f}")
    if gt is not None and not f > gt:
        raise InputError(f"{name}: must be > {gt:g}, got {f:g}")
    if ge is not None and not f >= ge:
        raise InputError(f"{name}: must be >= {ge:g}, got {f:g}")
    if lt is not None and not f < lt:
        raise InputError(f"{name}: must be < {lt:g}, got {f:g}")
    if le is not None and not f <= le:
        raise InputError(f"{name}: must be <= {le:g}, got {f:g}")
    return f


def check_vec(v: Any, name: str, n: int | None = None) -> tuple[float, ...]:
    """Validate a list of finite numbers (of length `n` when given)."""
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if not isinstance(v, (list, tuple)):
        raise InputError(f"{name}: expected a list of numbers, got {v!r}")
    if n is not None and len(v) != n:
        raise InputError(f"{name}: expected {n} numbers, got {len(v)}")
    return tuple(check_float(x, f"{name}[{i}]") for i, x in enumerate(v))


def check_array(v: Any, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Convert to a finite float64 array of `shape` (None = any length)."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected numbers of shape {_shape_text(shape)}") from None
    if a.ndim != len(shape) or any(s is not None and s != a.shape[i] for i, s in enumerate(shape)):
        raise InputError(f"{name}: expected shape {_shape_text(shape)}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{name}: contains NaN or infinity")
    return a


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
