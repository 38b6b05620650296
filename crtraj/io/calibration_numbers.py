"""The one bounded reader of the numbers in calibration files (datasets, marker files, stream logs).

Every number goes through `crtraj.core.fields.check_float` (or its vectorised form here, with the same
messages): integers of any size, 1e300, NaN and infinity are refused with the field's name, and each kind of
quantity has a physical range. A CSV field is text: `text_number` parses it first. `display_path` makes a
file name safe to print and to write into TOML or JSON (undecodable bytes and control characters shown as
escapes), so a hostile name can never raise or corrupt an output.
"""

from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, check_float, read_number

# Marker coordinates (mm): a kilometre.
POSITION_LIMIT = MAX_LENGTH
# Actuator values: servo angles (rad) and the stage (mm); far beyond any servo's turns or stage's stroke.
VALUE_LIMIT = 1.0e5
# Timestamps (s): capture systems stamp with the Unix epoch (1.7e9 s in 2024); 1e10 s is the year 2286.
TIME_LIMIT = 1.0e10


def number(v: Any, name: str, limit: float) -> float:
    """A JSON number (not a bool or a string) with ``|v| <= limit``; `InputError` naming `name`."""
    return check_float(v, name, limit=limit)


def text_number(s: str, name: str, limit: float) -> float:
    """A number written as text (a CSV field), bounded like `number`: the core reader
    (`crtraj.core.fields.read_number`), which also refuses other scripts' digits, ``_`` and 400-digit integers."""
    return read_number(s, name, limit=limit)


def _plain_numbers(v: Any) -> bool:
    """True when `v` is a list (of lists ...) of ints and floats only: no bool, str, None or dict."""
    stack = [v]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            stack.extend(item)
        elif type(item) not in (int, float):
            return False
    return True


def _first_bad(a: np.ndarray, bad: np.ndarray) -> tuple[str, float]:
    idx = tuple(int(i) for i in np.argwhere(bad)[0])
    return "".join(f"[{i}]" for i in idx), float(a[idx])


def number_array(v: Any, name: str, shape: tuple[int, ...], limit: float) -> np.ndarray:
    """A float64 array of exactly `shape` from JSON lists; every entry a number with ``|x| <= limit``.

    The first bad entry is named with its index (``values[3][2]: must be finite, got nan``).
    """
    if not isinstance(v, list) or not _plain_numbers(v):
        raise InputError(f"{name}: expected numbers of shape {list(shape)}")
    try:
        a = np.asarray(v, dtype=float)
    except OverflowError:  # an integer beyond float range: find it for the message
        a = np.asarray(v, dtype=object)
        if a.shape == shape:
            for idx in np.ndindex(*shape):
                check_float(a[idx], name + "".join(f"[{i}]" for i in idx), limit=limit)
        raise InputError(f"{name}: an integer beyond the float range") from None
    except ValueError:  # ragged lists
        raise InputError(f"{name}: expected shape {list(shape)}") from None
    if a.shape != shape:
        raise InputError(f"{name}: expected shape {list(shape)}, got {list(a.shape)}")
    finite = np.isfinite(a)
    if not finite.all():
        at, x = _first_bad(a, ~finite)
        raise InputError(f"{name}{at}: must be finite, got {x}")
    big = np.abs(a) > limit
    if big.any():
        at, x = _first_bad(a, big)
        raise InputError(f"{name}{at}: must be within +-{limit:g}, got {x:g}")
    return a


def display_path(p: str | os.PathLike[str]) -> str:
    """A file name as printable text: undecodable bytes as ``\\xNN``, control characters as ``\\uNNNN``.

    Safe to print to any stream and to write into TOML or JSON (it holds no surrogate and no control
    character); a plain name is returned unchanged.
    """
    out = []
    for ch in os.fspath(p):
        o = ord(ch)
        if 0xDC80 <= o <= 0xDCFF:  # a byte that was not UTF-8 (surrogateescape)
            out.append(f"\\x{o - 0xDC00:02x}")
        elif 0xD800 <= o <= 0xDFFF or not ch.isprintable():
            out.append(f"\\u{o:04x}")
        else:
            out.append(ch)
    return "".join(out)


def finite_or_none(x: float) -> float | None:
    """x, or None when it is not finite (JSON and TOML have no NaN)."""
    return float(x) if math.isfinite(x) else None
