"""The full page of a running loop: what a `LiveFeed` draws on for `crtraj replan --view`.

`LivePage` is a `crtraj.viz.live_feed.LiveFeed` drawer over a served `crtraj.viz.view.Visualizer`: it draws the
newest state (robot, obstacles with their D_sf shells, the closest-approach line) and, from every step the loop
recorded since the last draw, grows the page's numbers (in `crtraj.viz.page.run_fields`' layout): time, step status,
clearance to each obstacle, tip error against the plan, iteration time against the deadline, and the events
(replans, abnormal steps, deadline misses). The served page polls them, so its heads-up panel shows the newest
step and its plots grow. Everything here runs on the feed's thread, never on the loop's. Lengths in mm, times in s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.viz.page import legend, nums
from crtraj.viz.timeline import EVENT_STATUSES, Event, closest_approach


class LivePage:
    """Draws a running loop on a served Visualizer `vis` and keeps its page's numbers.

    model: the loop's model. safety_distance: D_sf (mm). deadline: the step deadline (s, NaN: none). names: the
    obstacles' names. goal: (3,) mm.
    """

    def __init__(
        self,
        vis: Any,
        model: Model,
        *,
        safety_distance: float,
        deadline: float,
        names: Sequence[str],
        goal: Any,
    ) -> None:
        self.vis, self.model = vis, model
        self.safety = float(safety_distance)
        self.deadline = float(deadline) if deadline and deadline > 0 else math.nan
        self.names = list(names)
        m = len(self.names)
        # the page's numbers, kept JSON-ready as they come (each draw converts only the new steps)
        self.t: list[float] = []
        self.status: list[str] = []
        self.clearance: list[list[float | None]] = [[] for _ in range(m)]
        self.near: list[int] = []
        self.tip_error: list[float | None] = []
        self.iteration: list[float | None] = []
        self.events: list[Event] = []
        self._closest_t, self._closest = 0.0, math.inf
        self._closest_pair: tuple[np.ndarray, np.ndarray] | None = None
        self.verdict = "running"
        vis.start_live(self.safety, goal, m)

    # ----------------------------------------------------------- the drawer
    def display(self, x: Any) -> None:
        """Draw the robot at x (nx,) and the closest approach of the newest step seen."""
        self.vis.display(x)
        if self._closest_pair is not None:
            self.vis.set_closest(*self._closest_pair)

    def set_obstacles(self, centers: Any, radii: Any) -> None:
        """Draw the obstacles (m, 3) / (m,) mm."""
        self.vis.set_obstacles(centers, radii)

    def extend(self, entries: Sequence[tuple[Any, Any]]) -> None:
        """Add the loop's records (StateRecord, StepRecord or None) to the page's numbers and send the page."""
        states = [s for s, _ in entries]
        X = np.array([s.x for s in states], dtype=float)
        m = len(self.names)
        C = np.array([np.reshape(s.centers, (-1, 3))[:m] for s in states], dtype=float).reshape(len(X), m, 3)
        R = np.array([np.reshape(s.radii, -1)[:m] for s in states], dtype=float).reshape(len(X), m)
        clear, near, body, obst = closest_approach(self.model, X, C, R, self.safety)
        planned = np.array([s.planned for s in states], dtype=float)
        tips = np.reshape(self.model.tip_position(X), (-1, 3))
        err = np.linalg.norm(tips - np.reshape(self.model.tip_position(planned), (-1, 3)), axis=1)
        for i in range(m):
            self.clearance[i].extend(nums(clear[:, i]))
        self.near.extend(int(i) for i in near)
        if m:
            self._closest_pair = (body[-1], obst[-1])
            k = int(np.argmin(clear.min(axis=1)))
            if clear[k].min() < self._closest:
                self._closest, self._closest_t = float(clear[k].min()), float(states[k].t)
        for (state, step), e in zip(entries, err, strict=True):
            self._add(float(state.t), step, float(e))
        self.push()

    def _add(self, t: float, step: Any, tip_error: float) -> None:
        status = str(step.step_status) if step is not None else ""
        it = float(step.iter_time) if step is not None else math.nan
        if status in EVENT_STATUSES and (not self.status or self.status[-1] != status):
            self.events.append(Event("dropout" if status == "stale" else status, t, f"step status {status}"))
        if math.isfinite(self.deadline) and it > self.deadline:
            self.events.append(Event("deadline", t, f"iteration {it * 1e3:.1f} ms > {self.deadline * 1e3:g} ms"))
        if step is not None and step.replanned and self.t:
            self.events.append(Event("replan", t, "new reference"))
        self.t.append(nums(t))
        self.status.append(status)
        self.tip_error.append(nums(tip_error))
        self.iteration.append(nums(it))

    # ------------------------------------------------------------- the page
    def data(self, live: bool = True) -> dict[str, Any]:
        """The page's data (`crtraj.viz.page.run_fields`' layout): one run, the loop so far (no actuator fractions
        live: null); live: the page keeps polling for more."""
        n = len(self.t)
        run = {
            "label": "",
            "kind": "replan",
            "verdict": self.verdict,
            "t": list(self.t),
            "status": list(self.status),
            "obstacles": list(self.names),
            "clearance": [list(c) for c in self.clearance],
            "near": list(self.near),
            "tip_error": list(self.tip_error),
            "iteration": list(self.iteration),
            "velocity": [None] * n,
            "acceleration": [None] * n,
            "deadline": nums(self.deadline),
            "safety_distance": self.safety,
            "closest_t": nums(self._closest_t),
            "events": [{"kind": e.kind, "t": nums(e.t), "text": e.text} for e in self.events],
        }
        return {"live": live, "runs": [run], "legend": legend(self.vis.options, self.model.robot.n_segments, False)}

    def push(self, live: bool = True) -> None:
        """Send the page's data to the server."""
        self.vis.push_page(self.data(live))
