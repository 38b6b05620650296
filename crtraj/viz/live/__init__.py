"""The live view of a running loop: the page, the feed that hands each step over, the drawing child process and
the link to the live meshcat server.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.viz.live._link": ("MeshcatWindow",),
        "crtraj.viz.live._view": ("LiveView",),
    },
)
