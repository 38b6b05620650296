"""Obstacle sources: where the closed loop's obstacle states come from each step.

Both implement `crtraj.control.ports.ObstacleSource` (structurally; the port lives above this layer):
`SceneObstacles` for obstacles whose motion is known in advance, `FeedObstacles` for a live
`crtraj.world.feed.ObstacleFeed` predicted at constant velocity. Units: mm, s.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.world.obstacle import Obstacle


class SceneObstacles:
    """Obstacles whose motion is known in advance: the scene's time functions are the prediction."""

    live = False

    def __init__(self, scene: Any) -> None:
        self.scene = scene

    def at(self, t: float) -> tuple[Any, str]:
        """(the obstacles as a `Scene` in the loop's clock, '') at time t (s)."""
        return self.scene, ""

    def new_events(self) -> list[Any]:
        """Known motion records no events."""
        return []

    def describe(self) -> dict[str, Any]:
        """Known motion has no counters: {}."""
        return {}


class FeedObstacles:
    """Obstacles from a live `crtraj.world.feed.ObstacleFeed`, predicted at constant velocity.

    Each step turns the newest states into a `Scene` valid over the next
    `window` seconds: every centre moves on a straight line at its measured
    velocity (extrapolated from the measurement's age to now; the feed fits
    it over a time window and bounds it by its max_speed). The keep-out
    radius grows from the last measured radius at g = max(radius rate,
    |velocity|) (`FeedState.keep_out_growth`), so the keep-out sphere always
    contains the last measured sphere, however wrong the velocity. r + g tau
    is bounded over the window by ``r + g W sin(pi tau / (2 W))`` (the
    sine's arc lies above its chord), or held at r + g W when that sine is
    not allowed (amplitude above the mean radius). template: a `Scene` giving
    D_sf, the workspace and the expected obstacles (their names are the feed
    ids). A stale feed (an id missing or older than the feed's max_age) gives
    no scene, and the loop holds still. lead: s between reading the feed for
    a step and the device executing that step (a streamed run's buffer,
    `crtraj.hardware.link.DeviceLink.lead`); loop time t is then predicted `lead` s ahead of now.
    The feed's rejected messages reach the run's record through `new_events`.
    """

    live = True

    def __init__(self, feed: Any, template: Any, window: float, lead: float = 0.0) -> None:
        if not (math.isfinite(lead) and lead >= 0.0):
            raise InputError(f"lead: must be >= 0 s, got {lead}")
        self.feed = feed
        self.template = template
        self.lead = float(lead)
        self.window = float(window) + self.lead
        names = [o.name for o in template.obstacles]
        if not all(names):
            raise InputError("scene.obstacle: with a live feed every obstacle needs a name (its feed id)")
        self.ids = tuple(names)
        self._seen = 0  # feed events already handed to the loop

    def at(self, t: float) -> tuple[Any, str]:
        st = self.feed.latest()
        if st.stale:
            return None, f"obstacle feed stale: {st.reason}"
        missing = [i for i in self.ids if i not in st.ids]
        if missing:
            return None, f"obstacle feed stale: no state for {', '.join(missing)}"
        idx = [st.ids.index(i) for i in self.ids]
        W = self.window
        growth = st.keep_out_growth()
        obs = []
        for j, name in zip(idx, self.ids, strict=True):
            v = st.velocities[j]
            c = st.centers[j] + st.ages[j] * v  # where it is now
            g = float(growth[j])
            r_now = float(st.radii[j] + st.ages[j] * g)
            grow = g * W
            if grow <= r_now:
                radius = {"radius": r_now, "amplitude": grow, "omega": math.pi / (2.0 * W)}
            else:
                radius = {"radius": r_now + grow}
            moving = bool(np.any(v != 0.0))
            obs.append(
                Obstacle(center=tuple(c), to=tuple(c + W * v) if moving else None, duration=W, name=name, **radius)
            )
        # the snapshot's own clock starts now: loop time t maps to its time `lead`
        return replace(self.template, obstacles=tuple(obs), time_origin=self.lead - float(t)), ""

    def new_events(self) -> list[Any]:
        """The feed's events (`crtraj.world.feed.FeedEvent`) recorded since the last call."""
        events = getattr(self.feed, "events", None)
        if events is None:
            return []
        out = events(self._seen)
        self._seen += len(out)
        return out

    def describe(self) -> dict[str, Any]:
        """The feed's counters and options (`ObstacleFeed.describe` without its event list)."""
        d = getattr(self.feed, "describe", None)
        if d is None:
            return {}
        info = d()
        info.pop("events", None)
        return info
