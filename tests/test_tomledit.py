"""The TOML editor (`crtraj.core.tomledit.set_values`): only the asked values change, the rest of the text
round-trips byte for byte."""

from __future__ import annotations

import sys

import pytest

from crtraj.core.errors import InputError
from crtraj.core.tomledit import set_values

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def test_comments_blank_lines_and_number_formats_are_kept():
    """Comments on edited lines, other lines and their number formats stay exactly as written."""
    text = "# head\n[a]  # table\nx = 1.0   # keep me\nh = 0x1f\n\n# lone\ne = 1e3\n"
    out = set_values(text, {("a", "x"): 2.5})
    assert out == text.replace("x = 1.0 ", "x = 2.5 ")


def test_crlf_line_endings_round_trip():
    """A CRLF file is edited (not refused) and keeps CRLF on every line, added lines included."""
    text = "[a]\r\nx = 1 # c\r\n\r\n[b]\r\ny = 2\r\n"
    out = set_values(text, {("a", "x"): 5, ("a", "z"): 3, ("q", "r"): 1})
    assert "\n" not in out.replace("\r\n", "")
    assert out.startswith("[a]\r\nx = 5 # c\r\n")
    assert tomllib.loads(out) == {"a": {"x": 5, "z": 3}, "b": {"y": 2}, "q": {"r": 1}}


def test_inline_tables_are_edited_in_place():
    """A key of an inline table is edited, and a new one added, inside the braces."""
    text = "[a]\ninl = {p = 1, q = 2}  # inline\n"
    out = set_values(text, {("a", "inl", "p"): 7, ("a", "inl", "s"): 8})
    assert out == "[a]\ninl = {p = 7, q = 2, s = 8}  # inline\n"


def test_dotted_key_tables_are_edited_correctly():
    """A table defined through dotted keys gets its new key as another dotted key."""
    out = set_values("a.b = 1\n", {("a", "c"): 2.0})
    assert tomllib.loads(out) == {"a": {"b": 1, "c": 2.0}}


def test_control_characters_round_trip():
    """Tabs, newlines, DEL and other control characters in a string are escaped and read back as given."""
    value = "tab\there\x01\x7f\nline\r\x00"
    out = set_values('[a]\ns = "x"  # why\n', {("a", "s"): value})
    assert tomllib.loads(out)["a"]["s"] == value
    assert out.endswith("  # why\n") and out.count("\n") == 2


def test_text_that_is_not_utf8_safe_is_refused():
    """A lone surrogate cannot be written as UTF-8: one-line error naming the key, nothing returned."""
    with pytest.raises(InputError, match=r"a\.s: the text cannot be written as UTF-8"):
        set_values('[a]\ns = "x"\n', {("a", "s"): "bad \udc80"})


def test_non_finite_numbers_and_unknown_types_are_refused():
    """NaN and infinity have no place in a robot file; neither has an object TOML cannot hold."""
    with pytest.raises(InputError, match="non-finite"):
        set_values("[a]\nx = 1.0\n", {("a", "x"): float("nan")})
    with pytest.raises(InputError, match="cannot write a object"):
        set_values("[a]\nx = 1.0\n", {("a", "x"): object()})


def test_missing_array_table_is_refused():
    """An index past the last [[a.b]] cannot be created: refused, naming the path."""
    with pytest.raises(InputError, match=r"a\.b\[2\]"):
        set_values("[[a.b]]\nz = 1\n", {("a", "b", 2, "z"): 4})


def test_added_keys_carry_the_comment_and_edited_ones_do_not():
    """The caller's comment marks added lines only."""
    out = set_values("[a]\nx = 1\n", {("a", "x"): 2, ("a", "y"): 3}, comment="crtraj calibrate")
    assert out == "[a]\nx = 2\ny = 3 # crtraj calibrate\n"


def test_a_file_that_does_not_parse_is_refused():
    """Broken TOML: one line, not a traceback from the parser."""
    with pytest.raises(InputError, match="does not parse"):
        set_values("[a\nx = 1\n", {("a", "x"): 2})
