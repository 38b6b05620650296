"""The device port on hardware (crtraj.hardware.link.DeviceLink): set-point generation and its errors."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest

from crtraj.control.ports import Device, DeviceError
from crtraj.control.tracking import ServoModel
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.link import DeviceLink
from crtraj.hardware.stream import StreamError, StreamOptions

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])


class _FakeStreamer:
    """The attributes of a started `Streamer` that `DeviceLink`'s set-point generation reads."""

    def __init__(self, actuators, position) -> None:
        self.actuators = actuators
        self.options = StreamOptions(prebuffer=0.1)
        self.position = position

    def limit_fractions(self) -> dict:
        return {"max_velocity_fraction": math.nan, "max_acceleration_fraction": math.nan}  # sent: nothing yet


def test_follower_respects_limits_and_reproduces_the_verified_motion(robot):
    acts = Actuators.from_robot(robot)
    servo = ServoModel(robot, 0.05, 0.1)
    q0 = robot.cables(XS)
    link = DeviceLink(_FakeStreamer(acts, acts.command(q0)), servo, 0.1)
    link.follower.reset(acts.command(q0))
    # the verified motion inside one step equals the servo's closed form, period by period
    cmds = q0 + np.outer(np.arange(1, 6), np.append(np.full(6, 0.1), 1.5))
    off = np.linspace(0.001, 0.1, 37)
    Q = link.verified(q0, cmds, 0.02, off)
    q = q0.copy()
    for j in range(5):
        inside = (off > j * 0.02 + 1e-12) & (off <= (j + 1) * 0.02 + 1e-12)
        np.testing.assert_allclose(Q[inside], servo.trajectory(q, cmds[j], off[inside] - j * 0.02), atol=1e-12)
        q = servo.advance(q, cmds[j], 0.02)
    # a target with a velocity jump far beyond the limits: the set-points stay within them ...
    rng = np.random.default_rng(3)
    target = acts.command(q0) + np.cumsum(rng.normal(0.0, 0.05, (300, acts.n)), axis=0) * acts.vmax * 0.01
    P = np.vstack([acts.command(q0)[None], link.follower.follow(target)])
    V = np.diff(P, axis=0) / 0.01
    A = np.diff(np.vstack([np.zeros(acts.n), V]), axis=0) / 0.01
    assert np.all(np.abs(V) <= acts.vmax) and np.all(np.abs(A) <= acts.amax)
    # ... and reach a target that stops, at rest, without overshooting it by more than round-off
    goal = target[-1]
    tail = link.follower.follow(np.repeat(goal[None], 400, axis=0))
    np.testing.assert_allclose(tail[-1], goal, atol=1e-6)
    np.testing.assert_allclose(link.follower.state.velocity, 0.0, atol=1e-4)
    # a smooth, feasible target is followed exactly
    smooth = goal + np.outer(np.sin(np.linspace(0, 1, 100)), 0.001 * acts.vmax)
    link.follower.reset(smooth[0])
    np.testing.assert_allclose(link.follower.follow(smooth[1:]), smooth[1:], atol=1e-3 * acts.vmax.max())


def test_stream_rate_must_divide_the_step(robot):
    acts = Actuators.from_robot(robot)
    fake = _FakeStreamer(acts, acts.command(robot.cables(XS)))
    fake.options = StreamOptions(rate=35.0, prebuffer=0.1)  # 3.5 frames per 0.1 s step
    with pytest.raises(InputError, match=r"stream\.rate"):
        DeviceLink(fake, ServoModel(robot, 0.05, 0.1), 0.1)


class _RefusingStreamer(_FakeStreamer):
    """A started stream that was held meanwhile: it refuses every set-point."""

    state = "streaming"
    reason = ""

    def send_values(self, t, values) -> None:
        pass

    def send_path(self, stamps, values) -> None:
        raise StreamError("stream held: source stalled")


def test_a_refused_move_is_a_device_error_and_nothing_is_remembered(robot):
    acts = Actuators.from_robot(robot)
    q0 = robot.cables(XS)
    link = DeviceLink(_RefusingStreamer(acts, acts.command(q0)), ServoModel(robot, 0.05, 0.1), 0.1)
    assert isinstance(link, Device)  # the loop's device port
    link.begin(0.0)
    history = len(link.history)
    cmds = np.repeat((q0 + 0.05)[None], 5, axis=0)
    with pytest.raises(DeviceError, match="stream held: source stalled") as info:
        link.move(0.0, q0, cmds, 0.02)
    assert isinstance(info.value.__cause__, StreamError)  # wrapped, not swallowed
    assert len(link.history) == history and not link.moving  # a move not sent is not taken as sent
    # the loop plans on from where the held stream rests: its last sent set-point, not the unsent step's end
    land = link.landing(0.0, 5, 0.02)
    np.testing.assert_allclose(land.executed, np.repeat(q0[None], 5, axis=0), atol=1e-9)
    np.testing.assert_allclose(land.commands, land.executed, atol=0.0)


class _RecordingStreamer(_FakeStreamer):
    """A started stream that takes every set-point and records it."""

    state = "streaming"
    reason = ""

    def __init__(self, actuators, position) -> None:
        super().__init__(actuators, position)
        self.frames: list[np.ndarray] = []

    def send_values(self, t, values) -> None:
        pass

    def send_path(self, stamps, values) -> None:
        self.frames.extend(np.asarray(values, dtype=float))


def test_the_limit_figures_of_a_live_run_are_those_of_the_frames_sent(robot):
    acts = Actuators.from_robot(robot)
    q0 = robot.cables(XS)
    fake = _RecordingStreamer(acts, acts.command(q0))
    link = DeviceLink(fake, ServoModel(robot, 0.05, 0.1), 0.1)
    link.begin(0.0)
    assert all(np.isnan(v) for v in link.limit_fractions().values())  # nothing sent yet
    # steps whose commands jump (the follower limits them) and then stop: 3 s of set-points
    q = q0.copy()
    for k in range(30):
        target = q0 + (0.6 if k < 15 else 0.0) * np.append(np.full(6, 1.0), 8.0) * (k % 4 == 0)
        link.move(0.1 * k, q, np.repeat(target[None], 5, axis=0), 0.02)
        q = target
    # independently: finite differences at the stream rate of every frame, from rest at the start
    P = np.vstack([acts.command(q0)[None], np.array(fake.frames)])
    V = np.diff(P, axis=0) / 0.01
    A = np.diff(np.vstack([np.zeros(acts.n), V]), axis=0) / 0.01
    got = link.limit_fractions()
    assert got["max_velocity_fraction"] == pytest.approx(np.max(np.abs(V) / acts.vmax), rel=1e-12)
    assert got["max_acceleration_fraction"] == pytest.approx(np.max(np.abs(A) / acts.amax), rel=1e-12)
    # the follower's 98 % of the limits, and reached: the jumps asked for far more
    assert 0.9 < got["max_acceleration_fraction"] <= 0.98 * (1 + 1e-9)
    assert link.describe()["max_acceleration_fraction"] == got["max_acceleration_fraction"]


def test_a_hold_latched_while_moving_ends_its_stop_before_the_link_resumes(robot):
    """In process, on the stream's virtual clock: a real `Streamer` (frames through its limits gate) driven by a
    `DeviceLink`. The loop falls one step late while the device moves (the source stalls mid-motion, as under
    CPU load): the stream latches ``source stalled`` and brakes within the limits; a move during the stop is a
    `DeviceError` (resuming would reset the gate at rest mid-stop), and once at rest the link resumes from where
    the stop ended. No frame is refused and every frame that left is within the limits (recomputed)."""
    from test_stream import _Capture, _check_frames

    from crtraj.core.clock import VirtualClock
    from crtraj.hardware.protocol import MOVE
    from crtraj.hardware.stream import Streamer

    acts = Actuators.from_robot(robot)
    clock, cap = VirtualClock(), _Capture()
    s = Streamer(cap, acts, StreamOptions(prebuffer=0.1, watchdog=0.1), None, clock=clock)
    q0 = robot.cables(XS)
    start = acts.command(q0)
    s.start(start, background=False)
    link = DeviceLink(s, ServoModel(robot, 0.05, 0.1), 0.1)

    def ticks(n: int) -> None:
        for _ in range(n):
            s._step(clock.now(), False)
            clock.advance(0.01)

    def step(t: float, q: np.ndarray) -> np.ndarray:
        target = q + np.append(np.zeros(6), 0.6)  # z at ~6 mm/s: the device is moving when the loop is late
        link.move(t, q, np.repeat(target[None], 5, axis=0), 0.02)
        return target

    link.begin(0.0)
    q = step(0.0, q0)
    for k in range(1, 8):
        q = step(0.1 * k, q)
        ticks(10)
    ticks(12)  # queued up to t = 0.8 s; the loop is late: the buffer runs dry (inside the watchdog) while z moves
    braking = s.state == "held" and bool(np.any(s._gate.velocity != 0.0))
    with pytest.raises(DeviceError, match=r"stopping|still braking") if braking else contextlib.nullcontext():
        step(0.8, q)  # the late step arrives: it used to be queued, and its first frame refused
    ticks(60)
    assert [e for e in s._machine.events if e[1] == "refused"] == []
    assert s.buffer.sent_stamp > 0.8 + 0.005  # the stop's frames are stamped on past the late step's start
    with pytest.raises(DeviceError, match="stopping"):
        step(0.8, acts.actuation(s.position))  # a restart stamped before them would send stamps back in time
    assert braking and s.state == "held" and s.reason.startswith("source stalled"), s.reason
    here = acts.actuation(s.position)
    q = step(0.9, here)  # resumes at rest where the stop ended
    assert s.state == "waiting" and link.restarts == 1
    for k in range(10, 13):
        q = step(0.1 * k, q)
        ticks(10)
    rep = s.close()
    assert "refused" not in [e[1] for e in rep.events], rep.events
    assert rep.brakes == 1 and rep.brake_frames > 0
    _check_frames(cap.frames, acts, start, 0.01)
    # on the wire, stamps never go back: the stop's frames, the holds after it, the restart and the steps after it
    stamps = [f.stamp for f in cap.frames]
    assert np.all(np.diff(stamps) >= 0.0) and np.all(np.diff([f.stamp for f in cap.frames if f.kind == MOVE]) > 0.0)
