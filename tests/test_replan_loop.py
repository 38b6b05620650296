"""Closed-loop replanning (crtraj.control.loop.ClosedLoop) on small seeded scenes, re-checked independently.

The independent check replays the recorded actuator set-points through its
own first-order servo formula, samples the actual motion on a fine time grid,
evaluates the obstacles' time functions in closed form and measures the
distance from 150 backbone points; it shares nothing with the loop's own
verification except the forward kinematics.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from crtraj.app.run_output import write_run
from crtraj.control.horizon import HorizonResult, HorizonStatus, Replanner, ReplanOptions
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.control.loop._options import LoopOptions
from crtraj.control.loop._run_record import RunStatus, StepStatus
from crtraj.control.ports import Device, DeviceError, Landing
from crtraj.control.tracking import TrackingOptions
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=0.5, phase=-0.43, name="ball")
FAST = {"horizon": 6, "points": 12, "solver": "sqp"}


def _obstacle_state(o: Obstacle, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form centre (S, 3) and radius (S,) of a fixed or linearly moving obstacle."""
    c0 = np.array(o.center)
    if o.to is None:
        c = np.broadcast_to(c0, (len(t), 3))
    else:
        assert o.profile == "linear"
        c = c0 + np.clip(t / o.duration, 0.0, 1.0)[:, None] * (np.array(o.to) - c0)
    return c, o.radius + o.amplitude * np.sin(o.omega * t + o.phase)


def _replay(run, robot, tracking: TrackingOptions, sub: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Actual actuator positions on a fine grid from q[0] and the set-points.

    Returns (times (S,), q (S, nq), q at the end of every control period).
    """
    n = robot.n_segments
    tau = np.append(np.full(3 * n, tracking.servo_tau), tracking.servo_tau_z)
    h = run.control_dt
    q = run.q[0].copy()
    s = h * np.arange(sub) / sub
    T, Q, ends = [], [], []
    for j, qc in enumerate(run.commands):
        T.append(j * h + s)
        Q.append(qc + np.exp(-s[:, None] / tau) * (q - qc))
        q = qc + np.exp(-h / tau) * (q - qc)
        ends.append(q)
    T.append(np.array([len(run.commands) * h]))
    Q.append(q[None])
    return np.concatenate(T), np.concatenate(Q), np.array(ends)


def _independent_clearance(run, model, scene: Scene, tracking: TrackingOptions) -> np.ndarray:
    """Body clearance (mm, minus D_sf) at every fine sample of the replayed actual motion."""
    robot = model.robot
    T, Q, ends = _replay(run, robot, tracking)
    # the replay reproduces the recorded actual state at every step end
    n_sub = round((run.t[1] - run.t[0]) / run.control_dt) if len(run.t) > 1 else 1
    np.testing.assert_allclose(ends[n_sub - 1 :: n_sub], run.q[1:], atol=1e-9)
    X = robot.config(Q)
    P = model.points(X, 150)  # (S, 150, 3)
    out = np.full(len(T), np.inf)
    for o in scene.obstacles:
        c, r = _obstacle_state(o, T)
        d = np.linalg.norm(P - c[:, None, :], axis=-1).min(axis=1) - r
        out = np.minimum(out, d)
    return out - robot.body_radius - scene.safety_distance


def _loop(model, scene, goal_config=XG, **kw) -> ClosedLoop:
    """A loop with FAST horizon options; keyword options go to `LoopOptions` or `ReplanOptions` by name."""
    loop_keys = {f: v for f, v in kw.items() if f in LoopOptions.__dataclass_fields__}
    opts = ReplanOptions(**{**FAST, **{f: v for f, v in kw.items() if f not in loop_keys}})
    return ClosedLoop.build(
        model,
        scene,
        model.tip_position(goal_config),
        XS,
        options=opts,
        loop_options=LoopOptions(**loop_keys),
        goal_config=goal_config,
    )


@pytest.fixture(scope="module")
def ball_scene() -> Scene:
    return Scene(obstacles=(BALL,), safety_distance=5.0)


@pytest.fixture(scope="module")
def ball_run(model, ball_scene):
    loop = _loop(model, ball_scene, duration=20.0)
    return loop, loop.run()


def test_breathing_ball_run_is_safe_at_every_instant_and_reaches_the_goal(model, ball_scene, ball_run):
    loop, run = ball_run
    assert run.status is RunStatus.REACHED and run.reached and run.is_success(), run.summary_line()
    clear = _independent_clearance(run, model, ball_scene, loop.tracking_options)
    assert clear.min() > 0.0, clear.min()
    # the loop's own records agree: no collision, no D_sf breach
    assert run.collisions == 0 and run.safety_violations == 0
    assert run.summary()["min_clearance_mm"] > 0.0
    # final tip error within the goal tolerance (0.5 mm default)
    assert run.goal_error[-1] <= 0.5
    assert set(run.step_status) <= {str(s) for s in StepStatus}


def test_the_ball_really_is_in_the_way(model, ball_scene):
    """Control: the same run without the collision-free terms goes through the ball."""
    loop = _loop(model, ball_scene, duration=20.0, safety=False)
    run = loop.run()
    assert run.reached
    clear = _independent_clearance(run, model, ball_scene, loop.tracking_options)
    assert clear.min() < -5.0
    assert run.safety_violations > 0


def test_rate_limits_are_respected(model, ball_run):
    loop, run = ball_run
    tr = loop.tracking_options
    A, _ = model.robot.cable_matrix()
    h = run.control_dt
    # every set-point change per control period within the actuator rate limits
    cmds = np.vstack([run.q[:1], run.commands])
    dq = np.abs(np.diff(cmds, axis=0))
    n = model.robot.n_segments
    assert np.all(dq[:, : 3 * n] <= tr.max_cable_rate * h + 1e-9)
    assert np.all(dq[:, -1] <= tr.max_z_rate * h + 1e-9)
    # every planned move per step within the replanner's (tighter) limits
    o = loop.options
    limit = np.append(np.full(3 * n, o.max_cable_speed), o.max_z_speed) * o.dt
    moved = np.array([s in ("move", "suboptimal") for s in run.step_status])
    steps = np.abs((run.planned[1:] - run.x[:-1]) @ A.T)[moved]
    assert np.all(steps <= limit + 1e-6)
    # the actual actuators never leave the robot's limits
    assert np.all(model.robot.limit_violation(run.x) <= 1e-7)


def test_blocked_goal_makes_the_robot_wait_then_finish(model):
    pg = model.tip_position(XG)
    out = np.array([pg[0], pg[1], 0.0]) / np.hypot(pg[0], pg[1])
    blocker = Obstacle(center=tuple(pg), radius=20.0, to=tuple(pg + 120.0 * out), duration=60.0, name="blocker")
    scene = Scene(obstacles=(blocker,), safety_distance=5.0)
    # independent: the first time the goal configuration itself is clear
    ts = np.linspace(0.0, 60.0, 1201)
    c, r = _obstacle_state(blocker, ts)
    P = model.points(XG, 150)
    free = np.linalg.norm(P[None] - c[:, None], axis=-1).min(axis=1) - r - model.robot.body_radius - 5.0 > 0
    t_free = ts[np.argmax(free)]
    assert t_free > 10.0
    loop = _loop(model, scene, duration=40.0)
    run = loop.run()
    assert run.reached, run.summary_line()
    assert run.t[-1] > t_free  # it could not finish before the goal was free ...
    near = np.flatnonzero(run.goal_error < 30.0)
    assert run.t[near[0]] < t_free - 4.0  # ... but got close long before: it waited
    clear = _independent_clearance(run, model, scene, loop.tracking_options)
    assert clear.min() > 0.0


class _FailingReplanner(Replanner):
    """A Replanner whose solves of steps `fail` (0-based) return a failure, as a crashed solver would. The
    loop's first solve is its untimed warm-up before step 0 (counted as -1)."""

    def __init__(self, *args, fail: range, **kw) -> None:
        super().__init__(*args, **kw)
        self.fail = fail
        self.calls = -1

    def solve(self, x0, reference, obstacles, **kw) -> HorizonResult:
        i = self.calls
        self.calls += 1
        if i in self.fail:
            nan = np.full((self.N, self.nx), np.nan)
            tips = np.full((self.N, 3), np.nan)
            return HorizonResult(
                nan, tips, HorizonStatus.FAILED, "Injected_Failure", 0, 0.0, math.inf, math.nan, math.inf
            )
        return super().solve(x0, reference, obstacles, **kw)


def test_nlp_failure_falls_back_then_holds_safely_and_reports_it(model, ball_scene):
    opts = ReplanOptions(**FAST)
    fail = range(15, 40)
    rp = _FailingReplanner(model, opts, max_obstacles=1, safety_distance=5.0, fail=fail)
    loop = ClosedLoop.build(
        model,
        ball_scene,
        model.tip_position(XG),
        XS,
        options=opts,
        loop_options=LoopOptions(duration=25.0),
        goal_config=XG,
        replanner=rp,
    )
    run = loop.run()
    st = np.array(run.step_status)
    window = np.arange(fail.start, fail.stop)
    # the failure is reported verbatim and never passed off as a move
    assert all(run.solver_status[k] == "Injected_Failure" for k in window)
    assert set(st[window]) <= {"fallback", "hold"}
    # first the rest of the previous solution, then holding still
    assert st[window[0]] == "fallback"
    holds = window[st[window] == "hold"]
    assert len(holds) >= 10
    for k in holds:
        np.testing.assert_array_equal(run.x[k + 1], run.x[k])  # held exactly where it was
    assert all("NLP failed" in run.reason[k] for k in window if run.reason[k])
    # afterwards it recovers and finishes, safe throughout
    assert st[fail.stop] in ("move", "suboptimal")
    assert run.reached
    clear = _independent_clearance(run, model, ball_scene, loop.tracking_options)
    assert clear.min() > 0.0


def test_unavoidable_obstacle_is_reported_not_hidden(model):
    # a sphere 30 mm beside the straight body grows from 10 to 150 mm in 1.6 s: nothing can move away that fast
    grow = Obstacle(center=(30.0, 0.0, 150.0), radius=80.0, amplitude=70.0, omega=2.0, phase=-math.pi / 2)
    scene = Scene(obstacles=(grow,), safety_distance=5.0)
    loop = ClosedLoop.build(
        model,
        scene,
        model.tip_position(XG),
        np.zeros(5),
        options=ReplanOptions(**FAST),
        loop_options=LoopOptions(duration=2.0),
        goal_config=XG,
    )
    run = loop.run()
    assert "unsafe" in run.step_status
    assert not run.is_success()
    assert run.safety_violations > 0


def test_start_in_collision_is_refused_without_moving(model):
    scene = Scene(obstacles=(Obstacle(center=(0.0, 0.0, 200.0), radius=30.0),), safety_distance=5.0)
    loop = ClosedLoop.build(
        model, scene, model.tip_position(XG), np.zeros(5), options=ReplanOptions(**FAST), goal_config=XG
    )
    run = loop.run()
    assert run.status is RunStatus.INVALID_START and not run.is_success()
    assert run.steps == 0 and not run.reached


def test_result_files_round_trip(model, ball_run, tmp_path):
    loop, run = ball_run
    paths = write_run(run, loop, tmp_path, html=False)
    res = json.loads((tmp_path / "run.json").read_text())
    assert res["kind"] == "replan" and res["success"] is True
    assert len(res["waypoints"]) == len(run.t)
    w = res["waypoints"][5]
    np.testing.assert_allclose(w["tip"], model.tip_position(np.array(w["x"])), atol=1e-9)
    np.testing.assert_allclose(w["q"], model.cables(np.array(w["x"])), atol=1e-9)
    assert len(w["obstacles"]["radii"]) == 1
    with np.load(paths["npz"]) as z:  # no pickles needed
        np.testing.assert_array_equal(z["t"], run.t)
        assert list(z["status"]) == list(run.step_status)
    assert (tmp_path / "run.png").stat().st_size > 10_000


def _random_scene(model, rng: np.random.Generator) -> tuple[Scene, np.ndarray]:
    """Two breathing, drifting spheres near the straight motion from XS to a random goal configuration."""
    while True:
        xg = XG + rng.normal(0.0, [0.15, 0.15, 0.1, 0.1, 10.0])
        X = XS + np.linspace(0.2, 0.8, 4)[:, None] * (xg - XS)
        P = model.points(X, 9)[:, 2:]  # upper body along the motion
        obs = []
        for i in range(2):
            p = P[rng.integers(len(P)), rng.integers(P.shape[1])]
            c = p + rng.normal(0.0, 25.0, 3)
            r = rng.uniform(12.0, 25.0)
            to = c + rng.normal(0.0, 15.0, 3)
            obs.append(
                Obstacle(
                    center=tuple(c),
                    radius=r,
                    amplitude=rng.uniform(0.0, 0.4) * r,
                    omega=rng.uniform(0.3, 1.5),
                    phase=rng.uniform(0, 2 * np.pi),
                    to=tuple(to),
                    duration=rng.uniform(3.0, 8.0),
                    name=f"o{i}",
                )
            )
        scene = Scene(obstacles=tuple(obs), safety_distance=5.0)
        start_ok = float(scene.clearance_over(model, XS, 0.0, 0.5, 50)) > 2.0
        goal_ok = float(scene.clearance(model, xg, 10.0, 50)) > 2.0
        if start_ok and goal_ok:
            return scene, xg


@pytest.mark.parametrize("seed", [1, 2, 4, 5])
def test_seeded_random_scenes_never_violate_clearance(model, seed):
    rng = np.random.default_rng(seed)
    scene, xg = _random_scene(model, rng)
    # control: without the collision-free terms the robot runs into an obstacle in each of these scenes,
    # found by the independent dense check (the body surface inside an obstacle, not only inside D_sf)
    bare = _loop(model, scene, goal_config=xg, duration=12.0, safety=False)
    unsafe = bare.run()
    penetration = _independent_clearance(unsafe, model, scene, bare.tracking_options) + scene.safety_distance
    assert penetration.min() < 0.0, (seed, penetration.min(), unsafe.summary_line())
    # with them, the same scene is cleared at every instant
    loop = _loop(model, scene, goal_config=xg, duration=12.0)
    run = loop.run()
    clear = _independent_clearance(run, model, scene, loop.tracking_options)
    assert clear.min() > 0.0, (seed, clear.min(), run.summary_line())
    assert "unsafe" not in run.step_status


class _RefusingDevice:
    """A device port stand-in: no telemetry, never lost, and every move is refused (`DeviceError`), as a
    stream held meanwhile would; or, with `error`, a move fails with that exception instead."""

    def __init__(self, q0: np.ndarray, error: Exception | None = None) -> None:
        self.q0, self.error = q0, error
        self.refused, self.holds, self.finished = 0, [], None

    def start_actuation(self) -> np.ndarray:
        return self.q0.copy()

    def begin(self, t_origin: float) -> None:
        pass

    def problem(self) -> str:
        return ""

    def measure(self, t, q, qc):
        return q, qc, False

    def move(self, t, q0, commands, control_dt) -> None:
        if self.error is not None:
            raise self.error
        self.refused += 1
        raise DeviceError("stream held: source stalled")

    def pace(self, t: float) -> bool:
        return False

    def landing(self, t, periods, control_dt) -> Landing:
        return Landing.at_rest(self.q0, periods)  # nothing was ever sent: the robot rests where it started

    def hold(self, reason: str) -> None:
        self.holds.append(reason)

    def estop(self, reason: str) -> None:
        raise AssertionError(f"no step of this run is unsafe: {reason}")

    def finish(self, q_final):
        self.finished = np.array(q_final)

    def limit_fractions(self) -> dict:
        return {"max_velocity_fraction": math.nan, "max_acceleration_fraction": math.nan}  # nothing was sent

    def describe(self) -> dict:
        return {"refused": self.refused}


def test_loop_catches_only_device_errors_from_a_device(model, ball_scene):
    loop = _loop(model, ball_scene, duration=1.0)
    q0 = loop.tracker.initial_command(XS)
    dev = _RefusingDevice(q0)
    assert isinstance(dev, Device)
    run = loop.run(device=dev)
    # a refused move does not end the run (the device's `problem()` decides that): every step ran
    assert run.status is RunStatus.TIMEOUT and run.steps == 10
    sent = [s for s in run.step_status if s in ("move", "suboptimal", "fallback")]
    assert dev.refused == len(sent) > 0 and run.device == {"refused": len(sent)}
    # the limit figures of a live run are the device's (here: nothing sent), not the loop model's samples
    s = run.summary()
    assert s["max_velocity_fraction"] is None and s["max_acceleration_fraction"] is None
    assert "no motion was sent to the device" in run.limits_line()
    np.testing.assert_array_equal(dev.finished, run.q[-1])  # finished at the final actuation
    # anything else from a device is not the loop's to swallow
    with pytest.raises(ZeroDivisionError):
        _loop(model, ball_scene, duration=1.0).run(device=_RefusingDevice(q0, ZeroDivisionError("device bug")))
