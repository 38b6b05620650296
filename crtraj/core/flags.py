"""argparse types that read a flag's text as strictly as a file's field (`crtraj.core.fields`).

`strict_flag_types` sets them on every option and positional of a parser and its subcommands, once:
an empty string for a path, URL, device or address flag is an error naming the flag (not "unset": an
empty ``--dynamixel ""`` would otherwise fall through to "no device"), and ``int``/``float`` flags take
ASCII text only (``int("١٢")`` is 12).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any


def strict_flag_types(parser: argparse.ArgumentParser, empty_allowed: frozenset[str] = frozenset()) -> None:
    """Make every plain string flag of `parser` (and its subcommands) refuse "", except the dests in
    `empty_allowed`, and every int or float flag refuse non-ASCII text."""
    for action in _all_actions(parser):
        if action.type is None and action.nargs != 0 and action.dest not in empty_allowed:
            action.type = non_empty
        elif action.type in (int, float):
            action.type = ascii_number(action.type)


def _all_actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """Every option and positional of every command."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for p in dict.fromkeys(action.choices.values()):
                out += _all_actions(p)
        else:
            out.append(action)
    return out


def ascii_number(kind: type) -> Callable[[str], Any]:
    """argparse type `kind` (int or float) that takes ASCII text only: ``int("١٢")`` is 12 and
    ``int("1_0")`` is 10, so other scripts' digits and ``_`` are refused like any other non-number."""

    def convert(text: str) -> Any:
        if not text.isascii() or "_" in text:
            raise ValueError(text)
        return kind(text)

    convert.__name__ = kind.__name__  # argparse names it in its message: "invalid int value: ..."
    return convert


def non_empty(value: str) -> str:
    """argparse type of every path, URL and device flag: an empty string is an error, not "unset"."""
    if not value:
        raise argparse.ArgumentTypeError("must not be empty")
    return value
