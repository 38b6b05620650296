"""The one exception type users see for bad input."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input: a one-line message that names the offending field or value."""
