"""The verified braking manoeuvre: a hold or e-stop while moving is a stop planned within the acceleration
limits and checked against the obstacles, sent as frames. Checked independently: accelerations by finite
differences of the frames, contact by this file's own numpy distances from backbone points to the spheres."""

from __future__ import annotations

import dataclasses
import itertools
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import PROBLEMS, paper_copy
from devlink import CoreLink

from crtraj.app.devices import admit_result
from crtraj.app.run_output import write_run_files
from crtraj.cli import main
from crtraj.control.braking import servo_stop, stop_frames
from crtraj.control.loop import ClosedLoop, ProblemRun, RobotNow, RunStatus, StepStatus, assemble, spec_from_problem
from crtraj.core.clock import VirtualClock
from crtraj.core.errors import AdmissionError
from crtraj.hardware.protocol import ESTOP, HOLD, MOVE, Frame
from crtraj.hardware.sim import DeviceCore
from crtraj.hardware.stream import Braking, Streamer, StreamOptions
from crtraj.hardware.transport import TransportError
from crtraj.io.problem import Problem

RATE = 100.0
DT = 1.0 / RATE
INTERRUPTS = 200  # random interrupt times per run (the test)


@pytest.fixture(scope="module")
def motion(tmp_path_factory):
    """The paper's simulation 1 (`crtraj plan problems/paper_static.toml --seed 1`), admitted at 100 Hz."""
    out = tmp_path_factory.mktemp("plan") / "plan.json"
    assert main(["plan", str(PROBLEMS / "paper_static.toml"), "--seed", "1", "--out", str(out)]) == 0
    return admit_result(Path(out), rate=RATE)


def _accelerations(frames: np.ndarray) -> np.ndarray:
    """Second finite differences of frames sent every DT (per s^2)."""
    return np.diff(np.diff(frames, axis=0), axis=0) / DT**2


def _body_clearance(model, scene, T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Independent: distance (mm) from the body (backbone points plus the body radius) to the nearest obstacle
    surface at each time T (S,) for configurations X (S, nx), brute force over every point-sphere pair."""
    P = model.points(X, 60)  # (S, 60, 3)
    C, R = scene.states(T)  # (S, m, 3), (S, m)
    gap = np.sqrt(((P[:, :, None, :] - C[:, None, :, :]) ** 2).sum(axis=-1)) - R[:, None, :]
    return gap.min(axis=(1, 2)) - model.robot.body_radius


def _min_clearance(motion, stamps: np.ndarray, values: np.ndarray, sub: int = 8) -> float:
    """Smallest distance (mm) from the body to an obstacle surface over the frame-to-frame motions of
    `values` (M, n) at `stamps`, each sampled `sub` times (vectorised over every sample)."""
    s = np.linspace(0.0, 1.0, sub + 1)[:-1]
    V = np.concatenate([a + s[:, None] * (b - a) for a, b in itertools.pairwise(values)] + [values[-1:]])
    T = np.concatenate([t0 + s * (t1 - t0) for t0, t1 in itertools.pairwise(stamps)] + [stamps[-1:]])
    X = motion.robot.config(motion.actuators.actuation(V))
    return float(_body_clearance(motion.verifier.model, motion.scene, T, X).min())


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
    """200 random interrupt times of the simulation-1 plan: each planned stop passes the streamer's check, its
    accelerations (finite differences from the two frames before it) are within the limits, and the body
    keeps D_sf from every obstacle during it (own dense check)."""
    rng = np.random.default_rng(1)
    stamps, values = motion.stamps, motion.values
    braking = Braking(motion.actuators, DT, motion.verifier)
    d_sf = motion.scene.safety_distance
    moving = 0
    for k in rng.integers(1, len(stamps) - 1, size=INTERRUPTS):
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
    assert moving >= 150


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
    # the report's limit figures are those of every frame on the wire, the stop included: finite differences of
    # the set-points as sent (from rest at the first), against the report's
    W = np.array([f.values for f in frames if f.kind in (MOVE, HOLD)])
    W = np.vstack([W[:1], W])
    V = np.diff(W, axis=0) / DT
    A = np.diff(np.vstack([np.zeros((1, W.shape[1])), V]), axis=0) / DT
    acts = motion.actuators
    assert rep.max_velocity_fraction == pytest.approx(float(np.max(np.abs(V) / acts.vmax)), rel=1e-9)
    assert rep.max_acceleration_fraction == pytest.approx(float(np.max(np.abs(A) / acts.amax)), rel=1e-9)
    assert 0.0 < rep.max_acceleration_fraction <= 1.0 + 1e-9


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


@pytest.fixture(scope="module")
def loop_runs(tmp_path_factory):
    """(loop, run, problem) of the closed loop, seed 1, on the paper's simulation 1 ("sim1", static obstacles) or 2
    ("sim2", moving, without its step deadline), each run once for every test of this file."""
    cache: dict[str, tuple] = {}

    def get(name: str) -> tuple:
        if name not in cache:
            path = PROBLEMS / "paper_static.toml" if name == "sim1" else paper_copy(tmp_path_factory.mktemp(name))
            problem = Problem.load(path)
            loop = ClosedLoop.from_problem(problem, seed=1)
            run = loop.run()
            assert run.status == RunStatus.REACHED
            cache[name] = (loop, run, problem)
        return cache[name]

    return get


@pytest.fixture(scope="module")
def sim2_motion(loop_runs, tmp_path_factory):
    """The simulation-2 run written as `crtraj replan` writes it and admitted at 100 Hz (slower when the executed
    motion is too fast for the actuators, as the CLI says)."""
    loop, run, problem = loop_runs("sim2")
    out = tmp_path_factory.mktemp("sim2run")
    write_run_files(run, loop, out, problem=problem, seed=1, html=False)
    try:
        return admit_result(out / "run.json", rate=RATE)
    except AdmissionError as exc:
        m = re.search(r"--time-scale (\d+\.\d+)", str(exc))
        assert m, exc
        return admit_result(out / "run.json", rate=RATE, time_scale=float(m.group(1)))


def test_stops_at_random_interrupt_times_of_a_sim2_run_are_verified_or_latched(sim2_motion):
    """200 random interrupt times of the paper's simulation 2 (moving obstacles): each stop either passes the
    streamer's check, and then keeps within the acceleration limits and clear of the moving obstacles at its
    own times (own dense check), or is refused by that check (the stream would latch, counted)."""
    motion = sim2_motion
    rng = np.random.default_rng(2)
    stamps, values = motion.stamps, motion.values
    braking = Braking(motion.actuators, DT, motion.verifier)
    verified = 0
    for k in rng.integers(1, len(stamps) - 1, size=INTERRUPTS):
        plan = braking.plan(values[k], (values[k] - values[k - 1]) / DT, float(stamps[k]))
        if not len(plan.values) or not plan.ok:
            continue
        verified += 1
        F = np.vstack([values[k - 1], values[k], plan.values])
        assert np.all(np.abs(_accelerations(F)) <= motion.actuators.amax * (1 + 1e-9))
        clearance = _min_clearance(motion, np.concatenate([[stamps[k]], plan.stamps]), F[1:])
        assert clearance > 0.0 and clearance >= motion.scene.safety_distance - 0.25, clearance
    assert verified >= 120


# ---------------------------------------------------------------------------------------- the closed loop's hold


@pytest.fixture(params=["sim1", "sim2"])
def loop_run(request, loop_runs):
    """(loop, run) of the closed loop on simulation 1 or 2."""
    loop, run, _ = loop_runs(request.param)
    return loop, run


def _servo_samples(servo, q0: np.ndarray, C: np.ndarray, h: float, sub: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Independent: the first-order servo (tau dq/dt = c - q) from q0 under set-points C, one per period of h
    s: (times (len(C) sub + 1,) from 0, actual actuation there), by its closed form."""
    tau = h * np.arange(1, sub + 1) / sub
    T, Q, q = [np.zeros(1)], [q0[None]], q0
    for j, c in enumerate(C):
        Q.append(c + np.exp(-tau[:, None] / servo.tau) * (q - c))
        T.append(j * h + tau)
        q = Q[-1][-1]
    return np.concatenate(T), np.vstack(Q)


def test_the_loops_hold_at_random_interrupt_times_is_a_verified_stop_within_the_limits(loop_run):
    """200 random interrupt times of a closed-loop run (any control period's end, moving or not): the loop's hold
    there is a stop whose set-points the servo model executes exactly as planned, whose samples keep the
    acceleration limits (second differences, from the two periods before), that ends at rest; when the loop's
    dense check verifies it (the whole stop and a step at rest after), an independent dense check of the servo's
    closed-form motion finds no contact and D_sf kept."""
    loop, run = loop_run
    motion, policy = loop.parts.motion, loop.parts.policy
    servo, limits, full = loop.servo, motion.brake_limits, loop.rate_limits
    h = run.control_dt
    E = run.executed  # actual actuation at every period's end
    rng = np.random.default_rng(3)
    moving = verified = 0
    for i in rng.integers(1, len(E) - 1, size=INTERRUPTS):
        q, q_last, t = E[i], E[i - 1], round(i * h, 12)
        Q, C = servo_stop(servo, q, q_last, h, limits)
        step, bound = policy.hold(RobotNow(t, q, q, servo.config(q), np.zeros(loop.robot.nx), q_last))
        if not len(Q):
            assert np.array_equal(step.commands, np.repeat(q[None], loop.n_sub, axis=0))  # at rest: held in place
            continue
        moving += 1
        assert np.allclose(motion.periods(q, C), Q, rtol=0, atol=1e-9)  # the plant executes the stop as planned
        n = min(loop.n_sub, len(Q))
        assert np.array_equal(step.commands[:n], C[:n]) and np.allclose(step.q, Q[n - 1], atol=1e-12)
        X = servo.config(np.vstack([q_last, q, Q]))
        acc = np.diff(X, 2, axis=0) @ full.jacobian.T / h**2
        assert np.all(np.abs(acc) <= limits.amax * (1 + 1e-9)) and np.all(limits.amax <= full.amax)
        assert len(Q) == 1 or np.allclose(Q[-1], Q[-2], atol=1e-12)  # at rest
        if bound < 0.0:
            continue  # refused by the loop's check: the policy would not apply it as a safe hold
        verified += 1
        Ts, Qs = _servo_samples(servo, q, np.vstack([C, Q[-1:]]), h)
        d = _body_clearance(loop.model, loop.scene, t + Ts, loop.robot.config(Qs))
        assert d.min() > 0.0 and d.min() >= loop.scene.safety_distance - 0.25, d.min()
    assert moving >= 150 and verified >= 0.9 * moving


class _Gap:
    """Obstacle states that are missing from t0 to t1 (s): the loop's steps there are STALE holds."""

    live = False

    def __init__(self, scene, t0: float, t1: float) -> None:
        self.scene, self.t0, self.t1 = scene, t0, t1

    def at(self, t: float):
        return (None, "test gap") if self.t0 <= t < self.t1 else (self.scene, "")

    def new_events(self):
        return []

    def describe(self):
        return {}


def test_a_hold_while_moving_stops_the_simulated_robot_within_the_limits(tmp_path):
    """Simulation 2 with the obstacle states missing for 0.6 s while the robot moves: the loop holds (STALE), and
    the simulated robot brakes within the acceleration limits to rest (the executed samples' second differences,
    over the whole run), then resumes and reaches the goal."""
    problem = Problem.load(paper_copy(tmp_path))
    spec = spec_from_problem(problem, ProblemRun(seed=1))
    parts, config = assemble(dataclasses.replace(spec, obstacles=_Gap(spec.scene, 1.0, 1.6)))
    loop = ClosedLoop(parts, config)
    run = loop.run()
    assert run.status == RunStatus.REACHED
    h, E, limits = run.control_dt, run.executed, loop.rate_limits
    stale = np.flatnonzero(np.asarray(run.step_status) == str(StepStatus.STALE))
    assert len(stale) >= 5
    k0 = round(1.0 / h)
    assert np.max(np.abs(E[k0] - E[k0 - 1])) > 1e-3  # moving when the gap began
    X = loop.servo.config(E)
    acc = np.diff(X, 2, axis=0) @ limits.jacobian.T / h**2
    assert np.all(np.abs(acc) <= limits.amax * (1 + 1e-6)), np.max(np.abs(acc) / limits.amax)  # an instant stop: ~30x
    end = round(1.6 / h)
    assert np.max(np.abs(E[end] - E[end - 1])) <= 1e-9  # at rest before the gap ended


def test_an_inconsistent_state_is_not_planned_as_a_stop(loop_runs):
    """q and q_last far more than one period's motion apart (a position jump, not a velocity): no stop of millions
    of periods is planned; the hold commands the measured position."""
    loop, run, _ = loop_runs("sim1")
    q = run.executed[10]
    Q, C = servo_stop(loop.servo, q, q - 1e4, run.control_dt, loop.parts.motion.brake_limits)
    assert Q.shape == C.shape == (0, q.size)
