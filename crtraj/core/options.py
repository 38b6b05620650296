"""One style for every options section: frozen dataclasses whose fields declare their own bounds.

Every ``[section]`` of a problem file is a frozen dataclass deriving from `Options`. Each field is
declared with `option(default, ...)`, which records its bounds (``gt``/``ge``/``lt``/``le``, a
magnitude ``limit``), its ``choices`` or its string length in the field's metadata. The same
declaration then serves three readers:

- `Options.from_table` reads a TOML table through `crtraj.core.fields.Table`: every declared field by
  its annotated type (float, int, bool, str, each optionally ``| None``), unknown keys are errors;
- ``__post_init__`` checks an object built in Python against the same bounds, so a script gets the
  same one-line `InputError` (``section.key: must be > 0, got -1``) as a file;
- `Options.to_dict` gives the plain data of the TOML schema back (it round-trips through `from_table`).

A field whose value is not a scalar (a nested table of raw solver options, say) is declared with
``option(default, read=False)``: the class reads it in its own `_read_extra` and checks it in
`_check`, the two hooks a subclass may override for cross-field rules. Integers must carry an upper
bound (``le``): every size-like input is bounded before any work is done.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_MAGNITUDE, Table, check_float

T = TypeVar("T", bound="Options")

_KEY = "crtraj.option"


@dataclass(frozen=True)
class Bounds:
    """What one option field accepts (units are the field's own, given in its class docstring)."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    limit: float = MAX_MAGNITUDE
    choices: tuple[str, ...] | None = None
    max_len: int = 10_000
    read: bool = True


def option(
    default: Any,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    limit: float = MAX_MAGNITUDE,
    choices: Sequence[str] | None = None,
    max_len: int = 10_000,
    read: bool = True,
) -> Any:
    """A dataclass field with a default and the bounds that the readers enforce (see the module docstring)."""
    spec = Bounds(gt, ge, lt, le, limit, None if choices is None else tuple(choices), max_len, read)
    return dataclasses.field(default=default, metadata={_KEY: spec})


def _base_type(hint: Any) -> tuple[type, bool]:
    """(scalar type, optional) of an annotation such as ``float``, ``int | None`` or ``Optional[str]``."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return rest[0], True
    return hint, False


@dataclass(frozen=True)
class Options:
    """Base of every options section; subclasses set `SECTION` and declare fields with `option`."""

    SECTION: ClassVar[str] = "options"

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            spec = f.metadata.get(_KEY)
            if spec is None or not spec.read:
                continue
            typ, optional = _base_type(hints[f.name])
            value = getattr(self, f.name)
            if value is None and optional:
                continue
            name = f"{self.SECTION}.{f.name}"
            if typ is bool:
                if not isinstance(value, bool):
                    raise InputError(f"{name}: expected true or false, got {value!r}")
            elif typ is int:
                _check_int(value, name, spec)
                object.__setattr__(self, f.name, int(value))  # a numpy integer is stored as the file would give it
            elif typ is float:
                # store a float even when built with an int (1 -> 1.0), as a file would give
                v = check_float(value, name, gt=spec.gt, ge=spec.ge, lt=spec.lt, le=spec.le, limit=spec.limit)
                object.__setattr__(self, f.name, v)
            elif typ is str:
                _check_str(value, name, spec)
        self._check()

    def _check(self) -> None:
        """Cross-field rules of a subclass (raise `InputError` naming the field)."""

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        """Fields declared with ``read=False``, read by the subclass from the same table."""
        return {}

    @classmethod
    def from_table(cls: type[T], t: Table) -> T:
        """Read the section from a TOML table; unknown keys and bad values raise one-line `InputError`."""
        hints = typing.get_type_hints(cls)
        kw: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            spec = f.metadata.get(_KEY)
            if spec is None or not spec.read:
                continue
            typ, _ = _base_type(hints[f.name])
            d = f.default
            if typ is bool:
                kw[f.name] = t.bool(f.name, d) if d is not None or t.has(f.name) else None
            elif typ is int:
                if spec.le is None:
                    raise TypeError(f"{cls.__name__}.{f.name}: an int option needs an upper bound (le)")
                ge = None if spec.ge is None else math.ceil(spec.ge)
                kw[f.name] = t.int(f.name, d, ge=ge, le=int(spec.le))
            elif typ is float:
                kw[f.name] = t.float(f.name, d, gt=spec.gt, ge=spec.ge, lt=spec.lt, le=spec.le, limit=spec.limit)
            elif typ is str:
                kw[f.name] = t.str(f.name, d, choices=spec.choices, max_len=spec.max_len)
            else:
                raise TypeError(f"{cls.__name__}.{f.name}: option type {typ!r} is not readable; use read=False")
        kw.update(cls._read_extra(t))
        t.finish()
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        """Plain data in the TOML schema (None values are left out: they mean 'the default')."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            out[f.name] = [list(p) if isinstance(p, tuple) else p for p in v] if isinstance(v, tuple) else v
        return out

    def with_(self: T, **changes: Any) -> T:
        """A copy with some fields changed (checked like any other)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise InputError(f"{self.SECTION}.{unknown[0]}: unknown option")
        return dataclasses.replace(self, **changes)


def _check_int(value: Any, name: str, spec: Bounds) -> None:
    # numpy integers are ints too (a value computed in Python)
    numpy_int = hasattr(value, "dtype") and getattr(value.dtype, "kind", "") in "iu"
    if (isinstance(value, bool) or not isinstance(value, int)) and not numpy_int:
        raise InputError(f"{name}: expected an integer, got {value!r}")
    v = int(value)
    # integral bounds print as integers, as the file reader prints them (1000000, not 1e+06)
    if spec.ge is not None and v < spec.ge:
        raise InputError(f"{name}: must be >= {_bound(spec.ge)}, got {v}")
    if spec.gt is not None and v <= spec.gt:
        raise InputError(f"{name}: must be > {_bound(spec.gt)}, got {v}")
    if spec.le is not None and v > spec.le:
        raise InputError(f"{name}: must be <= {_bound(spec.le)}, got {v}")


def _bound(b: float) -> str:
    return str(int(b)) if float(b).is_integer() else f"{b:g}"


def _check_str(value: Any, name: str, spec: Bounds) -> None:
    if not isinstance(value, str):
        raise InputError(f"{name}: expected a string, got {value!r}")
    if len(value) > spec.max_len:
        raise InputError(f"{name}: longer than {spec.max_len} characters ({len(value)})")
    if spec.choices is not None and value not in spec.choices:
        raise InputError(f"{name}: must be one of {', '.join(spec.choices)}; got {value!r}")
