"""The full page of a running loop: what a `LiveFeed` draws on for `crtraj replan --view`.

`LivePage` is a `crtraj.viz.live._feed.LiveFeed` drawer over a served `crtraj.viz.view.Visualizer`: each `draw`
grows the page's numbers (in `crtraj.viz.page.run_fields`' layout) from every step the loop recorded since the last
draw: time, step status, clearance to each obstacle, tip error against the plan, iteration time against the
deadline, the largest actuator velocity and acceleration as fractions of their limits (from the executed actuation
the loop records for each step), and the events (replans, abnormal steps, deadline misses); then it sends the newest
state (robot, obstacles with their D_sf shells, the closest-approach line) and those new numbers to the server as
one message (`crtraj.viz.view.Visualizer.draw_frame`). The page's script moves the scene and appends the numbers,
so its heads-up panel shows the newest step and its plots grow. Everything here runs in the drawing process
(`crtraj.viz.live._child`), never on the loop's thread. Lengths in mm, times in s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from crtraj.model.kinematics import Model
from crtraj.viz.page import ROW_FIELDS, headline_text, legend, nums
from crtraj.viz.timeline import EVENT_STATUSES, Event, closest_approach


class ActuatorFractions:
    """The largest actuator velocity and acceleration of each step, as fractions of the limits, from the executed
    actuation samples the loop records (one per tracking period), as the replay measures them
    (`crtraj.viz.timeline`): finite differences of the actuator values over each period.

    limits: `crtraj.model.actuator_limits.ActuatorLimits` (None: no limits, every fraction NaN); rest: the
    straight-pose actuation (nq,) mm.
    """

    def __init__(self, limits: Any, rest: Any) -> None:
        self.limits, self.rest = limits, np.asarray(rest, dtype=float)
        self._t: float | None = None  # time (s) of the last sample
        self._value: np.ndarray | None = None  # actuator values of the last sample
        self._velocity: np.ndarray | None = None  # velocity over the period before it

    def start(self, t: float, q: Any) -> None:
        """The first recorded state: time t (s), actuation q (nq,) mm."""
        if self.limits is not None:
            self._t, self._value, self._velocity = float(t), self.limits.command(np.asarray(q, float), self.rest), None

    def step(self, t: float, executed: Any) -> tuple[float, float]:
        """(velocity, acceleration) fraction of the step ending at t (s), whose executed actuation `executed`
        (n, nq) mm was sampled at the end of each of its n equal periods; NaN where there is nothing to measure."""
        ex = np.asarray(executed, dtype=float).reshape(-1, len(self.rest))
        if self.limits is None or self._value is None or self._t is None or not len(ex) or not t > self._t:
            return math.nan, math.nan
        h = (t - self._t) / len(ex)
        values = self.limits.command(ex, self.rest)
        V = np.diff(np.vstack([self._value, values]), axis=0) / h
        A = np.diff(V if self._velocity is None else np.vstack([self._velocity, V]), axis=0) / h
        self._t, self._value, self._velocity = float(t), values[-1], V[-1]
        vf = float(np.max(np.abs(V) / self.limits.vmax))
        af = float(np.max(np.abs(A) / self.limits.amax)) if len(A) else math.nan
        return vf, af


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
        self.velocity: list[float | None] = []
        self.acceleration: list[float | None] = []
        self.events: list[Event] = []
        self._closest_t, self._closest, self._closest_j = 0.0, math.inf, -1
        self._held = self._fallback = self._over = 0  # steps so far, for the headline
        self._closest_pair: tuple[np.ndarray, np.ndarray] | None = None
        self.fractions = ActuatorFractions(model.robot.actuator_limits(), model.robot.cable_matrix()[1])
        self.verdict = "running"
        # the server may lack rows of a frame it did not answer in time: the next draw sends the whole data first
        self.resync = False
        vis.start_live(self.safety, goal, m)

    # ----------------------------------------------------------- the drawer
    def warm_up(self) -> None:
        """Evaluate every model function a draw uses once, on the straight configuration, drawing nothing: the
        first evaluation builds them (about 0.1 s), which belongs before the run, not in its first frame."""
        x = np.zeros((1, self.model.robot.nx))
        closest_approach(self.model, x, np.zeros((1, 1, 3)), np.ones((1, 1)), self.safety)
        self.model.tip_position(x)
        self.vis.robot_poses(x[0])

    def draw(self, state: Any, entries: Sequence[tuple[Any, Any]]) -> None:
        """Add the loop's records `entries` (StateRecord, StepRecord or None) to the page's numbers and draw
        `state` (t s, x, centers, radii mm) with them: one message to the server."""
        rows = self.extend(entries) if entries else None
        self.vis.draw_frame(state.x, state.centers, state.radii, closest=self._closest_pair, rows=rows)

    def extend(self, entries: Sequence[tuple[Any, Any]]) -> dict[str, Any]:
        """Add the loop's records (StateRecord, StepRecord or None) to the page's numbers; returns the new rows
        (`crtraj.viz.page.append_rows`)."""
        k0, e0 = len(self.t), len(self.events)
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
                self._closest_j = int(np.argmin(clear[k]))
        for (state, step), e in zip(entries, err, strict=True):
            self._add(state, step, float(e))
        rows: dict[str, Any] = {f: getattr(self, f)[k0:] for f in ROW_FIELDS}
        rows.update(k=k0, clearance=[c[k0:] for c in self.clearance], closest_t=nums(self._closest_t))
        rows["events"] = [_event(e) for e in self.events[e0:]]
        rows["headline"] = self.headline()
        return rows

    def headline(self) -> str:
        """The page's headline for the loop so far (`crtraj.viz.page.headline_text`; deadline misses are the
        loop's own count, known when the run ends)."""
        j = self._closest_j
        closest = (self._closest, self.names[j], self._closest_t) if j >= 0 else None
        counts = (self._held, self._fallback) if self.status else None
        return headline_text(closest, self.safety, counts, None, self._over, self.deadline)

    def _add(self, state: Any, step: Any, tip_error: float) -> None:
        t = float(state.t)
        status = str(step.step_status) if step is not None else ""
        it = float(step.iter_time) if step is not None else math.nan
        if step is None:
            self.fractions.start(t, state.q)
            vf = af = math.nan
        else:
            vf, af = self.fractions.step(t, step.executed)
        if status in EVENT_STATUSES and (not self.status or self.status[-1] != status):
            self.events.append(Event("dropout" if status == "stale" else status, t, f"step status {status}"))
        self._held += status == "hold"
        self._fallback += status == "fallback"
        if math.isfinite(self.deadline) and it > self.deadline:
            self._over += 1
            self.events.append(Event("deadline", t, f"iteration {it * 1e3:.1f} ms > {self.deadline * 1e3:g} ms"))
        if step is not None and step.replanned and self.t:
            self.events.append(Event("replan", t, "new reference"))
        self.t.append(nums(t))
        self.status.append(status)
        self.tip_error.append(nums(tip_error))
        self.iteration.append(nums(it))
        self.velocity.append(nums(vf))
        self.acceleration.append(nums(af))

    # ------------------------------------------------------------- the page
    def data(self, live: bool = True) -> dict[str, Any]:
        """The page's data (`crtraj.viz.page.run_fields`' layout): one run, the loop so far; live: the page
        takes new steps as they come (`crtraj.viz.page.append_rows`)."""
        run = {
            "label": "",
            "kind": "replan",
            "verdict": self.verdict,
            **{f: list(getattr(self, f)) for f in ROW_FIELDS},
            "obstacles": list(self.names),
            "clearance": [list(c) for c in self.clearance],
            "deadline": nums(self.deadline),
            "safety_distance": self.safety,
            "closest_t": nums(self._closest_t),
            "headline": self.headline(),
            "events": [_event(e) for e in self.events],
        }
        return {"live": live, "runs": [run], "legend": legend(self.vis.options, self.model.robot.n_segments, False)}

    def push(self, live: bool = True) -> None:
        """Send the page's data to the server."""
        self.vis.push_page(self.data(live))


def _event(e: Event) -> dict[str, Any]:
    return {"kind": e.kind, "t": nums(e.t), "text": e.text}
