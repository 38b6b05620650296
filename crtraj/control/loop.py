"""Closed-loop simulation of the receding-horizon replanner with the tracking controller.

`ClosedLoop` runs the paper's simulation 2 loop ("the robot periodically
updates its path based on its current position") at the replanner's step dt:

1. read the obstacles (the scene's known time functions);
2. keep a reference path toward the goal: plan it with the planner from the
   current configuration when there is none, when it becomes invalid (the
   next seconds of it collide with the predicted obstacles), when the robot
   stalls, after an NLP failure, or every `replan_period` seconds;
3. solve the horizon NLP (`crtraj.control.horizon.Replanner`) from the measured
   configuration toward the reference;
4. simulate the tracking controller (`crtraj.control.tracking.TrackingController`,
   with its servo model) over the step to get the motion the robot would
   really make, and verify that motion densely before applying it (the
   continuous body, every instant of the step, `validity.MotionValidator`
   bounds), together with a safe way to stop after it (holding the end
   configuration over the next step is safe);
5. if the move fails verification or the NLP failed, try the previous
   solution's next move, then holding still (actuators commanded to their
   measured positions: the servos stop where they are); if even holding is
   unsafe, apply the least unsafe of these and report it.

Every step records time, configuration, actuation, set-points, tip,
backbone, obstacle states, clearance (sampled densely in time, and the
conservative bound the decision used), NLP and planner time, status and the
solver's own status text. Units: mm, rad, s.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from crtraj.control.horizon import HorizonResult, Replanner, ReplanOptions
from crtraj.control.tracking import TrackingController, TrackingOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import check_array
from crtraj.model.kinematics import Model
from crtraj.planning.validity import MotionValidator
from crtraj.world.feed import FeedOptions
from crtraj.world.obstacle import Obstacle

# backbone points used to measure (not decide) clearance and to record the body
REPORT_POINTS = 41


class UnsolvableTaskError(Exception):
    """A well-formed task the loop cannot start: `status` is "invalid_start" (no safe start
    configuration) or "invalid_goal" (no configuration can ever put the tip on the goal safely).
    Not an input error: the command exits 1 with the status, as `crtraj plan` does."""

    def __init__(self, status: str, message: str) -> None:
        super().__init__(message)
        self.status = status


class StepStatus(str, enum.Enum):
    """What the loop did in one control step."""

    MOVE = "move"  # the NLP converged; its first move passed verification and was applied
    SUBOPTIMAL = "suboptimal"  # the NLP stopped at an iteration/time limit at a feasible point; move applied
    FALLBACK = "fallback"  # the NLP's move was unusable; the previous solution's next move was applied
    HOLD = "hold"  # no verified move: the robot held its configuration (verified safe)
    UNSAFE = "unsafe"  # nothing verified safe, not even holding: the least unsafe option was applied
    STALE = "stale"  # no trustworthy obstacle state (live feed stale): held still, nothing could be verified

    def __str__(self) -> str:
        return self.value


@dataclass(frozen=True)
class ReferencePlan:
    """A reference path toward the goal, or why there is none.

    configs: (K, nx) configurations, straight motions in between (empty
    when the planner found nothing). status, message: the planner's.
    wall_time: s. tree_edges: (E, 2, 3) tip positions for drawing.
    """

    configs: np.ndarray
    status: str
    message: str
    wall_time: float
    tree_edges: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))

    @property
    def ok(self) -> bool:
        return len(self.configs) >= 1


# (configuration (nx,), time s, the obstacles as known at that time: a Scene) -> ReferencePlan
ReferenceSource = Callable[[np.ndarray, float, Any], ReferencePlan]


class DirectReference:
    """Reference source without search: the straight motion to one known goal configuration (nx)."""

    def __init__(self, goal_config: Any) -> None:
        self.goal_config = np.array(check_array(goal_config, "goal_config", (None,)), dtype=float)

    def __call__(self, x: np.ndarray, t: float, scene: Any = None) -> ReferencePlan:
        return ReferencePlan(np.stack([np.asarray(x, float), self.goal_config]), "direct", "straight line", 0.0)


class PlannerReference:
    """Reference source backed by crtraj's planner: plans from the current configuration at time t.

    planner: a planner with ``plan(goal, start_config=, t0=, stop=, seed=, scene=, goal_tolerance=)``
    (`crtraj.planning.registry.make_planner`). goal: tip (mm). stop: a bounded
    `crtraj.planning.stop.StopCondition` per plan. seed: base seed; each call uses the
    next one so runs reproduce exactly. scene: always plan among these
    obstacles (e.g. none, for a run without the collision-free terms);
    default: the obstacles the loop passes with each call.
    """

    def __init__(
        self,
        planner: Any,
        goal: Any,
        *,
        goal_tolerance: float,
        stop: Any,
        seed: int = 0,
        scene: Any = None,
    ) -> None:
        stop.check_bounded()
        self.planner = planner
        self.goal = check_array(goal, "goal", (3,))
        self.goal_tolerance = float(goal_tolerance)
        self.stop = stop
        self.seed = int(seed)
        self.scene = scene
        self.calls = 0

    def __call__(self, x: np.ndarray, t: float, scene: Any = None) -> ReferencePlan:
        t1 = time.perf_counter()
        res = self.planner.plan(
            self.goal,
            start_config=np.asarray(x, float),
            t0=float(t),
            stop=self.stop,
            seed=self.seed + self.calls,
            scene=self.scene if self.scene is not None else scene,
            goal_tolerance=self.goal_tolerance,
        )
        self.calls += 1
        configs = res.configs if res.is_success() else np.zeros((0, len(x)))
        return ReferencePlan(configs, str(res.status), res.message, time.perf_counter() - t1, res.tree_edges)


class SceneObstacles:
    """Obstacles whose motion is known in advance: the scene's time functions are the prediction."""

    live = False

    def __init__(self, scene: Any) -> None:
        self.scene = scene

    def at(self, t: float) -> tuple[Any, str]:
        """(the obstacles as a `Scene` in the loop's clock, '') at time t (s)."""
        return self.scene, ""


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
    `DeviceLink.lead`); loop time t is then predicted `lead` s ahead of now.
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


class DeviceLink:
    """Drives a device live from the loop, through a started `crtraj.hardware.stream.Streamer`.

    Stream time is loop time. Each step's verified actuator motion (the
    servo model's response to the step's commands, sampled at the stream's
    rate) passes an acceleration-limited follower (every frame within 98 % of
    each actuator's velocity and acceleration limits, so joins between steps
    and restarts from rest never trip the streamer's gate) and is queued
    `lead` s before the device plays it: the loop computes step t at wall
    time S + t - lead while the device is at stream time t - lead.

    The measured configuration: while streaming, the device's telemetry at
    stream time tau, propagated to the step's start through the set-points
    already in flight with the servo model (the telemetry's deviation from
    the verified motion decays as the servo's lag); while held or waiting,
    the telemetry itself, with the held position as the command in force.
    `hold` latches the stream's hold (HOLD frames at the last sent
    position); the next move resumes from there, at rest. `estop` is final.
    Units: actuation q in mm, actuator values in rad / mm, times in s.
    """

    # late-loop holds the link may resume from; any other hold (telemetry lost, device refusal) ends the run
    _RECOVERABLE = ("source stalled", "set-point refused")

    def __init__(self, streamer: Any, servo: Any, dt: float, *, lead: float | None = None) -> None:
        self.streamer = streamer
        self.actuators = streamer.actuators
        self.servo = servo
        o = streamer.options
        self.fdt = o.dt
        n = dt * o.rate
        if abs(n - round(n)) > 1e-9 or round(n) < 1:
            raise InputError(f"stream.rate: must give whole frames per replan step of {dt:g} s, got {o.rate:g} Hz")
        self.frames_per_step = round(n)
        self.lead = max(o.prebuffer, dt) if lead is None else float(lead)
        if o.prebuffer < self.lead - 1e-9:
            raise InputError(f"stream.prebuffer: must be >= the link's lead {self.lead:g} s, got {o.prebuffer:g}")
        self._vmax = 0.98 * self.actuators.vmax
        self._amax = 0.98 * self.actuators.amax
        self._p: np.ndarray | None = None  # last queued set-point (actuator values) and its velocity
        self._v = np.zeros(self.actuators.n)
        self._S: float | None = None  # the stream plays stamp tau at wall time S + tau
        self._first: float | None = None  # first stamp queued since the stream (re)started
        self._origin: float | None = None  # the loop computes step t at wall time origin + t
        self._hist_t = np.zeros(0)
        self._hist_q = np.zeros((0, self.actuators.n))
        self._requested = False
        self._moving = False  # motion queued since the stream (re)started
        self._last_target: np.ndarray | None = None
        self.measured_steps = 0
        self.max_deviation = np.zeros(self.actuators.n)  # largest |set-point - verified motion| (rad, mm)
        self.restarts = 0
        self.holds = 0
        self.report: Any = None

    # --------------------------------------------------------------- state
    def start_actuation(self) -> np.ndarray:
        """Where the device is (its start telemetry, as actuation q in mm)."""
        p = self.streamer.position
        if p is None:
            raise InputError("--stream: the streamer has not started (no device position)")
        return self.actuators.actuation(p)

    def begin(self, t_origin: float) -> None:
        """Queue the device's position at stream time 0 (at rest); pace by t_origin until the stream runs."""
        self._origin = t_origin
        self._restart(0.0)

    def _restart(self, t: float) -> None:
        self._p = np.asarray(self.streamer.position, dtype=float)
        self._v = np.zeros(self.actuators.n)
        self._S, self._first, self._moving, self._last_target = None, t, False, self._p
        self.streamer.send_values(t, self._p)
        self._remember(np.array([t]), self.actuators.actuation(self._p)[None])

    def _remember(self, stamps: np.ndarray, Q: np.ndarray) -> None:
        keep = self._hist_t > stamps[0] - 2.0 * self.lead - 1.0
        self._hist_t = np.concatenate([self._hist_t[keep], stamps])
        self._hist_q = np.concatenate([self._hist_q[keep], Q])

    def problem(self) -> str:
        """Why the loop cannot drive the device any more ('' when it can)."""
        s = self.streamer
        if s.state in ("estop", "error", "done", "closed"):
            return f"device stream {s.state}: {s.reason}"
        if s.state == "held" and not self._requested and not s.reason.startswith(self._RECOVERABLE):
            return f"device held: {s.reason}"
        return ""

    def measure(self, t: float, q: np.ndarray, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """The measured actuation and the command in force at loop time t (mm), and whether the
        device's telemetry gave them (else the servo model's q, qc are returned unchanged)."""
        s = self.streamer
        tel = s.telemetry
        if tel is None or s.position is None:
            return q, qc, False
        q_tel = self.actuators.actuation(tel.positions)
        if s.state == "held" or not self._moving:
            # at rest, or braking to rest, at the last sent position
            self._S = None
            self.measured_steps += 1
            return q_tel, self.actuators.actuation(s.position), True
        if self._S is None or len(self._hist_t) < 2:
            return q, qc, False  # motion queued, the stream not yet running: the model knows best
        tau = min(time.perf_counter() - self._S, t)
        if tau < self._hist_t[0]:
            return q, qc, False
        ref = np.array([np.interp(tau, self._hist_t, self._hist_q[:, i]) for i in range(self.actuators.n)])
        self.measured_steps += 1
        return q + self.servo.decay(max(t - tau, 0.0)) * (q_tel - ref), qc, True

    # -------------------------------------------------------------- motion
    def move(self, t: float, q0: np.ndarray, commands: np.ndarray, control_dt: float) -> str:
        """Queue the verified motion of the step starting at loop time t from actuation q0 (mm) under
        `commands` (one per control period of control_dt s). Returns '' or why it was not sent."""
        s = self.streamer
        if s.state == "held":
            s.resume()
            self._requested = False
            self.restarts += 1
            self._restart(t)
        n = self.frames_per_step
        stamps = t + self.fdt * np.arange(1, n + 1)
        Q = self.verified(q0, commands, control_dt, self.fdt * np.arange(1, n + 1))
        target = self.actuators.command(Q)
        values = self._follow(target)
        self.max_deviation = np.maximum(self.max_deviation, np.max(np.abs(values - target), axis=0))
        from crtraj.hardware.stream import StreamError

        try:
            s.send_path(stamps, values)
        except StreamError as exc:  # held or stopped meanwhile; `problem` says whether that is final
            return str(exc)
        self._moving = True
        self._remember(stamps, Q)
        self._clock_after_queue(t, stamps[-1])
        return ""

    def verified(self, q0: np.ndarray, commands: np.ndarray, h: float, offsets: np.ndarray) -> np.ndarray:
        """Actuation (len(offsets), nq) of the servo model at `offsets` s into the step (0 < offset <= n h)."""
        C = np.asarray(commands, dtype=float)
        starts = [np.asarray(q0, dtype=float)]
        for c in C[:-1]:
            starts.append(self.servo.advance(starts[-1], c, h))
        j = np.clip(np.ceil(offsets / h - 1e-9).astype(int) - 1, 0, len(C) - 1)
        tau = (offsets - j * h)[:, None]
        Q0 = np.array(starts)[j]
        return C[j] + np.exp(-tau / self.servo.tau) * (Q0 - C[j])

    def _follow(self, target: np.ndarray) -> np.ndarray:
        """Set-points tracking `target` (frames, n) with |v| <= vmax and |dv| <= amax dt per frame.

        The target's own frame velocity is fed forward; the remaining error is closed at the
        speed from which it can still brake to zero (sqrt(2 a e)), so the follower does not
        overshoot a target that stops."""
        dt, vmax, amax = self.fdt, self._vmax, self._amax
        p, v = self._p, self._v
        prev = p if self._last_target is None else self._last_target
        out = np.empty_like(target)
        for k, d in enumerate(target):
            vt = (d - prev) / dt
            e = d - (p + vt * dt)
            corr = np.sign(e) * np.minimum(np.abs(e) / dt, np.sqrt(amax * np.abs(e)))
            v_new = np.clip(v + np.clip(vt + corr - v, -amax * dt, amax * dt), -vmax, vmax)
            p = p + v_new * dt
            v, prev = v_new, d
            out[k] = p
        self._p, self._v, self._last_target = p, v, prev
        return out

    def _clock_after_queue(self, t: float, last: float) -> None:
        now = time.perf_counter()
        s = self.streamer
        if self._S is None:
            if self._first is not None and last - self._first >= s.options.prebuffer - 1e-9:
                # the stream starts on its next tick (within one period) from the first stamp
                self._S = now + 0.5 * self.fdt - self._first
                self._origin = self._S - self.lead
        elif now > self._S + t:
            # queued after the stream needed it: the stream waited at stamp t until now
            self._S = now - t
            self._origin = self._S - self.lead

    def pace(self, t: float) -> bool:
        """Sleep until loop time t is due; True when the loop is more than one step late."""
        origin = self._origin
        if origin is None:
            return False
        lag = time.perf_counter() - origin - t
        if lag < 0.0:
            time.sleep(-lag)
        return lag > self.frames_per_step * self.fdt

    # ------------------------------------------------------------- control
    def hold(self, reason: str) -> None:
        """Latch the stream's hold (the device stops at the last sent set-point)."""
        s = self.streamer
        if s.state not in ("held", "estop", "error", "done", "closed"):
            s.hold(reason)
            self.holds += 1
        self._requested = True
        self._S, self._moving = None, False
        if s.position is not None:
            self._p, self._v = np.asarray(s.position, dtype=float), np.zeros(self.actuators.n)
            self._last_target = self._p

    def estop(self, reason: str) -> None:
        self.streamer.estop(reason)

    def finish(self, q_final: np.ndarray, timeout: float = 10.0) -> Any:
        """Bring the set-points to rest at q_final (mm), let the device settle, close; the `StreamReport`.
        A held or stopped stream is only closed (the device stays where it is)."""
        from crtraj.hardware.stream import StreamError

        s = self.streamer
        if s.state in ("waiting", "streaming") and self._p is not None:
            goal = self.actuators.command(np.asarray(q_final, dtype=float))
            tail = []
            for _ in range(int(timeout / self.fdt)):
                tail.append(self._follow(goal[None])[0])
                if np.all(np.abs(tail[-1] - goal) <= 1e-6) and np.all(np.abs(self._v) * self.fdt <= 1e-6):
                    tail.append(goal)  # the last micro-step, far inside every limit
                    break
            t = float(self._hist_t[-1]) if len(self._hist_t) else 0.0
            try:
                s.send_path(t + self.fdt * np.arange(1, len(tail) + 1), np.array(tail))
                s.finish()
                s.wait(len(tail) * self.fdt + self.lead + s.options.settle_timeout + 2.0)
            except StreamError:
                pass  # stopped meanwhile: the report says why
        self.report = s.close()
        return self.report

    def describe(self) -> dict[str, Any]:
        """What the link did, for the run record: the stream report and the follower's deviation."""
        rep = self.report.to_dict() if self.report is not None else {}
        return {
            "stream": rep,
            "lead_s": self.lead,
            "max_setpoint_deviation": dict(zip(self.actuators.names, self.max_deviation.tolist(), strict=True)),
            "restarts": self.restarts,
            "holds": self.holds,
            "measured_steps": self.measured_steps,
        }


class _Reference:
    """A reference path timed by the rate limits; progress is tracked by projection, not by the clock."""

    def __init__(self, configs: np.ndarray, seconds_per: Callable[[np.ndarray], np.ndarray], metric: Any) -> None:
        X = np.asarray(configs, dtype=float)
        if len(X) == 1:
            X = np.concatenate([X, X])
        self.X = X
        self.s = np.concatenate([[0.0], np.cumsum(seconds_per(np.diff(X, axis=0)))])
        self.end = float(self.s[-1])
        self.Y = metric(X)  # body-motion units (mm) for projections
        self._metric = metric

    def at(self, s: np.ndarray) -> np.ndarray:
        """Configurations at path times s (s), clamped to the path."""
        s = np.clip(np.asarray(s, dtype=float), 0.0, self.end)
        if self.end == 0.0:
            return np.broadcast_to(self.X[-1], (*s.shape, self.X.shape[1])).copy()
        i = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.X) - 2)
        seg = self.s[i + 1] - self.s[i]
        u = np.divide(s - self.s[i], seg, out=np.zeros_like(s), where=seg > 0)
        return self.X[i] + u[..., None] * (self.X[i + 1] - self.X[i])

    def locate(self, x: np.ndarray, s_hint: float, back: float, ahead: float) -> float:
        """Path time of the point nearest to x (body-motion metric) within [s_hint - back, s_hint + ahead]."""
        if self.end == 0.0:
            return 0.0
        y = self._metric(np.asarray(x, dtype=float)[None])[0]
        lo, hi = s_hint - back, s_hint + ahead
        segs = np.flatnonzero((self.s[1:] >= lo) & (self.s[:-1] <= hi))
        if not len(segs):
            segs = np.arange(len(self.X) - 1)
        A, B = self.Y[segs], self.Y[segs + 1]
        AB = B - A
        den = np.maximum(np.sum(AB * AB, axis=1), 1e-300)
        u = np.clip(np.sum((y - A) * AB, axis=1) / den, 0.0, 1.0)
        d = np.linalg.norm(A + u[:, None] * AB - y, axis=1)
        j = int(np.argmin(d))
        i = segs[j]
        return float(np.clip(self.s[i] + u[j] * (self.s[i + 1] - self.s[i]), lo, hi))


@dataclass(frozen=True)
class ReplanRun:
    """A closed-loop run. Arrays have one row per recorded time t[k] (k = 0..K).

    t (K+1,) s; x (K+1, nx) actual configurations; q (K+1, nq) actual actuator
    positions (mm); q_command (K+1, nq) the actuator set-point in force at
    t[k] (mm); tip (K+1, 3) mm; backbone
    (K+1, P, 3) mm; centers (K+1, m, 3), radii (K+1, m) obstacle states (mm);
    clearance (K+1,) mm: min over the step ending at t[k] of the body
    clearance (distance to the obstacle surface minus body radius and D_sf),
    sampled densely in time and along the body; distance (K+1,) the same
    without D_sf (negative = the body touches an obstacle); clearance_bound
    (K+1,) mm the conservative bound the decision used; planned (K+1, nx) the
    configuration the NLP planned for t[k]; tip_error (K+1,) mm: actual tip
    to planned tip; goal_error (K+1,) mm: actual tip to goal. Per step (K,):
    status, solver_status, nlp_time, plan_time, iter_time (s), iterations,
    replanned (bool), reason (why the reference was replanned, or "").
    dense_t, dense_x: every verification sample of the actual motion.
    commands: (K n_sub, nq) actuator set-point of every tracking period of
    length control_dt (s), from t = 0: with the servo model and q[0] they
    reproduce the actual motion at any instant (for independent re-checks).
    reference_tips: tip polylines of every reference path used, with the
    step index each started at. feed: a live feed's counters, options and
    every rejected or clamped message (loop time t, receiver time, kind,
    reason); {} without a feed.
    """

    t: np.ndarray
    x: np.ndarray
    q: np.ndarray
    q_command: np.ndarray
    tip: np.ndarray
    backbone: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    clearance: np.ndarray
    distance: np.ndarray
    clearance_bound: np.ndarray
    planned: np.ndarray
    tip_error: np.ndarray
    goal_error: np.ndarray
    status: tuple[str, ...]
    solver_status: tuple[str, ...]
    nlp_time: np.ndarray
    plan_time: np.ndarray
    iter_time: np.ndarray
    iterations: np.ndarray
    replanned: np.ndarray
    reason: tuple[str, ...]
    dense_t: np.ndarray
    dense_x: np.ndarray
    commands: np.ndarray
    control_dt: float
    reference_tips: tuple[tuple[int, np.ndarray], ...]
    tree_edges: np.ndarray
    goal: np.ndarray
    reached: bool
    outcome: str
    message: str
    safety: bool
    setup_time: float
    wall_time: float
    nlp: dict[str, Any] = field(default_factory=dict)
    late_steps: int = 0
    live: bool = False
    device: dict[str, Any] = field(default_factory=dict)  # `DeviceLink.describe` of a live-streamed run
    feed: dict[str, Any] = field(default_factory=dict)  # a live feed's counters and rejections (`_Log.feed_record`)

    @property
    def steps(self) -> int:
        return len(self.status)

    @property
    def success(self) -> bool:
        """Reached the goal without any step breaking D_sf."""
        return self.reached and self.safety_violations == 0

    @property
    def collisions(self) -> int:
        """Steps during which the body touched an obstacle (sampled distance < 0)."""
        return int(np.sum(self.distance[1:] < 0.0))

    @property
    def safety_violations(self) -> int:
        """Steps during which the body came closer than D_sf (sampled clearance < 0)."""
        return int(np.sum(self.clearance[1:] < 0.0))

    def summary(self) -> dict[str, Any]:
        """Headline figures (mm, s) for printing and the result file."""
        it = self.iter_time
        counts: dict[str, int] = {}
        for s in self.status:
            counts[s] = counts.get(s, 0) + 1
        return {
            "outcome": self.outcome,
            "reached_goal": self.reached,
            "safety": self.safety,
            "steps": self.steps,
            "duration_s": float(self.t[-1] - self.t[0]),
            "collisions": self.collisions,
            "safety_violations": self.safety_violations,
            "min_clearance_mm": float(np.min(self.clearance[1:])) if self.steps else math.nan,
            "min_distance_mm": float(np.min(self.distance[1:])) if self.steps else math.nan,
            "min_clearance_bound_mm": float(np.min(self.clearance_bound[1:])) if self.steps else math.nan,
            "median_iteration_s": float(np.median(it)) if self.steps else math.nan,
            "p90_iteration_s": float(np.percentile(it, 90)) if self.steps else math.nan,
            "max_iteration_s": float(np.max(it)) if self.steps else math.nan,
            "median_nlp_s": float(np.median(self.nlp_time)) if self.steps else math.nan,
            "p90_nlp_s": float(np.percentile(self.nlp_time, 90)) if self.steps else math.nan,
            "median_nlp_iterations": float(np.median(self.iterations)) if self.steps else math.nan,
            "final_tip_error_mm": float(self.goal_error[-1]),
            "max_tracking_error_mm": float(np.max(self.tip_error)),
            "reference_plans": int(np.sum(self.replanned)),
            "planner_time_s": float(np.sum(self.plan_time)),
            "status_counts": counts,
            "live_obstacles": self.live,
            "feed_rejected": int(self.feed.get("rejected", 0)),
            "feed_events": dict(self.feed.get("counts", {})),
            "late_steps": self.late_steps,
            "setup_s": self.setup_time,
            "wall_time_s": self.wall_time,
        }

    def summary_line(self) -> str:
        """One line: reached?, collisions, min clearance, median/p90 time per iteration, final tip error."""
        s = self.summary()
        return (
            f"{self.outcome}: reached goal {'yes' if self.reached else 'no'}, "
            f"collisions {s['collisions']} (D_sf breaches {s['safety_violations']}), "
            f"min clearance {s['min_clearance_mm']:.2f} mm, "
            f"iteration median {s['median_iteration_s'] * 1e3:.2f} ms / p90 {s['p90_iteration_s'] * 1e3:.2f} ms, "
            f"final tip error {s['final_tip_error_mm']:.3f} mm, {self.steps} steps, "
            f"{s['reference_plans']} reference plans"
        )


class ClosedLoop:
    """The replanning loop for one robot, scene and goal.

    model: the robot's `Model`. scene: `crtraj.world.scene.Scene` (obstacle truth
    and prediction). goal: tip position (mm). start_config: (nx,) the
    robot's configuration at t = 0 (servos settled). options:
    `ReplanOptions`. tracking: `TrackingOptions` (its dt must divide the
    replanner's dt). reference: a `ReferenceSource` ((x, t) ->
    `ReferencePlan`); default: the straight motion to `goal_config`.
    replanner: a prebuilt `Replanner` (tests inject failures this way).
    goal_tolerance: mm. goal_config: used by the default reference.
    initial_reference: a reference already planned from start_config at t = 0
    (saves the first planner call). extra_options: more option sections
    (name -> object with ``to_dict``) recorded in result files.
    obstacles: where the obstacle states come from each step: `SceneObstacles`
    (default: the scene's known time functions) or `FeedObstacles` (a live
    feed, extrapolated at constant velocity; the scene then only gives D_sf,
    the workspace and the expected obstacles).
    """

    def __init__(
        self,
        model: Model,
        scene: Any,
        goal: Any,
        start_config: Any,
        *,
        options: ReplanOptions | None = None,
        tracking: TrackingOptions | None = None,
        reference: ReferenceSource | None = None,
        replanner: Replanner | None = None,
        goal_tolerance: float = 0.5,
        goal_config: Any = None,
        initial_reference: ReferencePlan | None = None,
        extra_options: dict[str, Any] | None = None,
        obstacles: Any = None,
    ) -> None:
        t_setup = time.perf_counter()
        self.model = model
        self.robot = model.robot
        self.scene = scene
        self.options = ReplanOptions() if options is None else options
        o = self.options
        self.goal = check_array(goal, "goal", (3,))
        self.x_start = check_array(start_config, "start_config", (self.robot.nx,))
        if not goal_tolerance > 0:
            raise InputError(f"goal_tolerance: must be > 0 mm, got {goal_tolerance}")
        self.goal_tolerance = float(goal_tolerance)
        tr = TrackingOptions() if tracking is None else tracking
        n_sub = o.dt / tr.dt
        if abs(n_sub - round(n_sub)) > 1e-9 or round(n_sub) < 1:
            raise InputError(
                f"tracking.dt: must divide replan.dt = {o.dt:g} s into whole control periods, got {tr.dt:g} s"
            )
        self.n_sub = round(n_sub)
        if o.max_cable_speed > tr.max_cable_rate or o.max_z_speed > tr.max_z_rate:
            raise InputError(
                f"replan.max_cable_speed / max_z_speed ({o.max_cable_speed:g} / {o.max_z_speed:g} mm/s) "
                f"must not exceed the tracking rate limits ({tr.max_cable_rate:g} / {tr.max_z_rate:g} mm/s)"
            )
        self.tracker = TrackingController(model, tr)
        self.servo = self.tracker.servo
        if reference is None:
            if goal_config is None:
                raise InputError("reference: give a reference source or a goal_config")
            reference = DirectReference(check_array(goal_config, "goal_config", (self.robot.nx,)))
        self.reference_source = reference
        self.initial_reference = initial_reference
        self.tracking_options = tr
        self.extra_options = dict(extra_options or {})
        self.replanner = (
            replanner
            if replanner is not None
            else Replanner(model, o, max_obstacles=scene.n_obstacles, safety_distance=scene.safety_distance)
        )
        if self.replanner.options.dt != o.dt or o.horizon != self.replanner.N:
            raise InputError("replanner: its dt and horizon must match the loop's options")
        self.obstacles = SceneObstacles(scene) if obstacles is None else obstacles
        self._fns: dict[Any, Any] = {}  # CasADi functions shared by every step's validator
        self.validator = self._validator(scene)
        self._scene_now = scene
        A, _ = self.robot.cable_matrix()
        self._A = A
        self._rates = np.append(np.full(3 * self.robot.n_segments, o.max_cable_speed), o.max_z_speed)
        self.setup_time = time.perf_counter() - t_setup

    # ------------------------------------------------------------ utilities
    def _validator(self, scene: Any) -> MotionValidator:
        o = self.options
        return MotionValidator(
            self.model, scene, check_points=o.check_points, resolution=o.check_resolution, functions=self._fns
        )

    def _use(self, scene: Any) -> None:
        """Make `scene` the obstacles every check of this step uses."""
        if scene is not self._scene_now:
            self._scene_now = scene
            self.validator = self._validator(scene)

    def _seconds_per(self, dX: np.ndarray) -> np.ndarray:
        """Time (s) each configuration change takes at `reference_speed` times the rate limits."""
        o = self.options
        dq = np.abs(dX @ self._A.T)
        t_act = np.max(dq / (o.reference_speed * self._rates), axis=1)
        t_body = self.validator.motion_bound(dX) / (o.reference_speed * o.max_body_speed)
        return np.maximum(t_act, t_body)

    def _track(
        self, q: np.ndarray, qc: np.ndarray, x0: np.ndarray, x1: np.ndarray, t: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Simulate the tracking controller toward the straight move x0 -> x1 over one step.

        Returns (q at the end, set-point at the end, sample times (S,),
        actual configurations at the samples (S, nx), set-points per control
        period (n_sub, nq)). The first sample is the current state at t.
        """
        o, n, ctl, servo, v = self.options, self.n_sub, self.tracker, self.servo, self.validator
        h = o.dt / n
        rate = (x1 - x0) / o.dt
        ts, xs = [np.array([t])], [servo.config(q)[None]]
        cmds = np.empty((n, self.robot.nq))
        for j in range(n):
            xm = servo.config(q)
            cmd = ctl.step(xm, qc, x0 + (j + 1) / n * (x1 - x0), h, x_reference_rate=rate)
            q_end = servo.advance(q, cmd.q, h)
            span = float(v.motion_bound(servo.config(q_end) - xm))
            ns = max(1, math.ceil(2.0 * span / o.check_resolution))
            tau = h * np.arange(1, ns + 1) / ns
            ts.append(t + j * h + tau)
            xs.append(servo.config(servo.trajectory(q, cmd.q, tau)))
            q, qc = q_end, cmd.q
            cmds[j] = qc
        return q, qc, np.concatenate(ts), np.concatenate(xs), cmds

    def _verify(self, T: np.ndarray, X: np.ndarray, after: tuple[float, float] | None) -> float:
        """Conservative body clearance (mm, minus D_sf) of the sampled motion X at times T.

        after: a time window (s) over which the last configuration, held
        still, must also be clear (so the robot can always stop safely).

        Between two samples every actuator moves monotonically (first-order
        servos), and the bending part moves along a straight line, so each
        configuration in between is within half the body-motion bound of the
        two samples from one of them; each sample therefore must clear, over
        the time window from its previous to its next sample, the obstacles
        by that half bound on top of the validator's chord/sagitta bounds.
        """
        v = self.validator
        if len(X) == 1:
            half, t_lo, t_hi = np.zeros(1), T[:1], T[:1]
        else:
            B = v.motion_bound(np.diff(X, axis=0))
            half = 0.5 * np.concatenate([[B[0]], np.maximum(B[:-1], B[1:]), [B[-1]]])
            t_lo = np.concatenate([[T[0]], T[:-1]])
            t_hi = np.concatenate([T[1:], [T[-1]]])
        if after is not None:
            X = np.concatenate([X, X[-1:]])
            half = np.append(half, 0.0)
            t_lo = np.append(t_lo, after[0])
            t_hi = np.append(t_hi, after[1])
        return float(np.min(v.clearance(X, t_lo, t_hi, half)))

    def _measure(self, T: np.ndarray, X: np.ndarray) -> float:
        """Sampled (not conservative) body clearance (mm, minus D_sf) along the motion, many points."""
        P = self.model.points(X, REPORT_POINTS)
        return float(np.min(self._scene_now.clearance_points(P, T, inflate=self.robot.body_radius)))

    def _reference_valid(self, ref: _Reference, s_now: float, t: float) -> bool:
        """The next stretch of the reference is clear of the obstacles at the times it would be reached."""
        o = self.options
        look = max(2.0 * o.horizon * o.dt, 2.0)
        s = np.linspace(s_now, min(s_now + look, ref.end), 12)
        X = ref.at(s)
        tt = t + (s - s_now)
        return bool(np.all(self.validator.clearance(X, tt - o.dt, tt + o.dt) >= 0.0))

    # ------------------------------------------------------------------- run
    def run(
        self,
        *,
        progress: Callable[[int, float, str], None] | None = None,
        realtime: bool | None = None,
        device: DeviceLink | None = None,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], None] | None = None,
    ) -> ReplanRun:
        """Simulate from the start configuration until the goal is held, or `duration` runs out.

        progress: called after every step with (step index, time s, status).
        realtime: pace the steps by the wall clock (default: only with a live
        obstacle source, whose states are only meaningful in real time).
        device: drive a device live (`DeviceLink`, real time): the run starts
        where the device is, every verified move is streamed as it is chosen,
        the device's telemetry is the measured configuration, a held or stale
        step holds the device, an unsafe step e-stops it and ends the run, and
        Ctrl-C holds it and ends the run (outcome "interrupted"). The link is
        finished (device settled at the final actuation) and closed on return.
        clock, sleep: the time (s) and the sleep that pace a real-time run without a device and
        bound the wait for a live feed's first states (default: the wall clock); a virtual clock
        shared with the feed makes a live run independent of the machine's speed.
        """
        t_wall = time.perf_counter()
        clock = time.perf_counter if clock is None else clock
        sleep = time.sleep if sleep is None else sleep
        o, rp = self.options, self.replanner
        live = bool(getattr(self.obstacles, "live", False))
        realtime = live if realtime is None or device is not None else bool(realtime)
        q = self.tracker.initial_command(self.x_start) if device is None else device.start_actuation()
        st = _State(q=q, qc=q.copy(), x=self.servo.config(q))
        st.x_prev = st.x.copy()
        rp.reset()
        log = _Log()
        scene0, why = self.obstacles.at(0.0)
        deadline = clock() + 2.0
        while scene0 is None and live and clock() < deadline:
            sleep(0.01)  # give a live feed a moment to deliver its first states
            scene0, why = self.obstacles.at(0.0)
        log.feed_events(self.obstacles, 0.0)
        if scene0 is None:
            log.record(
                0.0,
                st,
                math.nan,
                math.nan,
                math.nan,
                st.x,
                np.zeros((0, self.robot.nq)),
                np.zeros(1),
                st.x[None],
                self.scene,
            )
            msg = f"no obstacle state to start from: {why}"
            return self._finish(log, st, False, "no_obstacles", msg, t_wall, device)
        self._use(scene0)
        c0 = self._measure(np.array([0.0]), st.x[None])
        b0 = self._verify(np.array([0.0]), st.x[None], None)
        log.record(
            0.0,
            st,
            c0,
            c0 + self.scene.safety_distance,
            b0,
            st.x,
            np.zeros((0, self.robot.nq)),
            np.array([0.0]),
            st.x[None],
            scene0,
        )
        if o.safety and b0 < 0.0:
            msg = f"the start configuration is not clear of the obstacles at t = 0 (bound {b0:.2f} mm)"
            return self._finish(log, st, False, "invalid_start", msg, t_wall, device)
        t_clock = clock()
        if device is not None:
            device.begin(time.perf_counter())
        try:
            return self._steps(log, st, t_wall, (clock, sleep, t_clock), realtime, progress, device)
        except KeyboardInterrupt:
            if device is None:
                raise
            device.hold("interrupted (Ctrl-C)")
            return self._finish(log, st, False, "interrupted", "interrupted (Ctrl-C): device held", t_wall, device)

    def _steps(
        self,
        log: _Log,
        st: _State,
        t_wall: float,
        pacing: tuple[Callable[[], float], Callable[[float], None], float],
        realtime: bool,
        progress: Callable[[int, float, str], None] | None,
        device: DeviceLink | None,
    ) -> ReplanRun:
        """The control steps of `run` after the start checks. pacing: (clock, sleep, clock at t = 0)."""
        o, rp, dt = self.options, self.replanner, self.options.dt
        clock, sleep, t_clock = pacing
        settled_since: float | None = None
        reached = False
        for k in range(math.ceil(o.duration / dt - 1e-9)):
            t = st.t
            t_iter = time.perf_counter()
            if device is not None:
                why_not = device.problem()
                if why_not:
                    return self._finish(log, st, False, "device", why_not, t_wall, device)
                st.q, st.qc, _ = device.measure(t, st.q, st.qc)
                st.x = self.servo.config(st.q)
            scene_t, why = self.obstacles.at(t)
            log.feed_events(self.obstacles, t)
            if scene_t is None:
                # no trustworthy obstacle state: keep the actuators where they are and say so
                status, res = StepStatus.STALE, _skipped(self.replanner, f"skipped: {why}")
                x1, bound = st.x.copy(), math.nan
                sim = self._hold(st)
                reason, plan_time, replanned, charged = "", 0.0, False, 0.0
                st.last_plan = None
                rp.reset()
            else:
                self._use(scene_t)
                reason, plan_time, replanned, charged = self._update_reference(st, k)
                X_ref = st.horizon_reference(self.replanner.N, dt)
                res = self._solve(st.x, X_ref, rp.obstacles_from_scene(scene_t, t), st.x_prev)
                st.nlp_failed = not res.feasible
                status, x1, sim, bound = self._choose(st, res)
            iter_time = time.perf_counter() - t_iter + charged
            q_new, qc_new, T, X, cmds = sim
            if device is not None:
                if status in (StepStatus.STALE, StepStatus.HOLD):
                    device.hold(f"replanner {status} at t={t:.2f} s" + (f": {why}" if why else ""))
                elif status is StepStatus.UNSAFE:
                    device.estop(f"unsafe step at t={t:.2f} s (clearance bound {bound:.2f} mm)")
                else:
                    device.move(t, st.q, cmds, dt / self.n_sub)
            measured = self._measure(T, X)
            st.x_prev, st.x, st.q, st.qc = st.x, self.servo.config(q_new), q_new, qc_new
            st.t = round((k + 1) * dt, 12)
            log.record(
                st.t, st, measured, measured + self.scene.safety_distance, bound, x1, cmds, T, X, self._scene_now
            )
            log.step(status, res, plan_time, iter_time, replanned, reason)
            if progress is not None:
                progress(k, st.t, str(status))
            if device is not None and status is StepStatus.UNSAFE:
                msg = f"unsafe step at t={t:.2f} s: nothing verified safe, device e-stopped"
                return self._finish(log, st, False, "estop", msg, t_wall, device)
            err = float(np.linalg.norm(self.model.tip_position(st.x) - self.goal))
            if err <= self.goal_tolerance:
                settled_since = st.t if settled_since is None else settled_since
                if st.t - settled_since >= o.settle_time - 1e-9:
                    reached = True
                    break
            else:
                settled_since = None
            if device is not None:
                log.late += device.pace(st.t)
            elif realtime:
                lag = clock() - t_clock - st.t
                if lag < 0.0:
                    sleep(-lag)
                elif lag > dt:
                    log.late += 1
        outcome = "reached" if reached else "timeout"
        msg = "goal reached and held" if reached else f"goal not reached within {o.duration:g} s"
        return self._finish(log, st, reached, outcome, msg, t_wall, device)

    def _hold(self, st: _State) -> tuple[Any, ...]:
        """The motion of holding still for one step: actuators commanded to their measured positions."""
        t, dt = st.t, self.options.dt
        return (
            st.q.copy(),
            st.q.copy(),
            np.array([t, t + dt]),
            np.stack([st.x, st.x]),
            np.repeat(st.q[None], self.n_sub, axis=0),
        )

    def _update_reference(self, st: _State, k: int) -> tuple[str, float, bool, float]:
        """Replan the reference path when needed; returns (reason, planner time s, replanned, time to charge s)."""
        o, t = self.options, st.t
        ref = st.ref
        reason = ""
        if ref is None:
            reason = "no reference"
        elif st.nlp_failed:
            reason = "NLP failed"
        elif o.replan_period > 0 and t - st.t_last_plan >= o.replan_period - 1e-9:
            reason = "periodic"
        elif t - st.progress_t >= o.stall_time and st.s_ref < ref.end - 1e-9:
            reason = "stalled"
        elif o.safety and not self._reference_valid(ref, st.s_ref, t):
            reason = "reference blocked"
        # after a failed attempt wait a little before asking the planner again
        if not reason or (reason != "periodic" and t - st.t_last_attempt < max(1.0, o.dt) - 1e-9):
            if st.ref is not None:
                st.locate(o.dt * self.replanner.N)
            return "", 0.0, False, 0.0
        st.t_last_attempt = t
        reused = k == 0 and self.initial_reference is not None
        plan = self.initial_reference if reused else self.reference_source(st.x, t, self._scene_now)
        replanned = plan.ok
        if plan.ok:
            st.ref = _Reference(plan.configs, self._seconds_per, self.validator.metric)
            st.s_ref, st.progress_s, st.progress_t, st.t_last_plan = 0.0, 0.0, t, t
            st.refs_used.append((k, self.model.tip_position(st.ref.X)))
            if len(plan.tree_edges):
                st.tree_edges = plan.tree_edges
        if st.ref is not None:
            st.locate(o.dt * self.replanner.N)
        # a reference planned before the loop started is charged to this iteration
        return f"{reason}: {plan.status}", plan.wall_time, replanned, plan.wall_time if reused else 0.0

    def _choose(self, st: _State, res: HorizonResult) -> tuple[StepStatus, np.ndarray, tuple[Any, ...], float]:
        """The move to apply: the NLP's, else the previous solution's next one, else holding still.

        Returns (status, planned configuration for the step's end, simulated
        motion (q end, set-point end, sample times, sample configurations,
        set-points per period), conservative clearance bound (mm; NaN without safety)).
        """
        o, t, dt = self.options, st.t, self.options.dt
        cands: list[tuple[StepStatus, np.ndarray]] = []
        if res.feasible:
            cands.append((StepStatus.MOVE if res.success else StepStatus.SUBOPTIMAL, res.configs[0]))
        if st.last_plan is not None and len(st.last_plan) > 1:
            cands.append((StepStatus.FALLBACK, st.last_plan[1]))
        tried: list[tuple[float, StepStatus, np.ndarray, tuple[Any, ...]]] = []
        chosen: tuple[StepStatus, np.ndarray, tuple[Any, ...], float] | None = None
        for status, x1 in cands:
            sim = self._track(st.q, st.qc, st.x, x1, t)
            if not o.safety:
                chosen = (status, x1, sim, math.nan)
                break
            bound = self._verify(sim[2], sim[3], (t + dt, t + 2 * dt))
            tried.append((bound, status, x1, sim))
            if bound >= 0.0:
                chosen = (status, x1, sim, bound)
                break
        if chosen is None:
            # hold: command every actuator to its measured position; first-order servos then stay put
            hold = self._hold(st)
            bound_h = float(self.validator.clearance(st.x[None], t, t + dt)[0])
            best = max(tried, key=lambda c: c[0]) if tried else None
            if bound_h >= 0.0 or best is None or best[0] <= bound_h:
                chosen = (StepStatus.HOLD if bound_h >= 0.0 else StepStatus.UNSAFE, st.x.copy(), hold, bound_h)
            else:
                chosen = (StepStatus.UNSAFE, best[2], best[3], best[0])
        status = chosen[0]
        if status in (StepStatus.MOVE, StepStatus.SUBOPTIMAL):
            st.last_plan = res.configs
        elif status is StepStatus.FALLBACK and st.last_plan is not None:
            st.last_plan = st.last_plan[1:]
        else:
            st.last_plan = None
        if status is not StepStatus.MOVE and status is not StepStatus.SUBOPTIMAL:
            # the warm start no longer matches where the robot is going
            self.replanner.reset()
        return chosen

    def _solve(self, x: np.ndarray, X_ref: np.ndarray, obstacles: np.ndarray, x_prev: np.ndarray) -> HorizonResult:
        return self.replanner.solve(x, X_ref, obstacles, x_prev=x_prev)

    def _finish(
        self,
        log: _Log,
        st: _State,
        reached: bool,
        outcome: str,
        message: str,
        t_wall: float,
        device: DeviceLink | None = None,
    ) -> ReplanRun:
        model = self.model
        if device is not None:
            device.finish(st.q)
        t = np.array(log.t)
        X = np.array(log.x)
        planned = np.array(log.planned)
        tips = model.tip_position(X)
        nq = self.robot.nq
        return ReplanRun(
            t=t,
            x=X,
            q=np.array(log.q),
            q_command=np.array(log.qc),
            tip=tips,
            backbone=model.points(X, REPORT_POINTS),
            centers=np.array(log.centers),
            radii=np.array(log.radii),
            clearance=np.array(log.clear),
            distance=np.array(log.dist),
            clearance_bound=np.array(log.bound),
            planned=planned,
            tip_error=np.linalg.norm(tips - model.tip_position(planned), axis=1),
            goal_error=np.linalg.norm(tips - self.goal, axis=1),
            status=tuple(log.status),
            solver_status=tuple(log.solver),
            nlp_time=np.array(log.nlp, dtype=float),
            plan_time=np.array(log.plan, dtype=float),
            iter_time=np.array(log.iter, dtype=float),
            iterations=np.array(log.its, dtype=int),
            replanned=np.array(log.replanned, dtype=bool),
            reason=tuple(log.reason),
            dense_t=np.concatenate(log.dense_t),
            dense_x=np.concatenate(log.dense_x),
            commands=np.concatenate(log.commands) if log.commands else np.zeros((0, nq)),
            control_dt=self.options.dt / self.n_sub,
            reference_tips=tuple(st.refs_used),
            tree_edges=st.tree_edges,
            goal=self.goal,
            reached=reached,
            outcome=outcome,
            message=message,
            safety=self.options.safety,
            setup_time=self.setup_time,
            wall_time=time.perf_counter() - t_wall,
            nlp=self.replanner.describe(),
            late_steps=log.late,
            live=bool(getattr(self.obstacles, "live", False)),
            device={} if device is None else device.describe(),
            feed=log.feed_record(self.obstacles),
        )


def _skipped(rp: Replanner, status: str) -> HorizonResult:
    """The record of a step whose NLP was not solved (status says why)."""
    nan = np.full((rp.N, rp.nx), np.nan)
    return HorizonResult(nan, np.full((rp.N, 3), np.nan), False, status, 0, 0.0, math.inf, math.nan, math.inf)


class _State:
    """Mutable state of one run: actual and commanded actuators, reference path and progress."""

    def __init__(self, q: np.ndarray, qc: np.ndarray, x: np.ndarray) -> None:
        self.t = 0.0
        self.q, self.qc, self.x = q, qc, x
        self.x_prev = x
        self.ref: _Reference | None = None
        self.s_ref = 0.0  # progress along the reference (s of reference time)
        self.progress_s, self.progress_t = 0.0, 0.0  # last time the progress grew
        self.t_last_plan = -math.inf
        self.t_last_attempt = -math.inf
        self.last_plan: np.ndarray | None = None  # remaining steps of the last applied NLP solution
        self.nlp_failed = False
        self.refs_used: list[tuple[int, np.ndarray]] = []
        self.tree_edges = np.zeros((0, 2, 3))

    def locate(self, ahead: float) -> None:
        """Move the progress to the reference point nearest to the robot."""
        ref = self.ref
        if ref is None:
            return
        self.s_ref = ref.locate(self.x, self.s_ref, back=1.0, ahead=ahead)
        if self.s_ref > self.progress_s + 1e-3 or self.s_ref >= ref.end - 1e-9:
            self.progress_s, self.progress_t = self.s_ref, self.t

    def horizon_reference(self, N: int, dt: float) -> np.ndarray:
        """Reference configurations (N, nx) for the horizon's steps; hold still without a reference."""
        if self.ref is None:
            return np.broadcast_to(self.x, (N, len(self.x))).copy()
        return self.ref.at(self.s_ref + dt * np.arange(1, N + 1))


class _Log:
    """Per-time and per-step records of one run."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.x: list[np.ndarray] = []
        self.q: list[np.ndarray] = []
        self.qc: list[np.ndarray] = []
        self.clear: list[float] = []
        self.dist: list[float] = []
        self.bound: list[float] = []
        self.planned: list[np.ndarray] = []
        self.status: list[str] = []
        self.solver: list[str] = []
        self.nlp: list[float] = []
        self.plan: list[float] = []
        self.iter: list[float] = []
        self.its: list[int] = []
        self.replanned: list[bool] = []
        self.reason: list[str] = []
        self.dense_t: list[np.ndarray] = []
        self.dense_x: list[np.ndarray] = []
        self.commands: list[np.ndarray] = []
        self.centers: list[np.ndarray] = []
        self.radii: list[np.ndarray] = []
        self.late = 0  # real-time steps that finished more than one step late
        self.feed: list[dict[str, Any]] = []  # the live feed's rejected/clamped messages, with loop time

    def feed_events(self, source: Any, t: float) -> None:
        """Record the live feed's new events (rejected or clamped messages) at loop time t (s)."""
        new = getattr(source, "new_events", None)
        if new is not None:
            self.feed.extend({"t": float(t), **e.to_dict()} for e in new())

    def feed_record(self, source: Any) -> dict[str, Any]:
        """The feed section of a live run: counters, options and every recorded event ({} without a feed)."""
        describe = getattr(source, "describe", None)
        if describe is None:
            return {}
        self.feed_events(source, self.t[-1] if self.t else 0.0)
        return {**describe(), "events": list(self.feed)}

    def record(
        self,
        t: float,
        st: _State,
        clear: float,
        dist: float,
        bound: float,
        planned: np.ndarray,
        commands: np.ndarray,
        T: np.ndarray,
        X: np.ndarray,
        scene: Any,
    ) -> None:
        """The state at time t, the motion samples (T, X) that led to it (first sample = previous time)
        and the obstacles (as `scene` knows them) at t."""
        self.t.append(t)
        self.x.append(st.x)
        self.q.append(st.q)
        self.qc.append(st.qc)
        self.clear.append(clear)
        self.dist.append(dist)
        self.bound.append(bound)
        self.planned.append(np.asarray(planned, dtype=float))
        if len(commands):
            self.commands.append(commands)
        c, r = scene.states(t)
        self.centers.append(c.reshape(-1, 3))
        self.radii.append(r.reshape(-1))
        skip = 1 if self.dense_t else 0
        self.dense_t.append(T[skip:])
        self.dense_x.append(X[skip:])

    def step(
        self, status: StepStatus, res: HorizonResult, plan_time: float, iter_time: float, replanned: bool, reason: str
    ) -> None:
        self.status.append(str(status))
        self.solver.append(res.status)
        self.nlp.append(res.wall_time)
        self.plan.append(plan_time)
        self.iter.append(iter_time)
        self.its.append(res.iterations)
        self.replanned.append(replanned)
        self.reason.append(reason)


# ------------------------------------------------------------------ problems
def loop_from_problem(
    problem: Any,
    *,
    safety: bool | None = None,
    seed: int | None = None,
    options: ReplanOptions | None = None,
    feed: Any = None,
    lead: float = 0.0,
) -> ClosedLoop:
    """A `ClosedLoop` for a problem file: its robot, scene, task and ``[replan]``, ``[tracking]``,
    ``[planner]``, ``[steer]`` sections. The start configuration is the task's ``start_config`` or the
    planner's safe IK for the start tip; references come from the planner ``[planner] algorithm`` names
    (`crtraj.planning.registry.make_planner`; default the configuration-space planner), each limited to
    ``replan.planner_time`` seconds.

    safety=False drops the collision-free terms (NLP constraints, verification, and obstacles in
    the reference planner), as in the paper's Fig. 4(b). seed overrides the problem's seed.
    feed: a `crtraj.world.feed.ObstacleFeed`: obstacle states come from it, live (`FeedObstacles`; the
    scene's obstacle names are the feed ids; the ``[feed]`` section, `crtraj.world.feed.FeedOptions`,
    configures it), and the run is paced in real time. lead: s the device
    executes each step after it is computed (`DeviceLink.lead`), so the feed is predicted that far ahead.
    """
    from crtraj.planning.options import PlannerOptions
    from crtraj.planning.registry import make_planner
    from crtraj.planning.result import PlanStatus
    from crtraj.planning.steer import SteerOptions
    from crtraj.planning.stop import StopCondition
    from crtraj.world.scene import Scene

    task = problem.require_task()
    seed = problem.seed if seed is None else int(seed)
    if seed < 0:
        raise InputError(f"--seed: must be >= 0, got {seed}")
    opts = problem.options(ReplanOptions, "replan") if options is None else options
    if safety is not None:
        opts = replace(opts, safety=bool(safety))
    tracking = problem.options(TrackingOptions, "tracking")
    popts = problem.options(PlannerOptions, "planner")
    scene = Scene.from_table(problem.section("scene"))
    feed_options = problem.options(FeedOptions, "feed")
    model = Model(problem.robot)
    planner = make_planner(model, scene, popts, problem.options(SteerOptions, "steer"))
    source: Any = None
    scene0 = scene
    extra: dict[str, Any] = {"planner": popts, "steer": problem.options(SteerOptions, "steer")}
    if feed is not None:
        feed.configure(feed_options)  # the problem's velocity bound and timestamp window
        extra["feed"] = feed_options
        source = FeedObstacles(feed, scene, window=max(2.0 * opts.horizon * opts.dt, 2.0) + 2.0 * opts.dt, lead=lead)
        t_end = time.perf_counter() + 2.0
        snap, why = source.at(0.0)
        while snap is None and time.perf_counter() < t_end:
            time.sleep(0.01)
            snap, why = source.at(0.0)
        if snap is None:
            raise InputError(f"--feed: {why}")
        # the run starts a moment after this snapshot (the first reference plan): find the start
        # configuration among everything the obstacles may cover over the next half second
        a, b, rmax = snap.swept(0.0, 0.5)
        scene0 = snap.with_obstacles(
            replace(
                o,
                center=tuple(0.5 * (a[i] + b[i])),
                radius=float(rmax[i] + 0.5 * np.linalg.norm(b[i] - a[i])),
                amplitude=0.0,
                omega=0.0,
                phase=0.0,
                to=None,
            )
            for i, o in enumerate(snap.obstacles)
        )
    first: ReferencePlan | None = None
    res = None
    if task.start_config is not None:
        x0 = np.asarray(task.start_config, dtype=float)
    else:
        # the start configuration: the planner's safe IK for the start tip (among the real obstacles)
        res = planner.plan(
            task.goal, start_tip=task.start, t0=0.0, seed=seed, goal_tolerance=task.goal_tolerance, scene=scene0
        )
        if res.status is PlanStatus.INVALID_START:
            raise UnsolvableTaskError("invalid_start", f"task.start: {res.message}")
        if res.has_path:
            x0 = res.configs[0]
            if res.is_success() and opts.safety:
                first = ReferencePlan(
                    res.configs, str(res.status), res.message, res.timings.get("total", 0.0), res.tree_edges
                )
        else:
            only = planner.plan(task.start, start_tip=task.start, t0=0.0, seed=seed, goal_tolerance=1.0, scene=scene0)
            if not only.has_path:
                raise UnsolvableTaskError("invalid_start", f"task.start: {only.message}")
            x0 = only.configs[0]
    moving = feed is not None or any(o.amplitude != 0.0 or o.to is not None for o in scene.obstacles)
    _check_goal(planner, task, x0, scene0, seed, res, among_obstacles=opts.safety and not moving)
    reference = PlannerReference(
        planner,
        task.goal,
        goal_tolerance=task.goal_tolerance,
        stop=popts.stop() | StopCondition(time_limit=opts.planner_time),
        seed=seed,
        scene=None if opts.safety else scene.with_obstacles(()),
    )
    return ClosedLoop(
        model,
        scene,
        task.goal,
        x0,
        options=opts,
        tracking=tracking,
        reference=reference,
        goal_tolerance=task.goal_tolerance,
        initial_reference=None if feed is not None else first,
        obstacles=source,
        extra_options=extra,
    )


def _check_goal(
    planner: Any, task: Any, x0: np.ndarray, scene: Any, seed: int, res: Any, *, among_obstacles: bool
) -> None:
    """Fail fast, as `crtraj plan` does, when no configuration can ever put the tip on the goal safely
    (`UnsolvableTaskError` "invalid_goal"), instead of running the loop until its duration ends.

    among_obstacles (static obstacles, with the safety terms): the planner's goal IK among them
    decides. Obstacles that move or breathe, or come from a live feed, may uncover the goal later,
    so then only a goal the robot cannot reach even with no obstacles at all is refused. res: the
    planner's result from x0 among `scene`, when there is one.
    """
    from crtraj.planning.result import PlanStatus
    from crtraj.planning.stop import StopCondition

    if res is not None and res.status not in (PlanStatus.INVALID_GOAL, PlanStatus.INVALID_START):
        return  # the goal IK found a safe goal configuration: reachable
    if not among_obstacles:
        scene, res = scene.with_obstacles(()), None
    if res is None:  # the goal IK runs before any search; one search iteration bounds the cost
        res = planner.plan(
            task.goal,
            start_config=x0,
            t0=0.0,
            seed=seed,
            goal_tolerance=task.goal_tolerance,
            scene=scene,
            stop=StopCondition(max_iterations=1),
        )
    if res.status is PlanStatus.INVALID_GOAL:
        raise UnsolvableTaskError("invalid_goal", f"task.goal: {res.message}")
