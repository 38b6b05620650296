"""The meshcat browser view. Above: io.

Public names load on first use (`crtraj.core.lazy.lazy_exports`): meshcat only when a view is made.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.viz.view": ("Visualizer",),
        "crtraj.viz.options": ("ViewOptions",),
    },
)
