"""The verified braking manoeuvre: a hold or e-stop while moving is a stop planned within the acceleration
limits and checked against the obstacles, sent as frames. Checked independently: accelerations by finite
differences of the frames, contact by this file's own numpy distances from backbone points to the spheres."""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import PROBLEMS, paper_copy
from devlink import CoreLink

from crtraj.app.stream import admit_result
from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.core.errors import AdmissionError
from crtraj.hardware.braking import Braking, stop_frames
from crtraj.hardware.protocol import ESTOP, MOVE, Frame
from crtraj.hardware.sim_device import DeviceCore
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.hardware.transport import TransportError

RATE = 100.0
DT = 1.0 / RATE


@pytest.fixture(scope="module")
def motion(tmp_path_factory):
    """The paper's simulation 1 (`crtraj plan problems/paper_static.toml --seed 1`), admitted at 100 Hz."""
    out = tmp_path_factory.mktemp("plan") / "plan.json"
    assert main(["plan", str(PROBLEMS / "paper_static.toml"), "--seed", "1", "--out", str(out)]) == 0
    return admit_result(Path(out), rate=RATE)


def _accelerations(frames: np.ndarray) -> np.ndarray:
    """Second finite differences of frames sent every DT (per s^2)."""
    return np.diff(np.diff(frames, axis=0), axis=0) / DT**2


def _min_clearance(motion, stamps: np.ndarray, values: np.ndarray, sub: int = 8) -> float:
    """Smallest distance (mm) from the body (backbone points plus the body radius) to an obstacle surface,
    over the frame-to-frame motions of `values` (M, n) at `stamps`, each sampled `sub` times."""
    robot, acts, scene = motion.robot, motion.actuators, motion.scene
    s = np.linspace(0.0, 1.0, sub + 1)[:-1]
    V = np.concatenate([a + s[:, None] * (b - a) for a, b in itertools.pairwise(values)])
    V = np.vstack([V, values[-1:]])
    T = np.concatenate([t0 + s * (t1 - t0) for t0, t1 in itertools.pairwise(stamps)] + [stamps[-1:]])
    P = motion.verifier.model.points(robot.config(acts.actuation(V)), 60)  # (K, 60, 3)
    best = np.inf
    for k in range(len(T)):
        centers, radii = scene.states(T[k])
        d = np.linalg.norm(P[k][:, None, :] - centers[None, :, :], axis=2) - radii[None, :] - robot.body_radius
        best = min(best, float(d.min()))
    return best


def test_stop_frames_decelerate_within_the_limits_and_end_at_rest():
    """For random velocities: every acceleration is within its limit, the stop ends at rest, and it takes the
    fewest periods that allow that."""
    rng = np.random.default_rng(0)
    amax = np.array([50.0, 50.0, 30.0, 100.0])
    for _ in range(200):
        p, v = rng.normal(size=4), rng.normal(scale=5.0, size=4)
        F = np.vstack([p - DT * v, p, stop_frames(p, v, amax, DT)])  # the two frames before, then the stop
        assert np.all(np.abs(_accelerations(F)) <= amax * (1 + 1e-9))
        assert np.array_equal(F[-1], F[-2])  # at rest
        n = len(F) - 2
        assert np.max(np.abs(v) / amax) > (n - 1) * DT  # one period fewer would need more than amax
    assert stop_frames(np.ones(3), np.zeros(3), np.ones(3), DT).shape == (0, 3)


def test_stops_at_random_interrupt_times_of_sim1_stay_within_limits_and_clear_of_obstacles(motion):
    """40 random interrupt times of the simulation-1 plan: each planned stop passes the streamer's check, its
    accelerations (finite differences from the two frames before it) are within the limits, and the body
    keeps D_sf from every obstacle during it (own dense check)."""
    rng = np.random.default_rng(1)
    stamps, values = motion.stamps, motion.values
    braking = Braking(motion.actuators, DT, motion.verifier)
    d_sf = motion.scene.safety_distance
    moving = 0
    for k in rng.integers(1, len(stamps) - 1, size=40):
        v = (values[k] - values[k - 1]) / DT
        plan = braking.plan(values[k], v, float(stamps[k]))
        assert plan.ok, plan.why
        if not len(plan.values):
            continue
        moving += 1
        F = np.vstack([values[k - 1], values[k], plan.values])
        assert np.all(np.abs(_accelerations(F)) <= motion.actuators.amax * (1 + 1e-9))
        assert np.all(plan.values >= motion.actuators.lower) and np.all(plan.values <= motion.actuators.upper)
        assert np.allclose(np.diff(plan.stamps), DT) and plan.stamps[0] == pytest.approx(stamps[k] + DT)
        clearance = _min_clearance(motion, np.concatenate([[stamps[k]], plan.stamps]), F[1:])
        assert clearance > 0.0  # no contact
        assert clearance >= d_sf - 0.25, clearance  # and D_sf kept, up to this check's sampling
    assert moving >= 30


class _Clock(VirtualClock):
    """Virtual time whose sleeps run the callbacks due (an e-stop pressed at a time)."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[tuple[float, object]] = []

    def sleep(self, s: float) -> None:
        super().sleep(s)
        for ev in [e for e in self.events if e[0] <= self.now()]:
            self.events.remove(ev)
            ev[1]()


@pytest.mark.parametrize("at", [0.8, 3.3, 7.1])
def test_estop_while_moving_sends_the_verified_stop_then_the_estop(motion, at):
    """An e-stop at time `at` of the stream: the frames after it are the stop (moves within the acceleration
    limits, clear of the obstacles), then e-stop frames at rest; the report counts the stop, no latch."""
    clock = _Clock()
    core = DeviceCore(motion.actuators, initial=motion.values[0])
    link = CoreLink(core, clock)
    st = Streamer(link, motion.actuators, StreamOptions(rate=RATE), realtime=True, clock=clock)
    sent_before: list[int] = []

    def press() -> None:
        sent_before.append(len(link.sent))
        st.estop("test e-stop")

    clock.events.append((clock.now() + at, press))
    rep = st.run_path(motion)
    assert rep.status == "estop" and rep.brakes == 1 and rep.latched == 0
    frames = [Frame.decode(f) for f in link.sent]
    before = [f for f in frames[: sent_before[0]] if f.kind == MOVE][-2:]
    after = frames[sent_before[0] :]
    m = sum(1 for f in after if f.kind == MOVE)
    assert m == rep.brake_frames >= 2
    assert [f.kind for f in after] == [MOVE] * m + [ESTOP] * (len(after) - m) and len(after) > m
    F = np.array([f.values for f in before + after[:m]])
    assert np.all(np.abs(_accelerations(F)) <= motion.actuators.amax * (1 + 1e-9))
    assert np.array_equal(F[-1], F[-2]) and np.array_equal(after[-1].values, F[-1])
    stamps = np.array([f.stamp for f in before[1:] + after[:m]])
    assert _min_clearance(motion, stamps, F[1:]) >= motion.scene.safety_distance - 0.25


class _FailingLink(CoreLink):
    """A link that breaks (every send raises) after `fail_at` frames."""

    def __init__(self, core: DeviceCore, clock: VirtualClock, fail_at: int) -> None:
        super().__init__(core, clock)
        self.fail_at = fail_at

    def send(self, frame: bytes) -> None:
        if len(self.sent) >= self.fail_at:
            raise TransportError("link down")
        super().send(frame)


def test_a_link_that_fails_while_moving_counts_as_latched(motion):
    """No stop can be sent over a broken link: the device's own latch is the last resort, counted as such."""
    clock = VirtualClock()
    link = _FailingLink(DeviceCore(motion.actuators, initial=motion.values[0]), clock, fail_at=300)
    rep = Streamer(link, motion.actuators, StreamOptions(rate=RATE), realtime=True, clock=clock).run_path(motion)
    assert rep.status == "error" and "link down" in rep.message
    assert rep.latched == 1 and rep.brakes == 0


@pytest.mark.slow
def test_stops_at_random_interrupt_times_of_a_sim2_run_are_verified_or_latched(tmp_path):
    """The paper's simulation 2 (moving obstacles): each stop at a random interrupt time either passes the
    streamer's check, and then keeps within the acceleration limits and clear of the moving obstacles at its
    own times (own dense check), or is refused by that check (the stream would latch, counted)."""
    out = tmp_path / "replan"
    args = ["replan", str(paper_copy(tmp_path)), "--seed", "1", "--out", str(out), "--no-html", "--quiet"]
    assert main(args) == 0
    try:
        motion = admit_result(out / "run.json", rate=RATE)
    except AdmissionError as exc:  # too fast for the actuators as executed: stream it slower, as the CLI says
        m = re.search(r"--time-scale (\d+\.\d+)", str(exc))
        assert m, exc
        motion = admit_result(out / "run.json", rate=RATE, time_scale=float(m.group(1)))
    rng = np.random.default_rng(2)
    stamps, values = motion.stamps, motion.values
    braking = Braking(motion.actuators, DT, motion.verifier)
    verified = 0
    for k in rng.integers(1, len(stamps) - 1, size=25):
        plan = braking.plan(values[k], (values[k] - values[k - 1]) / DT, float(stamps[k]))
        if not len(plan.values) or not plan.ok:
            continue
        verified += 1
        F = np.vstack([values[k - 1], values[k], plan.values])
        assert np.all(np.abs(_accelerations(F)) <= motion.actuators.amax * (1 + 1e-9))
        clearance = _min_clearance(motion, np.concatenate([[stamps[k]], plan.stamps]), F[1:])
        assert clearance > 0.0 and clearance >= motion.scene.safety_distance - 0.25, clearance
    assert verified >= 15
