"""A cycle-level emulation of ros2_controllers' joint_trajectory_controller (JTC) per distro, written from its C++
source (joint_trajectory_controller.cpp and trajectory.cpp of the humble, jazzy and master branches, 2026-08) and
without crtraj's controller model. `JtcCore` is plain numpy; `jtc_emulator.JtcEmulator` puts it on an rclpy node.

What each distro does with a message (`receive` at the node clock, adopted at the first `cycle` after it):

- **humble**: the new trajectory replaces the current one. At its first sample the point before the trajectory is
  stored (``open_loop_control``: the last command; else the measured state) stamped with the cycle time, and the
  command written at cycle ``time`` is the trajectory sampled at ``time``.
- **jazzy**: as humble, but the trajectory's own clock ``traj_time`` starts at the first cycle and advances by
  ``period * scaling_factor``; the command written is the sample at ``traj_time + update_period`` (one period ahead),
  the point before is (``last_commanded_time``, ``last_commanded_state``) with ``interpolate_from_desired_state`` or
  ``open_loop_control``.
- **rolling** (master): as jazzy (``interpolate_from_desired_state`` only), and, with ``allow_trajectory_replacement``
  (default true) while a trajectory of more than one point runs and the controller is not holding, the message is
  blended into it (`_blend`): its start ``new_start`` is the previous cycle's ``traj_time`` (the cursor), moved on by
  ``stamp - time`` when the stamp is in the future; the old waypoints in (cursor, new_start) and the old curve
  sampled at new_start (the bridge anchor, when strictly before the first new point) come first, and everything is
  re-anchored at the cursor and stamped 0 (start now).

Sampling (`_Trajectory.sample`, trajectory.cpp): stamp 0 starts at the first sample; before the point before: no
sample; before the first point: the segment from the point before; then the segment [t_i, t_i+1) that contains the
time (searched from the last one, when monotonic); after the last point: the last point. Each segment is linear,
cubic or quintic by what both ends carry, its polynomial solved here from its boundary conditions.
Units: whatever the messages carry, times in s.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

DISTROS = ("humble", "jazzy", "rolling")
FLOAT_EPS = float(np.finfo(np.float32).eps)  # std::numeric_limits<float>::epsilon()


@dataclass(frozen=True)
class Pt:
    """One trajectory point: t (time_from_start, s) and per-joint arrays (None: the field is empty)."""

    t: float
    p: np.ndarray
    v: np.ndarray | None = None
    a: np.ndarray | None = None
    effort: int = 0


@dataclass(frozen=True)
class Msg:
    """A JointTrajectory: joint names, header stamp (s; 0 = start now) and points."""

    names: tuple[str, ...]
    stamp: float
    points: tuple[Pt, ...]


def defaults(distro: str) -> dict:
    """The controller parameters of `distro` that the emulation reads, with the defaults of its parameter file."""
    common = {
        "interpolation_method": "splines",
        "allow_partial_joints_goal": False,
        "cmd_timeout": 0.0,
        "constraints.goal_time": 0.0,
        "constraints.stopped_velocity_tolerance": 0.01,
    }
    if distro == "humble":
        return {**common, "open_loop_control": False, "allow_nonzero_velocity_at_trajectory_end": True}
    later = {
        **common,
        "interpolate_from_desired_state": False,
        "allow_nonzero_velocity_at_trajectory_end": False,
        "speed_scaling.initial_scaling_factor": 1.0,
        "speed_scaling.state_interface": "",
        "speed_scaling.command_interface": "",
    }
    if distro == "jazzy":
        return {**later, "open_loop_control": False}
    return {**later, "allow_trajectory_replacement": True, "positions_upsampling.enable": False}


def _polynomial(a: dict, b: dict, h: float, kind: int) -> np.ndarray:
    """Coefficients (kind+1, n), lowest power first, from position (and velocity, acceleration) conditions at both
    ends of a segment of duration h, by solving the linear system."""
    rows, rhs = [], []
    for tau, s in ((0.0, a), (h, b)):
        for order, key in enumerate(("p", "v", "a")[: (kind + 1) // 2]):
            row = [0.0] * (kind + 1)
            for k in range(order, kind + 1):
                coef = 1.0
                for j in range(order):
                    coef *= k - j
                row[k] = coef * tau ** (k - order)
            rows.append(row)
            rhs.append(s[key])
    return np.linalg.solve(np.array(rows), np.array(rhs))


def interpolate(ta: float, a: dict, tb: float, b: dict, t: float) -> dict:
    """trajectory.cpp's interpolate_between_points: outside [ta, tb] clamped and linear; inside linear, cubic
    (velocities at both ends) or quintic (velocities and accelerations at both ends)."""
    h, tau = tb - ta, t - ta
    has_v = a.get("v") is not None and b.get("v") is not None
    has_a = a.get("a") is not None and b.get("a") is not None
    if tau < 0.0 or tau > h:
        tau, has_v, has_a = min(max(tau, 0.0), h), False, False
    kind = 5 if has_v and has_a else 3 if has_v else 1
    if kind == 1:
        slope = (b["p"] - a["p"]) / h if h != 0.0 else np.zeros_like(a["p"])
        return {"p": a["p"] + tau * slope, "v": slope, "a": np.zeros_like(a["p"])}
    c = _polynomial(a, b, h, kind)
    k = np.arange(kind + 1)
    return {
        "p": (tau**k) @ c,
        "v": (k[1:] * tau ** (k[1:] - 1)) @ c[1:],
        "a": (k[2:] * (k[2:] - 1) * tau ** (k[2:] - 2)) @ c[2:],
    }


def _as_state(pt: Pt) -> dict:
    return {"p": pt.p, "v": pt.v, "a": pt.a}


@dataclass
class _Trajectory:
    """trajectory.cpp's Trajectory: a message, its start (0 until the first sample of a stamp-0 message) and the
    point before it."""

    points: list[Pt]
    start: float
    before_time: float = 0.0
    before: dict = field(default_factory=dict)
    sampled: bool = False
    last_idx: int = 0

    def set_before(self, time: float, state: dict) -> None:
        st = dict(state)
        first = self.points[0]
        if st.get("v") is None and first.v is not None:
            st["v"] = np.zeros_like(first.p)
        if st.get("a") is None and first.a is not None:
            st["a"] = np.zeros_like(first.p)
        self.before_time, self.before = time, st

    def sample(self, t: float, monotonic: bool = True) -> dict | None:
        """The state at t, or None (before the point before, or a last point without positions)."""
        if not self.sampled:
            if self.start == 0.0:
                self.start = t
            self.sampled = True
        if t < self.before_time:
            return None
        first = self.start + self.points[0].t
        if t < first:
            return interpolate(self.before_time, self.before, first, _as_state(self.points[0]), t)
        last = len(self.points) - 1
        for i in range(self.last_idx, last):
            t0, t1 = self.start + self.points[i].t, self.start + self.points[i + 1].t
            if t0 <= t < t1:
                if monotonic:
                    self.last_idx = i
                return interpolate(t0, _as_state(self.points[i]), t1, _as_state(self.points[i + 1]), t)
        self.last_idx = last
        end = self.points[-1]
        zero = np.zeros_like(end.p)
        return {"p": end.p, "v": zero if end.v is None else end.v, "a": zero if end.a is None else end.a}


class JtcCore:
    """One controller. joints: its joint names; start: their positions at activation; period: the update period
    (s; 1 / update_rate, the step of every `cycle`); params: parameter values over the distro's `defaults`; lag: s
    the measured state lags the command (perfect tracking, read `lag` late; at least one period, as ros2_control
    reads the state before it writes the command); velocity_state: the joints have a velocity state interface."""

    def __init__(self, joints, start, *, distro="humble", period=0.004, params=None, lag=None, velocity_state=True):
        if distro not in DISTROS:
            raise ValueError(f"distro: one of {DISTROS}, got {distro!r}")
        self.joints, self.distro, self.period = tuple(joints), distro, float(period)
        self.params = {**defaults(distro), **(params or {})}
        self.lag = self.period if lag is None else float(lag)
        self.velocity_state = velocity_state
        self.scaling = float(self.params.get("speed_scaling.initial_scaling_factor", 1.0))
        p0 = np.asarray(start, dtype=float)
        self._history: list[tuple[float, dict]] = []  # (cycle time, command written then)
        self._start = {"p": p0, "v": np.zeros_like(p0), "a": np.zeros_like(p0)}
        self.last_cmd, self.last_cmd_time = dict(self._start), 0.0
        self.command = p0.copy()
        self.traj: _Trajectory | None = None
        self.traj_time = 0.0
        self.holding = True
        self.pending: Msg | None = None
        self.commanded: list[tuple[float, np.ndarray]] = []  # (cycle time, position command)
        self.blends = 0
        self._adopt(Msg(self.joints, 0.0, (Pt(0.0, p0.copy()),)), 0.0)  # on_activate: hold position

    # ------------------------------------------------------------------ input
    def refusal(self, msg: Msg, now: float) -> str | None:
        """validate_trajectory_msg at node clock `now`: why the message is refused, or None."""
        names, n = msg.names, len(msg.names)
        if not self.params["allow_partial_joints_goal"] and n != len(self.joints):
            return "joints on incoming trajectory don't match the controller joints"
        if not names:
            return "empty joint names"
        if not msg.points:
            return "empty trajectory"
        if any(j not in self.joints for j in names):
            return "an incoming joint is not one of the controller's joints"
        last_v = msg.points[-1].v
        moving = last_v is not None and bool(np.any(np.abs(last_v) > FLOAT_EPS))
        if moving and not self.params["allow_nonzero_velocity_at_trajectory_end"]:
            return "velocity of the last trajectory point is not zero"
        if msg.stamp != 0.0 and msg.stamp + msg.points[-1].t < now:
            return "non-zero start time and ends in the past"
        for k, p in enumerate(msg.points):
            if k and not p.t > msg.points[k - 1].t:
                return f"time between points {k - 1} and {k} is not strictly increasing"
            if p.p.size != n or (p.v is not None and p.v.size != n) or (p.a is not None and p.a.size != n):
                return f"point {k}: wrong sizes"
            if p.effort:
                return f"point {k}: effort without an effort command interface"
        return None

    def receive(self, msg: Msg, now: float) -> str | None:
        """topic_callback: validate, then the message waits for the next cycle (a later one replaces it)."""
        why = self.refusal(msg, now)
        if why is None:
            self.pending = msg
            self.holding = False
        return why

    # ---------------------------------------------------------------- control
    def measured(self, time: float) -> dict:
        """The state interfaces at `time`: the command written `lag` s before (perfect tracking)."""
        old = [st for t, st in self._history if t <= time - self.lag + 1e-12]
        st = dict(old[-1] if old else self._start)
        st["a"] = None
        if not self.velocity_state:
            st["v"] = None
        return st

    def _open_loop(self) -> bool:
        if self.distro == "rolling":
            return bool(self.params["interpolate_from_desired_state"])
        if self.distro == "jazzy":
            return bool(self.params["interpolate_from_desired_state"] or self.params["open_loop_control"])
        return bool(self.params["open_loop_control"])

    def cycle(self, time: float) -> np.ndarray:
        """One update at `time` (s): adopt a pending message, sample, write the command; returns the position
        command."""
        if self.pending is not None:
            msg, self.pending = self.pending, None
            self._adopt(msg, time)
        traj = self.traj
        first = not traj.sampled
        if first:
            if self._open_loop():
                when = time if self.distro == "humble" or abs(self.last_cmd_time) < FLOAT_EPS else self.last_cmd_time
                traj.set_before(when, self.last_cmd)
            else:
                traj.set_before(time, self.measured(time))
            self.traj_time = time
        else:
            self.traj_time += self.period * self.scaling
        if self.distro == "humble":
            cmd = traj.sample(time)
        else:
            traj.sample(self.traj_time)  # the desired state (tolerances only)
            cmd = traj.sample(self.traj_time + self.period, monotonic=False)
        if cmd is not None:
            self.last_cmd, self.last_cmd_time = cmd, time
            self.command = np.asarray(cmd["p"], dtype=float).copy()
        self._history = [*self._history[-256:], (time, dict(self.last_cmd))]
        self.commanded.append((time, self.command.copy()))
        return self.command

    def _adopt(self, msg: Msg, time: float) -> None:
        """update(): blend (rolling) or replace."""
        blend = (
            self.distro == "rolling"
            and self.params["allow_trajectory_replacement"]
            and self.traj is not None
            and len(self.traj.points) > 1
            and not self.holding
        )
        ordered = self._sorted(msg)
        if blend:
            ordered = self._blend(ordered, time)
            self.blends += 1
        self.traj = _Trajectory(list(ordered.points), ordered.stamp)

    def _sorted(self, msg: Msg) -> Msg:
        order = [msg.names.index(j) for j in self.joints]
        pts = tuple(
            replace(p, p=p.p[order], v=None if p.v is None else p.v[order], a=None if p.a is None else p.a[order])
            for p in msg.points
        )
        return Msg(self.joints, msg.stamp, pts)

    def _blend(self, msg: Msg, time: float) -> Msg:
        """blend_with_active_trajectory for a message naming every joint (times relative to the old start, then
        re-anchored at the cursor, stamp 0)."""
        old = self.traj
        old_start, cursor = old.start, self.traj_time
        new_start = cursor + (msg.stamp - time) * self.scaling if msg.stamp > time else cursor
        anchor = old.sample(new_start, monotonic=False)
        new = [replace(p, t=new_start + p.t - old_start) for p in msg.points]
        prefix = [p for p in old.points if cursor < old_start + p.t < new_start]
        if anchor is not None and new_start - old_start < new[0].t:
            prefix.append(Pt(new_start - old_start, anchor["p"], anchor["v"], anchor["a"]))
        shift = cursor - old_start
        return Msg(self.joints, 0.0, tuple(replace(p, t=p.t - shift) for p in prefix + new))
