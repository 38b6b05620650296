"""The live view of a running loop: a served full page (127.0.0.1), drawn by a child process.

`LiveView` starts a `crtraj.viz.view.Visualizer` with a server (the page at its `url`), a drawing process
(`crtraj.viz.live._child`) that draws a `crtraj.viz.live._page.LivePage` on that server, and the
`crtraj.viz.live._feed.LiveFeed` thread between the loop and the child: `feed` is the loop's observer
(`crtraj.control.ports.StepObserver`). The loop's thread only keeps references; the feed thread only packs the newest
state and the new steps into one buffer and waits for the child; the child does the drawing and sends each frame to
the server as one message. Lengths in mm, times in s.
"""

from __future__ import annotations

import math
from typing import Any

from crtraj.model.kinematics import Model
from crtraj.viz.live._child import ChildDrawer, setup_message
from crtraj.viz.live._feed import MAX_RATE_HZ, LiveFeed
from crtraj.viz.view import Visualizer

# The drawing process and the server run at this niceness: on a busy machine the loop keeps the CPU and the view
# takes what is left (benchmarks/viz_live.py measures both ways: docs/benchmarks.md).
VIEW_NICE = 19


class LiveView:
    """A served full page (127.0.0.1) fed by a running loop: a `Visualizer` with a server, a `LivePage` drawing
    on it and the `LiveFeed` thread between the loop and the page (`feed` is the loop's observer).

    model, goal (3,) mm, scene (safety_distance mm, obstacles with names), deadline (s, 0/None: none); rate: Hz of
    drawing (<= 30); options: `crtraj.viz.options.ViewOptions`; timeout: s for the server's start-up and replies;
    nice: niceness (0-19) of the drawing process and the server.
    """

    def __init__(
        self,
        model: Model,
        goal: Any,
        scene: Any,
        deadline: float | None,
        *,
        rate: float = MAX_RATE_HZ,
        options: Any = None,
        timeout: float = 60.0,
        nice: int = VIEW_NICE,
    ) -> None:
        self.vis = Visualizer(model, server=True, options=options, timeout=timeout, nice=nice)
        try:
            zmq_url = self.vis.zmq_url or ""
            setup = setup_message(model, zmq_url, scene, deadline or math.nan, goal, timeout)
            self.drawer = ChildDrawer(setup, nice=nice)
        except BaseException:
            self.vis.close()
            raise
        self.feed = LiveFeed(self.drawer, rate=rate)

    @classmethod
    def for_loop(cls, loop: Any, **kw: Any) -> LiveView:
        """The live view of a `crtraj.control.loop.ClosedLoop` (its model, goal, scene and step deadline)."""
        return cls(loop.model, loop.goal, loop.scene, loop.options.step_deadline, **kw)

    @property
    def url(self) -> str | None:
        """The full page's address on 127.0.0.1."""
        return self.vis.url

    def stop_feed(self) -> dict[str, int]:
        """Draw what is pending, stop the feed's thread and the drawing process (the server stays); the feed's
        counters (published, drawn, dropped, failed)."""
        self.feed.close()
        self.drawer.close()
        return self.feed.summary()

    def close(self) -> None:
        """Stop the feed, the drawing process and the server (idempotent)."""
        self.feed.close()
        self.drawer.close()
        self.vis.close()
