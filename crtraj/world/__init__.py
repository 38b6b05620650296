"""Scenes: obstacles over time, their packing for solvers, the safety margin, live obstacle sources. Above: model.

Public names load on first use (`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.world.scene": ("Scene",),
        "crtraj.world.obstacle": ("Obstacle",),
        "crtraj.world.feed": ("ObstacleFeed", "FeedOptions", "StaleFeedError"),
        "crtraj.world.sources": ("SceneObstacles", "FeedObstacles"),
        "crtraj.world.replay": ("FeedReplay", "ReplayOptions"),
    },
)
