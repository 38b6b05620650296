"""The ROS device port (`crtraj.hardware.ros._device.RosDevice`) without ROS: a fake node records what would be
published and serves chosen joint states; a virtual clock times it."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PAPER
from feed_clock import VirtualClock

from crtraj.control.ports import DeviceError
from crtraj.control.tracking import TrackingController, TrackingOptions
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.ros._device import RosDevice
from crtraj.hardware.ros._options import RosOptions
from crtraj.hardware.verify import FrameVerifier
from crtraj.io.problem import Problem
from crtraj.model.kinematics import Model
from crtraj.world.scene import Scene


def test_trajectory_points_follow_the_servo_model_exactly():
    """Positions and velocities sent for a step: the first-order servo's response, checked against a fine
    numerical integration of dq/dt = (c - q) / tau (no ROS needed)."""
    from types import SimpleNamespace

    problem = Problem.load(PAPER)
    acts = Actuators.from_robot(problem.robot)
    servo = TrackingController(Model(problem.robot), TrackingOptions()).servo
    dev = RosDevice(SimpleNamespace(options=RosOptions(points_per_step=7)), acts, None, servo, 0.1, None, None)
    rng = np.random.default_rng(3)
    q0 = acts.actuation(np.zeros(acts.n)) + rng.normal(0, 0.5, acts.n)
    C = q0 + rng.normal(0, 1.0, (5, acts.n))  # one command per 0.02 s period
    values, vel = dev.samples(q0, C)
    # independent: explicit Euler with 20000 sub-steps per period
    h, n = 0.02, 20000
    q, Q = q0.copy(), [q0.copy()]
    for c in C:
        for _ in range(n):
            q = q + (h / n) * (c - q) / servo.tau
            Q.append(q.copy())
    Q = np.array(Q)
    for k, off in enumerate(dev.offsets):
        i = round(float(off) / (h / n))
        assert np.allclose(acts.actuation(values[k]), Q[i], atol=1e-3)
        left = (Q[i] - Q[i - 1]) / (h / n)  # the velocity at the point, from the period that ends there
        assert np.allclose(vel[k] / acts.scale, left, rtol=1e-3, atol=1e-3)


class _FakeNode:
    """A node without ROS: records what would be published and serves a chosen joint state."""

    def __init__(self, options: RosOptions, names=()) -> None:
        self.options, self.sent, self.state, self.names = options, [], None, tuple(names)

    def joint_state(self):
        return self.state

    def wait_joint_state(self, newer_than: float, timeout: float):
        return self.state if self.state is not None and self.state[1] >= newer_than else None

    def publish_trajectory(self, stamp, offsets, values, velocities) -> None:
        self.sent.append((stamp, np.array(offsets), np.array(values), np.array(velocities)))

    def publish_markers(self, msg) -> None:
        pass


def _hermite(t, T, P, V):
    """Independent cubic Hermite through knots (T, P, V) at time t (positions)."""
    k = int(np.clip(np.searchsorted(T, t, side="right") - 1, 0, len(T) - 2))
    h = T[k + 1] - T[k]
    x = (t - T[k]) / h
    return (
        (2 * x**3 - 3 * x**2 + 1) * P[k]
        + (x**3 - 2 * x**2 + x) * h * V[k]
        + (-2 * x**3 + 3 * x**2) * P[k + 1]
        + (x**3 - x**2) * h * V[k + 1]
    )


def test_measurement_is_the_commanded_motion_corrected_by_the_joint_state():
    """Sent lead s ahead, measured by prediction: the curve the controller executes at t plus the joint state's
    deviation from it at its stamp, decayed with the servo lag (closed form, no ROS needed)."""
    problem = Problem.load(PAPER)
    acts = Actuators.from_robot(problem.robot)
    model = Model(problem.robot)
    servo = TrackingController(model, TrackingOptions()).servo
    scene = Scene.from_table(problem.section("scene")).with_obstacles(())
    ros = RosOptions(points_per_step=5, joint_state_timeout=1.0)
    node, clock = _FakeNode(ros, acts.names), VirtualClock()
    ver = FrameVerifier(problem.robot, acts, scene, 0.005, model=model)
    dev = RosDevice(node, acts, model, servo, 0.1, ver, lambda: scene, clock=clock, sleep=clock.sleep, lead=0.2)
    x0 = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
    q0 = problem.robot.cable_matrix()[1] + problem.robot.cable_matrix()[0] @ x0
    node.state = (acts.command(q0), 0.0)
    assert np.allclose(dev.start_actuation(), q0)
    dev.begin(0.0)  # loop time 0 is clock time 0.2: the first step is sent now, 0.2 s ahead
    C = np.repeat((q0 + 0.05)[None], 5, axis=0)
    dev.move(0.0, q0, C, 0.02)
    assert node.sent[-1][0] == pytest.approx(0.2) and dev.pace(0.1) is False and clock() == pytest.approx(0.1)
    # the message: the state at the step's start (at rest), the step's 5 points, the stop tail's rest point
    _, offs, vals, vels = node.sent[-1]
    assert len(offs) == 7 and np.allclose(offs[:6], 0.02 * np.arange(6)) and np.all(vels[[0, -1]] == 0.0)
    values = vals[1:6]
    # the robot, measured at clock 0.25 (loop time 0.05), is 0.01 mm ahead on every actuator of what it executes
    ref = _hermite(0.05, offs, vals, vels)  # the controller's cubic segments, at loop time 0.05
    off = np.full(acts.n, 0.01)
    node.state = (acts.command(acts.actuation(ref) + off), 0.25)
    q, qc, ok = dev.measure(0.1, q0, C[-1])
    expect = acts.actuation(values[-1]) + np.exp(-(0.1 - 0.05) / servo.tau) * off
    assert ok and np.allclose(q, expect, atol=1e-9) and np.array_equal(qc, C[-1])
    # a step not ready before its start is refused; the robot finishes what is under way: its stop tail
    clock.advance_to(0.31)
    with pytest.raises(
        DeviceError, match=r"ready 0\.210 s late, beyond the bound .* \(\+0\.010 s from its start time\)"
    ):
        dev.move(0.1, q, C, 0.02)
    stamp, offs2, vals2, vels2 = node.sent[-1]
    # the hold: the committed knots from the last one already due (the step's last point, at loop time 0.1) to rest
    assert stamp == pytest.approx(0.2 + offs[-2]) and len(offs2) == 2
    assert np.array_equal(vals2, vals[-2:]) and np.array_equal(vels2, vels[-2:]) and np.all(vels2[-1] == 0.0)
    # no joint state newer than joint_state_timeout: the robot is lost
    clock.advance_to(5.0)
    dev.measure(0.2, q, qc)
    assert "robot lost" in dev.problem()


@pytest.mark.parametrize("off", [0.9, 1.1])
def test_a_controller_that_does_not_execute_what_was_sent_stops_the_run_named(off):
    """An inactive controller keeps its subscription but drops every message, and the topic gives no feedback:
    its joints stay at rest while the curve sent moves on. A joint state more than ``ros.following_error`` off
    the curve at its stamp (the controller's cubic segments, evaluated independently) ends the run with the
    joint named; `off` x the limit below it is measured as usual."""
    problem = Problem.load(PAPER)
    acts = Actuators.from_robot(problem.robot)
    model = Model(problem.robot)
    servo = TrackingController(model, TrackingOptions()).servo
    scene = Scene.from_table(problem.section("scene")).with_obstacles(())
    x0 = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
    q0 = problem.robot.cable_matrix()[1] + problem.robot.cable_matrix()[0] @ x0
    C = np.repeat((q0 + np.r_[np.full(acts.n - 1, 0.04), 0.05])[None], 5, axis=0)  # z (the stage) moves most
    # the curve sent for this step, at loop time 0.08, from a first device (the limit does not change what is sent)
    probe_node, probe_clock = _FakeNode(RosOptions(points_per_step=5), acts.names), VirtualClock()
    probe_node.state = (acts.command(q0), 0.0)
    ver = FrameVerifier(problem.robot, acts, scene, 0.005, model=model)
    probe = RosDevice(probe_node, acts, model, servo, 0.1, ver, lambda: scene, clock=probe_clock, lead=0.2)
    assert np.allclose(probe.start_actuation(), q0)
    probe.begin(0.0)
    probe.move(0.0, q0, C, 0.02)
    _, offs, vals, vels = probe_node.sent[-1]
    gap = acts.actuation(_hermite(0.08, offs, vals, vels)) - q0  # what an idle robot lags behind it, mm
    worst = int(np.argmax(np.abs(gap)))
    limit = float(np.abs(gap[worst])) / off
    ros = RosOptions(points_per_step=5, joint_state_timeout=1.0, following_error=limit, joints=(("z", "stage"),))
    node, clock = _FakeNode(ros, acts.names), VirtualClock()
    node.state = (acts.command(q0), 0.0)
    dev = RosDevice(node, acts, model, servo, 0.1, ver, lambda: scene, clock=clock, sleep=clock.sleep, lead=0.2)
    assert np.allclose(dev.start_actuation(), q0)
    dev.begin(0.0)
    dev.move(0.0, q0, C, 0.02)
    node.state = (acts.command(q0), 0.28)  # the joints still at rest, stamped at loop time 0.08
    clock.advance_to(0.3)
    q, _, ok = dev.measure(0.1, q0, C[-1])
    if off < 1.0:
        assert ok and dev.problem() == ""
        return
    name = ros.joint_name(acts.names[worst])
    assert not ok and np.array_equal(q, q0)
    assert dev.problem() == (
        f"ros: joint {name!r} is {abs(gap[worst]):.2f} mm off the curve sent to joint_trajectory_controller at "
        f"t = 0.080 s (ros.following_error {limit:g} mm): the controller is not executing it; check that it is "
        "active (ros2 control list_controllers) and owns the joint"
    )


@pytest.mark.parametrize("margin", [0.0, 0.05])
def test_a_step_later_than_the_lateness_bound_is_refused_not_sent(margin):
    """Steps computed late on a virtual clock (lead 0.2 s, arrival margin `margin`): up to the bound lead - margin
    each is published, and its message starts at a committed knot already due (it survives arrival up to
    `margin` later); a bound and 1 ms late, the step is refused and counted (late_refused), and the only message
    that leaves is the hold: the committed curve, unchanged."""
    problem = Problem.load(PAPER)
    acts = Actuators.from_robot(problem.robot)
    model = Model(problem.robot)
    servo = TrackingController(model, TrackingOptions()).servo
    scene = Scene.from_table(problem.section("scene")).with_obstacles(())
    node, clock = _FakeNode(RosOptions(points_per_step=5), acts.names), VirtualClock(1.0)
    ver = FrameVerifier(problem.robot, acts, scene, 0.005, model=model)
    dev = RosDevice(
        node, acts, model, servo, 0.1, ver, lambda: scene, clock=clock, sleep=clock.sleep, lead=0.2,
        arrival_margin=margin, state_lag=0.01,
    )  # fmt: skip
    q0 = problem.robot.cable_matrix()[1]
    node.state = (acts.command(q0), 0.0)
    dev.start_actuation()
    dev.begin(0.0)  # loop time t is clock time 1.2 + t
    q, qc, bound = q0.copy(), q0.copy(), 0.2 - margin
    dz = np.zeros(acts.n)
    dz[-1] = 0.02  # the z stage moves 0.02 mm a step
    for k, late in enumerate([0.0, bound * 0.5, bound]):
        t = 0.1 * k
        clock.advance_to(1.0 + t + late)  # step t is due to be sent 0.2 s before it starts
        C = qc + np.outer(np.arange(1, 6) / 5, dz)  # a ramp of set-points
        dev.move(t, q, C, 0.02)
        stamp = node.sent[-1][0]
        assert k == 0 or stamp <= clock() + 1e-12  # its first point is due when it is sent (after the start at rest)
        for c in C:  # where the servo model is at the step's end
            q = servo.advance(q, c, 0.02)
        qc = C[-1]
    assert dev.refused_steps == dev.late_refused == 0 and len(node.sent) == 3
    before = dev.committed
    clock.advance_to(1.3 + bound + 0.001)
    with pytest.raises(DeviceError, match=r"late, beyond the bound"):
        dev.move(0.3, q, qc + np.outer(np.arange(1, 6) / 5, dz), 0.02)
    assert dev.refused_steps == dev.late_refused == 1 and len(node.sent) == 4 and dev.holds == 1
    ts = np.linspace(clock() - 1.2, before.end + 0.1, 200)
    assert np.allclose(dev.committed.at(ts)[0], before.at(ts)[0], atol=1e-12)  # the hold: the same curve


def test_a_refused_step_lands_on_the_committed_stop_tail():
    """Issue 36: after a step is refused, the loop plans from `RosDevice.landing`, the committed curve the robot
    executes instead: its stop tail, then rest. Checked against an independent cubic Hermite through the last
    step message's knots (the controller's segments), with the set-point the first-order servo needs to move so
    (q + tau dq/dt, by central differences); `measure` gives the same set-point on the tail, not a rest at q."""
    problem = Problem.load(PAPER)
    acts = Actuators.from_robot(problem.robot)
    model = Model(problem.robot)
    servo = TrackingController(model, TrackingOptions()).servo
    scene = Scene.from_table(problem.section("scene")).with_obstacles(())
    node, clock = _FakeNode(RosOptions(points_per_step=5, joint_state_timeout=10.0), acts.names), VirtualClock(1.0)
    ver = FrameVerifier(problem.robot, acts, scene, 0.005, model=model)
    dev = RosDevice(node, acts, model, servo, 0.1, ver, lambda: scene, clock=clock, sleep=clock.sleep, lead=0.2)
    q = problem.robot.cable_matrix()[1]
    node.state = (acts.command(q), 0.0)
    dev.start_actuation()
    dev.begin(0.0)  # loop time t is clock time 1.2 + t
    qc, dz = q.copy(), np.zeros(acts.n)
    dz[-1] = 0.4  # the z stage ramps up to 4 mm/s
    for k in range(3):
        clock.advance_to(1.0 + 0.1 * k)
        C = qc + np.outer(np.arange(1, 6) / 5, dz)
        dev.move(0.1 * k, q, C, 0.02)
        for c in C:
            q = servo.advance(q, c, 0.02)
        qc = C[-1]
    stamp, offs, vals, vels = node.sent[-1]  # the last step: its points and its stop tail
    clock.advance_to(1.501)  # step 0.3 is ready 1 ms beyond the lateness bound (0.2 s): refused
    with pytest.raises(DeviceError, match="late"):
        dev.move(0.3, q, qc + np.outer(np.arange(1, 6) / 5, dz), 0.02)
    land = dev.landing(0.3, 5, 0.02)

    def curve(t):  # independent: the step message's cubic Hermite at loop time t, resting after its last knot
        tau = np.clip(t - (stamp - 1.2), offs[0], offs[-1])
        return acts.actuation(_hermite(tau, offs, vals, vels))

    times = 0.3 + 0.02 * np.arange(1, 6)
    np.testing.assert_allclose(land.executed, [curve(t) for t in times], atol=1e-9)
    e = 1e-6
    rate = np.array([(curve(t + e) - curve(t - e)) / (2 * e) for t in times])
    np.testing.assert_allclose(land.commands, land.executed + servo.tau * rate, atol=1e-5)
    assert np.abs(rate[0, -1]) > 1.0  # still moving after the refused step's start: a rest there would be a jump
    # the measurement off the sent steps: the committed set-point, consistent with the landing
    node.state = (acts.command(curve(0.32)), 1.52)  # the joint state on the curve: no deviation to correct
    q_m, qc_m, ok = dev.measure(0.32, q, qc)
    assert ok and np.allclose(q_m, land.executed[0], atol=1e-9) and np.allclose(qc_m, land.commands[0], atol=1e-9)
    # long after: at rest at the tail's end, every row equal
    rest = dev.landing(5.0, 5, 0.02)
    np.testing.assert_allclose(rest.executed, np.repeat(acts.actuation(vals[-1])[None], 5, axis=0), atol=1e-9)
    np.testing.assert_allclose(rest.commands, rest.executed, atol=1e-9)
