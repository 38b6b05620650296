"""Shared foundations: input errors, the TOML/JSON field reader, atomic file writes. Imports nothing of crtraj."""
