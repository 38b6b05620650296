"""The contract between the closed loop and any device (`crtraj.control.ports.Device.landing`): a step the device
refuses, holds or gets late is not executed, and the loop plans the next step from what the device executes
instead, never from its own unsent plan.

`GatedDevice` is a faithful emulator of a robot behind a trajectory controller, on loop time (no wall clock): its
first-order servos follow the set-points it accepts, and it accepts a step only when the step starts where the
robot is and its set-points continue the ones in force within the actuators' speed and acceleration limits (the
finite differences of the actuator values, as a controller's limits gate computes them). Besides, it refuses steps
at random and refuses steps that are ready too late; a refused or held step leaves the set-point where it is (a
hold: braking, always allowed) and the servos settle to it. A loop that planned on from its unsent plan asked the
held robot for the same impossible catch-up at every later step (the ROS round trip's wedge under load: 504
refusals for one acceleration figure); the property below drives the loop against this device and checks that
it never wedges.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import XG, XS
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import ClosedLoop, LoopOptions, RunStatus
from crtraj.control.ports import Device, DeviceError, Landing
from crtraj.core.clock import VirtualClock
from crtraj.hardware.actuators import Actuators
from crtraj.world.scene import Scene

FAST = {"horizon": 6, "points": 12, "solver": "sqp"}
# A step whose move the device never took: a hold (the loop's or the device's) that a feasible step could have
# avoided. After a refusal the loop plans from the device's landing, so its next step joins what the robot does
# and is accepted at once; the replanner restarts cold there (its warm start followed the unsent plan) and the
# one step of slack below lets a cold solve that misses its first iteration fall back to a hold. Random refusals
# and late steps are the device's doing and neither count nor break a streak.
MAX_AVOIDABLE_HOLDS = 1
LATE_BOUND = 0.05  # s: a step ready later than this is refused (ros.lead - ros.arrival_margin)


class GatedDevice:
    """A robot behind a trajectory controller on loop time; implements `crtraj.control.ports.Device`.

    servo: the loop's servo model (the robot's own servos). limits: the actuators' `RateLimits` (actuator
    values J x). q0: the start actuation (mm). h: the control period (s). refuse: probability of a refusal at
    random; late_scale: mean lateness (s) of a step, exponentially distributed; rng: the randomness. `outcomes`
    says for every step: moved, random, late, gate (refused by the limits gate) or hold (the loop's hold).
    """

    def __init__(self, servo, limits, q0, h: float, refuse: float, late_scale: float, rng) -> None:
        self.servo, self.limits, self.h = servo, limits, h
        self.dt = 0.0  # the loop's step (s), set by `_drive`
        self.q, self.qc = np.array(q0, dtype=float), np.array(q0, dtype=float)
        self.inc = np.zeros(len(limits.amax))  # the set-point's last change (actuator values)
        self.t = 0.0  # loop time the state is at
        self.refuse, self.late_scale, self.rng = refuse, late_scale, rng
        self.outcomes: list[str] = []
        self.gate_refusals: list[str] = []
        self.late_flag = False
        self.estopped = ""
        self.executed: list[np.ndarray] = []  # the actuation at the end of every control period (mm)
        self.lost_after: int | None = None  # steps after which the device is lost (None: never)

    def _a(self, q: np.ndarray) -> np.ndarray:
        return self.limits.jacobian @ self.servo.config(q)

    def _advance_to(self, t: float) -> None:
        """Hold (the set-point frozen, the servos settling) until loop time t."""
        while self.t < t - 1e-9:
            self.q = self.servo.advance(self.q, self.qc, self.h)
            self.inc = np.zeros_like(self.inc)
            self.t += self.h
            self.executed.append(self.q.copy())

    def start_actuation(self) -> np.ndarray:
        return self.q.copy()

    def begin(self, t_origin: float) -> None:
        pass

    def problem(self) -> str:
        lost = self.lost_after is not None and len(self.outcomes) >= self.lost_after
        return f"device lost after {self.lost_after} steps" if lost else ""

    def measure(self, t, q, qc):
        self._advance_to(t)
        return self.q.copy(), self.qc.copy(), True

    def _gate(self, q0: np.ndarray, commands: np.ndarray) -> str:
        """Why the controller would refuse the step ('' when it takes it)."""
        if not np.allclose(q0, self.q, atol=1e-6):
            return f"starts {np.max(np.abs(q0 - self.q)):.3f} mm from where the robot is"
        a = np.vstack([self._a(self.qc)[None], [self._a(c) for c in commands]])
        vel = np.diff(a, axis=0) / self.h
        acc = np.diff(np.vstack([self.inc[None] / self.h, vel]), axis=0) / self.h
        lim = self.limits
        for what, v, bound in (("velocity", vel, lim.vmax), ("acceleration", acc, lim.amax)):
            bad = np.abs(v) > bound * (1 + 1e-6) + 1e-9
            if np.any(bad):
                j, i = np.argwhere(bad)[0]
                return f"{lim.names[i]} {what} {v[j, i]:.3f} exceeds limit {bound[i]:g}"
        return ""

    def move(self, t, q0, commands, control_dt) -> None:
        self._advance_to(t)
        late = float(self.rng.exponential(self.late_scale)) if self.late_scale > 0 else 0.0
        self.late_flag = late > 2 * self.h
        if late > LATE_BOUND:
            self.outcomes.append("late")
            raise DeviceError(f"ready {late:.3f} s late, beyond the bound {LATE_BOUND:g} s")
        if self.rng.random() < self.refuse:
            self.outcomes.append("random")
            raise DeviceError("refused at random")
        why = self._gate(np.asarray(q0, dtype=float), np.asarray(commands, dtype=float))
        if why:
            self.outcomes.append("gate")
            self.gate_refusals.append(f"t={t:.2f} s: {why}")
            raise DeviceError(f"refused by the limits gate: {why}")
        for c in np.asarray(commands, dtype=float):
            self.q = self.servo.advance(self.q, c, self.h)
            self.inc = self._a(c) - self._a(self.qc)
            self.qc = c.copy()
            self.t += self.h
            self.executed.append(self.q.copy())
        self.outcomes.append("moved")

    def landing(self, t, periods, control_dt) -> Landing:
        self._advance_to(t)
        q, rows = self.q, []
        for _ in range(periods):
            q = self.servo.advance(q, self.qc, control_dt)
            rows.append(q)
        return Landing(np.repeat(self.qc[None], periods, axis=0), np.array(rows))

    def pace(self, t: float) -> bool:
        return self.late_flag

    def hold(self, reason: str) -> None:
        self.outcomes.append("hold")

    def estop(self, reason: str) -> None:
        self.estopped = reason
        self.outcomes.append("estop")

    def finish(self, q_final):
        self._advance_to(len(self.outcomes) * self.dt)  # a last held step
        return self.describe()

    def limit_fractions(self) -> dict:
        return {"max_velocity_fraction": math.nan, "max_acceleration_fraction": math.nan}

    def describe(self) -> dict:
        return {k: self.outcomes.count(k) for k in ("moved", "random", "late", "gate", "hold")}

    def avoidable_streak(self) -> int:
        """The longest run of steps without a move, not counting (nor ending a run at) the device's own random
        refusals and late steps."""
        best = cur = 0
        for o in self.outcomes:
            if o == "moved":
                cur = 0
            elif o in ("gate", "hold", "estop"):
                cur += 1
                best = max(best, cur)
        return best


@pytest.fixture(scope="module")
def loop(model, robot) -> ClosedLoop:
    """The loop from XS to XG's tip in open space under the actuators' limits, on a virtual clock."""
    limits = Actuators.from_robot(robot).rate_limits(robot)
    return ClosedLoop.build(
        model,
        Scene(obstacles=(), safety_distance=5.0),
        model.tip_position(XG),
        XS,
        options=ReplanOptions(**FAST),
        loop_options=LoopOptions(duration=40.0),
        goal_config=XG,
        rate_limits=limits,
        clock=VirtualClock(),
    )


def _drive(loop: ClosedLoop, refuse: float, late_scale: float, seed: int, lost_after: int | None = None):
    dev = GatedDevice(
        loop.servo,
        loop.rate_limits,
        loop.tracker.initial_command(XS),
        loop.options.dt / loop.n_sub,
        refuse,
        late_scale,
        np.random.default_rng(seed),
    )
    dev.dt, dev.lost_after = loop.options.dt, lost_after
    assert isinstance(dev, Device)
    return dev, loop.run(device=dev)


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    refuse=st.floats(0.1, 0.5),
    late_scale=st.floats(0.0, 0.03),
    seed=st.integers(0, 2**31 - 1),
    lost_after=st.one_of(st.none(), st.integers(10, 60)),
)
@example(refuse=0.5, late_scale=0.03, seed=7, lost_after=None)
@example(refuse=0.3, late_scale=0.02, seed=11, lost_after=25)
def test_random_refusals_and_lateness_never_wedge_the_loop(loop, refuse, late_scale, seed, lost_after):
    dev, run = _drive(loop, refuse, late_scale, seed, lost_after)
    counts = dev.describe()
    note = (refuse, late_scale, seed, counts, dev.gate_refusals[:3], run.summary_line())
    assert counts["random"] + counts["late"] > 0, note  # the device did refuse
    # every step the loop sent continued what the robot was doing: the limits gate never refused one ...
    assert counts["gate"] == 0, note
    # ... and no step held for longer than the bound while a feasible step existed (open space: always)
    assert dev.avoidable_streak() <= MAX_AVOIDABLE_HOLDS, note
    # the run reached the goal, or stopped for a named reason (here: only a lost device)
    if run.status is RunStatus.REACHED:
        assert np.linalg.norm(loop.model.tip_position(loop.servo.config(dev.q)) - loop.goal) <= loop.goal_tolerance
    else:
        assert run.status is RunStatus.DEVICE and run.message == f"device lost after {lost_after} steps", note
        assert len(dev.outcomes) == lost_after, note
    # either way the run's last state is where the device is (its committed motion ends on the held set-point)
    np.testing.assert_allclose(run.q[-1], dev.q, atol=1e-9)
    # the record follows the robot: every recorded state is the device's (its actuation at each step's start)
    assert run.steps == len(dev.outcomes)


def test_the_record_is_what_the_device_executed(loop):
    """The run's record follows the robot, refused and late steps included: its actuation at the end of every
    control period is the device's own (not the loop's unsent plan), and replays through the servo formula from
    the recorded set-points; a refused step names its reason."""
    dev, run = _drive(loop, 0.4, 0.025, 3)
    assert dev.outcomes.count("random") and dev.outcomes.count("late")
    np.testing.assert_allclose(run.executed[1:], np.array(dev.executed), atol=1e-9)
    tau, h = loop.servo.tau, run.control_dt
    q, ends = run.q[0].copy(), []
    for c in run.commands:
        q = c + np.exp(-h / tau) * (q - c)
        ends.append(q)
    np.testing.assert_allclose(np.array(ends), run.executed[1:], atol=1e-9)
    for k, o in enumerate(dev.outcomes):
        if o in ("random", "late"):
            assert "not sent: " + ("refused at random" if o == "random" else "ready") in run.reason[k]
