"""Shared foundations: input errors, the TOML/JSON field reader, atomic file writes. Imports nothing of crtraj.

Public names load on first use (`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.core.errors": ("InputError", "AdmissionError"),
        "crtraj.core.clock": ("Clock", "WallClock", "VirtualClock", "default_clock"),
        "crtraj.core.options": ("Options", "option"),
        "crtraj.core.fields": ("Table",),
        "crtraj.core.fileio": (
            "atomic_write_bytes",
            "atomic_write_json",
            "atomic_write_text",
            "json_document",
            "to_jsonable",
            "StagedDir",
            "StagedFile",
        ),
        "crtraj.core.build_cache": ("BuildCache",),
        "crtraj.core.lazy": ("lazy_exports", "lazy_module"),
        "crtraj.core.logs": ("configure_logging",),
        "crtraj.core.tomledit": ("set_values",),
        "crtraj.core.splines": ("BSplineCurve", "HermiteCubic"),
    },
)
