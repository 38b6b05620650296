"""Paths the command line's defaults name."""

from __future__ import annotations

from pathlib import Path

# the default robot file, problems/robots/cdsr2.toml of the repository (an editable install's tree)
DEFAULT_ROBOT = Path(__file__).resolve().parents[2] / "problems" / "robots" / "cdsr2.toml"
