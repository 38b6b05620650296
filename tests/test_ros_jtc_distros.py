"""The bridge's messages against each ros2_controllers release's joint_trajectory_controller, emulated cycle by cycle
from its C++ source (`jtc_core`, independent of crtraj's model): what the controller writes at every cycle is the
curve the bridge verified, to 1e-9, on Humble, Jazzy and Rolling (with the settings the bridge requires); the old
stamping (no lookahead) fails on Jazzy and Rolling, and Rolling's default blend moves any stamping off the verified
curve, which is why the bridge refuses it. No ROS needed."""

from __future__ import annotations

import numpy as np
import pytest
from jtc_core import JtcCore, Msg, Pt

from crtraj.hardware.ros._controller import check_parameters, detect_distro
from crtraj.hardware.ros._jtc import JtcParameters, Spline, executed, message_epoch, rejection, state_before
from crtraj.hardware.ros._shaping import step_message

NAMES = ("a", "b")
PERIOD = 0.004  # s, a 250 Hz controller
ORIGIN = 1.0  # controller clock time of loop time 0 (s)


def _wire(msg, epoch: float) -> Msg:
    """The message as it goes on the wire (stamp in controller clock time), read the way the controller does."""
    pts = tuple(
        Pt(p.time_from_start, p.positions.copy(), p.velocities.copy() if p.velocities.size else None)
        for p in msg.points
    )
    return Msg(msg.joint_names, epoch + msg.stamp, pts)


def _drive(core: JtcCore, params: JtcParameters, *, seed: int, steps: int = 12, lag: float = PERIOD):
    """Send `steps` replan steps the way `crtraj.hardware.ros._device.RosDevice` does (each sent `lead` s before it
    starts, computed late by up to lead - margin, arriving up to `margin` after it was sent) to `core`, running its
    cycles on the controller clock. Returns the largest difference between what the controller commanded at each
    cycle and the committed (verified) curve of the newest message sent before that cycle."""
    rng = np.random.default_rng(seed)
    dt, n_pts, lead, margin, amax = 0.1, 5, 0.2, 0.02, np.array([4.0, 3.0])
    offsets = dt * np.arange(1, n_pts + 1) / n_pts
    committed = Spline.hermite(np.zeros(1), np.zeros((1, 2)), np.zeros((1, 2)))
    epoch = message_epoch(ORIGIN, params)
    sent: list[tuple[float, Spline]] = []
    clock = 0.0
    deliveries: list[tuple[float, Msg]] = []
    for i in range(steps):
        t = 0.05 + lead + i * dt
        now = t - lead + rng.uniform(0.0, lead - margin)
        p_t = committed.state(t)[0]
        vals = p_t + np.cumsum(rng.normal(0.0, 0.004, (n_pts, 2)), axis=0) + np.outer(offsets, [0.3, -0.2])
        msg = step_message(committed, now, t, (offsets, vals, np.zeros_like(vals)), amax, NAMES, epoch)
        assert rejection(msg, NAMES, now, params, epoch=epoch) is None
        curve = executed(msg, now, *state_before(committed, now, lag), epoch=epoch)
        committed = committed.since(now - 2.0).then(curve)
        sent.append((ORIGIN + now, committed))
        deliveries.append((ORIGIN + now + rng.uniform(0.0, margin), _wire(msg, epoch)))
    end = ORIGIN + committed.end + 0.1
    worst, queue = 0.0, sorted(deliveries, key=lambda d: d[0])
    while clock <= end:
        while queue and queue[0][0] <= clock:
            _, m = queue.pop(0)
            assert core.receive(m, clock) is None
        cmd = core.cycle(clock)
        k = np.searchsorted([s for s, _ in sent], clock, side="right") - 1
        if k >= 0:
            worst = max(worst, float(np.max(np.abs(sent[k][1].at(clock - ORIGIN)[0] - cmd))))
        clock = round(clock + PERIOD, 12)
    return worst


ROLLING_REQUIRED = {"allow_trajectory_replacement": False}


@pytest.mark.parametrize(
    ("distro", "settings", "lag"),
    [
        ("humble", {}, PERIOD),
        ("humble", {"open_loop_control": True}, 3 * PERIOD),
        ("jazzy", {}, PERIOD),
        ("jazzy", {"interpolate_from_desired_state": True}, 2 * PERIOD),
        ("rolling", ROLLING_REQUIRED, PERIOD),
        ("rolling", {**ROLLING_REQUIRED, "interpolate_from_desired_state": True}, PERIOD),
    ],
)
def test_every_cycle_commands_the_verified_curve_on_each_distro(distro, settings, lag):
    """The bridge's stamping for the controller's parameters (`check_parameters`), 12 steps with random lateness
    and arrival: every command the emulated controller writes is the verified curve at its cycle time (1e-9)."""
    core = JtcCore(NAMES, np.zeros(2), distro=distro, period=PERIOD, params=settings, lag=lag)
    values = {**core.params, "joints": list(NAMES), "state_interfaces": ["position", "velocity"], "update_rate": 250}
    params, why = check_parameters("jtc", values, NAMES)
    assert why == "" and params.distro == distro
    assert params.lookahead == (0.0 if distro == "humble" else pytest.approx(PERIOD))
    worst = _drive(core, params, seed=3)
    assert len(core.commanded) > 300 and worst <= 1e-9, worst


@pytest.mark.parametrize("distro", ["jazzy", "rolling"])
def test_the_old_stamping_misses_the_verified_curve_on_jazzy_and_rolling(distro):
    """Stamped without the lookahead (the scheme before this fix), the controller that samples one period ahead runs
    the curve one period early: off the verified curve by about v * period (here more than 1e-4)."""
    core = JtcCore(
        NAMES, np.zeros(2), distro=distro, period=PERIOD, params=ROLLING_REQUIRED if distro == "rolling" else {}
    )
    worst = _drive(core, JtcParameters(distro=distro), seed=3)
    assert worst > 1e-4, worst


@pytest.mark.parametrize("lookahead", [0.0, PERIOD])
def test_rollings_default_blend_moves_any_stamping_off_the_verified_curve(lookahead):
    """Rolling's default (allow_trajectory_replacement: true) blends every message into the running trajectory: with
    or without the lookahead, what it commands differs from the verified curve (by more than 1e-4), so the bridge
    refuses that setting."""
    core = JtcCore(NAMES, np.zeros(2), distro="rolling", period=PERIOD)
    worst = _drive(core, JtcParameters(distro="rolling", lookahead=lookahead), seed=3)
    assert core.blends > 5 and worst > 1e-4, worst


MOVING_END = {"allow_nonzero_velocity_at_trajectory_end": True}  # a line that ends moving


def _ramp(t0: float, t1: float, v: np.ndarray, p0: np.ndarray, n: int = 6) -> Msg:
    """A straight line at velocity v from p0 at stamp t0, n points to t1, each with its velocity (the cubic
    segments are exactly the line)."""
    T = np.linspace(0.0, t1 - t0, n)
    return Msg(NAMES, t0, tuple(Pt(float(s), p0 + v * s, v.copy()) for s in T))


def test_jazzy_writes_the_sample_one_update_period_ahead():
    """Closed form: a line p0 + v (t - t0) sent to Jazzy; at every cycle after adoption the command is the line at
    the cycle time plus one period (Humble: at the cycle time)."""
    v, p0 = np.array([0.5, -0.25]), np.array([0.1, 0.2])
    for distro, ahead in (("jazzy", PERIOD), ("humble", 0.0)):
        core = JtcCore(NAMES, p0, distro=distro, period=PERIOD, params=MOVING_END)
        assert core.receive(_ramp(0.02, 0.4, v, p0), 0.0) is None
        for k in range(60):
            t = k * PERIOD
            cmd = core.cycle(t)
            if 0.02 <= t + ahead <= 0.4:
                assert np.allclose(cmd, p0 + v * (t + ahead - 0.02), atol=1e-12, rtol=0)


def test_rollings_blend_reanchors_a_past_stamp_at_the_arrival_and_stalls_the_old_curve():
    """Closed forms of blend_with_active_trajectory: a message stamped in the past runs from the cycle it arrives in
    (its first point there); one stamped in the future keeps its own times, and the old curve before it runs one
    period late (the command repeats at the arrival cycle)."""
    v, p0 = np.array([0.5, -0.25]), np.zeros(2)
    core = JtcCore(NAMES, p0, distro="rolling", period=PERIOD, params=MOVING_END)
    core.receive(_ramp(0.0, 1.0, v, p0), 0.0)
    cmds = {}
    for k in range(50):
        cmds[k] = core.cycle(k * PERIOD)
    arrival = 50 * PERIOD
    jump = np.array([1.0, 1.0])
    past = Msg(NAMES, 0.1, (Pt(0.0, jump, np.zeros(2)), Pt(0.3, jump, np.zeros(2))))
    assert core.receive(past, arrival) is None
    assert np.allclose(core.cycle(arrival), jump) and core.blends == 1  # its first point at the arrival cycle
    core = JtcCore(NAMES, p0, distro="rolling", period=PERIOD, params=MOVING_END)
    core.receive(_ramp(0.0, 1.0, v, p0), 0.0)
    for k in range(50):
        core.cycle(k * PERIOD)
    future = _ramp(0.4, 0.8, v, p0 + v * 0.4)  # the same line from 0.4 s on
    core.receive(future, arrival)
    stalled = core.cycle(arrival)
    assert np.allclose(stalled, cmds[49], atol=1e-12)  # the previous cycle's command again
    late = [core.cycle((k + 1) * PERIOD + arrival) for k in range(10)]
    # the old waypoint at 0.2 s now lies at 0.2 s + one period, the new one at its own 0.4 s: at cycle t the command
    # (sampled one period ahead) is the cubic Hermite between them, not the line
    ta, tb, pa, pb = 0.2 + PERIOD, 0.4, p0 + v * 0.2, p0 + v * 0.4
    h, x = tb - ta, (arrival + 10 * PERIOD + PERIOD - ta) / (tb - ta)
    hermite = (2 * x**3 - 3 * x**2 + 1) * pa + (x**3 - 2 * x**2 + x) * h * v + (-2 * x**3 + 3 * x**2) * pb
    hermite = hermite + (x**3 - x**2) * h * v
    assert np.allclose(late[-1], hermite, atol=1e-12)
    assert np.max(np.abs(late[-1] - (p0 + v * (arrival + 11 * PERIOD)))) > 1e-5  # off the line sent


@pytest.mark.parametrize(
    ("distro", "change", "field"),
    [
        ("rolling", {}, "jtc.allow_trajectory_replacement: true"),
        ("jazzy", {"speed_scaling.initial_scaling_factor": 0.5}, "jtc.speed_scaling.initial_scaling_factor"),
        ("rolling", {**ROLLING_REQUIRED, "speed_scaling.state_interface": "speed_scaling/factor"},
         "jtc.speed_scaling.state_interface"),
        ("humble", {"constraints.b.trajectory": 0.05}, "jtc.constraints.b.trajectory"),
        ("jazzy", {"constraints.goal_time": 0.5, "constraints.a.goal": 0.01}, "jtc.constraints.goal_time"),
        ("humble", {"cmd_timeout": 0.5}, "jtc.cmd_timeout"),
        ("humble", {"state_interfaces": ["position"]}, "jtc.open_loop_control: false"),
        ("jazzy", {"state_interfaces": ["position"]}, "jtc.interpolate_from_desired_state: false"),
        ("rolling", {**ROLLING_REQUIRED, "state_interfaces": ["position"]}, "jtc.interpolate_from_desired_state"),
        ("jazzy", {"update_rate": None}, "ros.update_rate"),
        ("humble", {"interpolation_method": "none"}, "jtc.interpolation_method"),
        ("rolling", {**ROLLING_REQUIRED, "joints": ["a"]}, "jtc.joints: no b"),
    ],
)  # fmt: skip
def test_each_parameter_that_changes_the_executed_curve_is_refused_in_one_line(distro, change, field):
    """Each distro's defaults (Rolling with allow_trajectory_replacement false) pass; each change that makes the
    executed curve differ from the verified one is refused in one line naming the parameter."""
    base = {**JtcCore(NAMES, np.zeros(2), distro=distro).params, "joints": list(NAMES), "update_rate": 250,
            "state_interfaces": ["position", "velocity"]}  # fmt: skip
    if distro == "rolling" and change != {}:
        assert check_parameters("jtc", {**base, **ROLLING_REQUIRED}, NAMES)[1] == ""
    elif distro != "rolling":
        assert check_parameters("jtc", base, NAMES)[1] == ""
    _, why = check_parameters("jtc", {**base, **change}, NAMES)
    assert why.startswith(field) and "\n" not in why, why


def test_the_distro_is_told_by_the_parameters_declared_and_an_explicit_one_is_checked():
    """Humble declares open_loop_control, Jazzy also interpolate_from_desired_state, Rolling
    allow_trajectory_replacement and not open_loop_control; Humble's allow_nonzero_velocity_at_trajectory_end
    defaults to true, later ones to false; ros.distro naming another release is refused."""
    for distro in ("humble", "jazzy", "rolling"):
        assert detect_distro(JtcCore(NAMES, np.zeros(2), distro=distro).params) == distro
    assert "open_loop_control" not in JtcCore(NAMES, np.zeros(2), distro="rolling").params
    assert detect_distro({"joints": ["a"]}) is None
    humble, _ = check_parameters("jtc", {"open_loop_control": False}, NAMES)
    jazzy, _ = check_parameters("jtc", {"interpolate_from_desired_state": False, "update_rate": 100}, NAMES)
    assert humble.allow_nonzero_velocity_at_trajectory_end and not jazzy.allow_nonzero_velocity_at_trajectory_end
    assert jazzy.lookahead == pytest.approx(0.01)
    _, why = check_parameters("jtc", {"open_loop_control": False}, NAMES, distro="jazzy")
    assert why.startswith("ros.distro: 'jazzy', but jtc has the parameters of humble")
    # no answer: ros.distro decides; Jazzy then needs ros.update_rate
    assert check_parameters("jtc", {}, NAMES, distro="jazzy")[1].startswith("ros.update_rate")
    params, why = check_parameters("jtc", {}, NAMES, distro="jazzy", update_rate=500.0)
    assert why == "" and params.lookahead == pytest.approx(0.002)
