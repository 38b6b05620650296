"""The closed loop's device port on real hardware: `DeviceLink` streams each verified step live.

Units: actuation q in mm, actuator values in rad / mm, times in s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from crtraj.control.ports import DeviceError, Landing
from crtraj.core.errors import InputError
from crtraj.hardware.follower import SetpointFollower
from crtraj.hardware.limits import LimitPeaks
from crtraj.hardware.stream import StreamError


class DeviceLink:
    """Drives a device live from the loop, through a started `crtraj.hardware.stream.Streamer`;
    implements `crtraj.control.ports.Device` (the loop's device port).

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

    Verified as sent: with a `verifier` (`crtraj.hardware.verify.FrameVerifier`)
    and `scene_now` (the scene snapshot the loop checked the step against), each
    step's frames, as they will leave (the follower's output), pass the same
    check as a whole motion (dense body check with D_sf, cables, limits from
    the last queued frame) before they are queued; a step that fails is not
    sent: the link holds and the loop gets a `DeviceError` naming the time and
    the reason (`refused_steps`, `refusal` record it).
    Units: actuation q in mm, actuator values in rad / mm, times in s.
    """

    # late-loop holds the link may resume from; any other hold (telemetry lost, device refusal) ends the run
    _RECOVERABLE = ("source stalled", "set-point refused")
    _STOP_WAIT = 5.0  # s: longest a held stream's stop within the limits may take before the link resumes

    def __init__(
        self,
        streamer: Any,
        servo: Any,
        dt: float,
        *,
        lead: float | None = None,
        verifier: Any = None,
        scene_now: Callable[[], Any] | None = None,
    ) -> None:
        self.streamer = streamer
        self.verifier = verifier
        self.scene_now = scene_now
        self.refused_steps = 0
        self.refusal = ""
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
        self.follower = SetpointFollower(self.fdt, 0.98 * self.actuators.vmax, 0.98 * self.actuators.amax)
        self._S: float | None = None  # the stream plays stamp tau at wall time S + tau
        self._first: float | None = None  # first stamp queued since the stream (re)started
        self._origin: float | None = None  # the loop computes step t at wall time origin + t
        self._hist_t = np.zeros(0)
        self._hist_q = np.zeros((0, self.actuators.n))
        self._requested = False
        self._moving = False  # motion queued since the stream (re)started
        self.measured_steps = 0
        self.max_deviation = np.zeros(self.actuators.n)  # largest |set-point - verified motion| (rad, mm)
        self.peaks = LimitPeaks(self.actuators, self.fdt)  # of the frames queued for the device
        self.restarts = 0
        self.holds = 0
        self.report: Any = None

    # --------------------------------------------------------------- state
    @property
    def moving(self) -> bool:
        """Motion has been queued since the stream (re)started."""
        return self._moving

    @property
    def history(self) -> np.ndarray:
        """The stamps (s) of the verified motion the link remembers (to compare telemetry with)."""
        return self._hist_t.copy()

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
        p = np.asarray(self.streamer.position, dtype=float)
        self.follower.reset(p)
        self._S, self._first, self._moving = None, t, False
        self.streamer.send_values(t, p)
        self._remember(np.array([t]), self.actuators.actuation(p)[None])

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
    def move(self, t: float, q0: np.ndarray, commands: np.ndarray, control_dt: float) -> None:
        """Queue the verified motion of the step starting at loop time t from actuation q0 (mm) under
        `commands` (one per control period of control_dt s). `DeviceError` (why) when it was not sent."""
        s = self.streamer
        if s.state == "held":
            try:  # a hold latched while moving brakes within the limits: resume from where the stop ends
                s.wait_stopped(self._STOP_WAIT)
                if t < s.sent_stamp - 1e-9:  # the stop's frames ran past t: stamps never go back
                    raise StreamError(f"device stream held: stopping (sent up to t={s.sent_stamp:.3f} s)")
                s.resume()
            except StreamError as exc:
                raise DeviceError(str(exc)) from exc
            self._requested = False
            self.restarts += 1
            self._restart(t)
        n = self.frames_per_step
        stamps = t + self.fdt * np.arange(1, n + 1)
        Q = self.verified(q0, commands, control_dt, self.fdt * np.arange(1, n + 1))
        target = self.actuators.command(Q)
        before = self.follower.state
        values = self.follower.follow(target)
        why = self._failure(stamps, values, before.position, before.velocity)
        if why is not None:
            self.follower.restore(before)
            self.refused_steps += 1
            self.refusal = self.refusal or why
            self.hold(f"step at t={t:.2f} s refused before sending: {why}")
            raise DeviceError(f"step at t={t:.2f} s refused before sending: {why}")
        self.max_deviation = np.maximum(self.max_deviation, np.max(np.abs(values - target), axis=0))
        try:
            s.send_path(stamps, values)
        except StreamError as exc:  # held or stopped meanwhile; `problem` says whether that is final
            raise DeviceError(str(exc)) from exc
        self.peaks.add(values, before.position, before.velocity)
        self._moving = True
        self._remember(stamps, Q)
        self._clock_after_queue(t, stamps[-1])

    def landing(self, t: float, periods: int, control_dt: float) -> Landing:
        """At rest at the stream's last sent set-point (`Device.landing`): the link holds the stream whenever a step
        is not sent, and a held stream brakes to rest there (the next measurement has the telemetry)."""
        p = self.streamer.position
        return Landing.at_rest(self.actuators.actuation(self.follower.state.position if p is None else p), periods)

    def _failure(self, stamps: np.ndarray, values: np.ndarray, p0: Any, v0: np.ndarray) -> str | None:
        """Why a step's frames may not leave (`FrameVerifier.failure` against the loop's scene), or None."""
        if self.verifier is None:
            return None
        v = self.verifier if self.scene_now is None else self.verifier.with_scene(self.scene_now())
        return v.failure(stamps, values, start=p0, start_velocity=v0)

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
            self.follower.reset(s.position)

    def estop(self, reason: str) -> None:
        self.streamer.estop(reason)

    def finish(self, q_final: np.ndarray, timeout: float = 10.0) -> Any:
        """Bring the set-points to rest at q_final (mm), let the device settle, close; the `StreamReport`.
        A held or stopped stream is only closed (the device stays where it is)."""
        s = self.streamer
        if s.state in ("waiting", "streaming") and self.follower.state.last_target is not None:
            goal = self.actuators.command(np.asarray(q_final, dtype=float))
            p0, v0 = self.follower.state.position, self.follower.state.velocity
            tail = []
            for _ in range(int(timeout / self.fdt)):
                tail.append(self.follower.follow(goal[None])[0])
                v = self.follower.state.velocity
                if np.all(np.abs(tail[-1] - goal) <= 1e-6) and np.all(np.abs(v) * self.fdt <= 1e-6):
                    tail.append(goal)  # the last micro-step, far inside every limit
                    break
            t = float(self._hist_t[-1]) if len(self._hist_t) else 0.0
            stamps = t + self.fdt * np.arange(1, len(tail) + 1)
            why = self._failure(stamps, np.array(tail), p0, v0) if tail else None
            if why is not None:  # the way to rest is unsafe: stop where the device is
                self.refused_steps += 1
                self.refusal = self.refusal or why
                self.hold(f"final approach to rest refused before sending: {why}")
                tail = []
            try:
                if not tail:
                    raise StreamError("nothing to send")
                s.send_path(stamps, np.array(tail))
                self.peaks.add(np.array(tail), p0, v0)
                s.finish()
                s.wait(len(tail) * self.fdt + self.lead + s.options.settle_timeout + 2.0)
            except StreamError:
                pass  # stopped meanwhile: the report says why
        elif s.state in ("held", "estop"):
            # a hold or e-stop while moving (Ctrl-C, a refusal) brakes within the limits on the stream's thread: let
            # it finish, or closing now would latch the last set-point (a stop as hard as the device can)
            s.wait_stopped(timeout)
        self.report = s.close()
        return self.report

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of the frames queued for the device and of every frame the
        stream sent it (its stops and holds too: `Streamer.limit_fractions`), as fractions of the limits (the
        limits gate's finite differences at the stream rate; NaN before any frame)."""
        queued, sent = self.peaks.as_dict(), self.streamer.limit_fractions()
        return {k: max(queued[k], sent[k]) if math.isfinite(sent[k]) else queued[k] for k in queued}

    def describe(self) -> dict[str, Any]:
        """What the link did, for the run record: the stream report and the follower's deviation."""
        rep = self.report.to_dict() if self.report is not None else {}
        return {
            "stream": rep,
            **self.limit_fractions(),
            "lead_s": self.lead,
            "max_setpoint_deviation": dict(zip(self.actuators.names, self.max_deviation.tolist(), strict=True)),
            "restarts": self.restarts,
            "holds": self.holds,
            "measured_steps": self.measured_steps,
            "refused_steps": self.refused_steps,
            "refusal": self.refusal,
        }
