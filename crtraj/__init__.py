"""crtraj: safety-constrained motion planning for cable-driven continuum robots."""

from __future__ import annotations

__version__ = "0.1.0"
