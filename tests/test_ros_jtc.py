"""The joint_trajectory_controller model (`crtraj.hardware.ros._jtc`) and the bridge's message shaping
(`crtraj.hardware.ros._shaping`) against closed forms; no ROS needed."""

from __future__ import annotations

import numpy as np
import pytest

from crtraj.hardware.ros._controller import check_parameters
from crtraj.hardware.ros._jtc import JtcMessage, JtcParameters, Spline, executed, rejection, state_before
from crtraj.hardware.ros._shaping import TAIL_FRACTION, hold_message, step_message, stop_tail

NAMES = ("a", "b")
DEFAULT = JtcParameters()


def _msg(stamp, tfs, P, V=None, A=None, names=NAMES):
    return JtcMessage.from_arrays(names, stamp, np.asarray(tfs, float), np.asarray(P, float), V, A)


def test_cubic_segment_meets_its_boundary_conditions_and_the_hermite_midpoint():
    """Positions and velocities at both ends: the cubic Hermite, p(h/2) = (pa+pb)/2 + h (va-vb)/8."""
    rng = np.random.default_rng(0)
    pa, pb, va, vb = rng.normal(size=(4, 2))
    h = 0.37
    s = Spline.hermite(np.array([1.0, 1.0 + h]), np.array([pa, pb]), np.array([va, vb]))
    p0, v0, _ = s.at(1.0)
    p1, v1, _ = s.at(1.0 + h - 1e-12)
    assert np.allclose(p0, pa) and np.allclose(v0, va) and np.allclose(p1, pb) and np.allclose(v1, vb, atol=1e-9)
    pm, _, _ = s.at(1.0 + h / 2)
    assert np.allclose(pm, (pa + pb) / 2 + h * (va - vb) / 8)


def test_quintic_segment_is_the_minimum_jerk_polynomial_at_rest_ends():
    """With accelerations at both ends (all zero here): p = pa + d (10 s^3 - 15 s^4 + 6 s^5)."""
    pa, pb, z = np.array([0.2, -1.0]), np.array([1.0, 3.0]), np.zeros(2)
    s = Spline(np.array([0.0, 2.0]), np.array([pa, pb]), [z, z], [z, z])
    assert s.kinds == ["quintic"]
    for x in (0.1, 0.5, 0.8):
        p, v, a = s.at(2.0 * x)
        assert np.allclose(p, pa + (pb - pa) * (10 * x**3 - 15 * x**4 + 6 * x**5))
        assert np.allclose(v, (pb - pa) * (30 * x**2 - 60 * x**3 + 30 * x**4) / 2.0)
        assert np.allclose(a, (pb - pa) * (60 * x - 180 * x**2 + 120 * x**3) / 4.0)


def test_quintic_segment_meets_given_end_velocities_and_accelerations():
    """Non-zero velocities and accelerations at both ends are met, and the velocity and acceleration it reports
    are the derivatives of its positions (central differences)."""
    rng = np.random.default_rng(1)
    pa, pb, va, vb, aa, ab = rng.normal(size=(6, 2))
    h = 0.5
    s = Spline(np.array([0.0, h]), np.array([pa, pb]), [va, vb], [aa, ab])
    for t, want in ((0.0, (pa, va, aa)), (h - 1e-9, (pb, vb, ab))):
        for got, w in zip(s.at(t), want, strict=True):
            assert np.allclose(got, w, atol=1e-6)
    e, t = 1e-4, 0.31
    q = np.array([s.at(t + k * e)[0] for k in (-1, 0, 1)])
    _, v, a = s.at(t)
    assert np.allclose((q[2] - q[0]) / (2 * e), v, atol=1e-6)
    assert np.allclose((q[2] - 2 * q[1] + q[0]) / e**2, a, atol=1e-4)


def test_positions_only_interpolate_linearly_and_the_end_holds():
    """Without velocities a segment is linear; after the last point the last point holds."""
    s = Spline(np.array([0.0, 1.0]), np.array([[0.0, 0.0], [2.0, -4.0]]), [None, None], [None, None])
    p, v, _ = s.at(0.25)
    assert np.allclose(p, [0.5, -1.0]) and np.allclose(v, [2.0, -4.0])
    p, v, _ = s.at(5.0)
    assert np.allclose(p, [2.0, -4.0]) and np.allclose(v, 0.0)


def test_replacement_mid_trajectory_splines_from_the_state_at_arrival():
    """A message arriving at t=0.3 with a future stamp: the executed curve starts at the arrival state and is
    the cubic Hermite from it to the first point, then the message's segments."""
    old = Spline.hermite(np.array([0.0, 1.0]), np.array([[0.0, 0.0], [1.0, 2.0]]), np.array([[0.0, 0.0], [0.0, 0.0]]))
    p_arr, v_arr = old.state(0.3)
    msg = _msg(0.5, [0.0, 0.4], [[2.0, 2.0], [3.0, 1.0]], [[1.0, 0.0], [0.0, 0.0]])
    assert rejection(msg, NAMES, 0.3, DEFAULT) is None
    cur = executed(msg, 0.3, p_arr, v_arr)
    p, v, _ = cur.at(0.3)
    assert np.allclose(p, p_arr) and np.allclose(v, v_arr)
    h, pa, pb, va, vb = 0.2, p_arr, np.array([2.0, 2.0]), v_arr, np.array([1.0, 0.0])
    x = 0.4  # at t = 0.3 + 0.4 h: the Hermite basis
    hb = [2 * x**3 - 3 * x**2 + 1, x**3 - 2 * x**2 + x, -2 * x**3 + 3 * x**2, x**3 - x**2]
    assert np.allclose(cur.at(0.3 + x * h)[0], hb[0] * pa + hb[1] * h * va + hb[2] * pb + hb[3] * h * vb)
    assert np.allclose(cur.at(0.5)[0], [2.0, 2.0]) and np.allclose(cur.at(0.9)[0], [3.0, 1.0])
    assert np.allclose(cur.at(3.0)[0], [3.0, 1.0]) and np.allclose(cur.at(3.0)[1], 0.0)


def test_stamp_zero_starts_at_arrival_and_points_already_due_are_passed_over():
    """Stamp 0 means the arrival; with a stamp in the past the segment that contains the arrival is used
    (the point before the trajectory is never reached)."""
    P, V = [[0.0, 0.0], [1.0, 1.0], [2.0, 0.0]], [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]
    now = _msg(0.0, [0.1, 0.2, 0.3], P, V)
    cur = executed(now, 4.0, np.array([5.0, 5.0]), np.zeros(2))
    assert np.allclose(cur.at(4.1)[0], P[0]) and np.allclose(cur.at(4.2)[0], P[1])
    late = _msg(1.0, [0.1, 0.2, 0.3], P, V)
    cur = executed(late, 1.15, np.array([5.0, 5.0]), np.zeros(2))
    ref = Spline.hermite(np.array([1.1, 1.2, 1.3]), np.array(P), np.array(V))
    for t in (1.15, 1.18, 1.25, 1.3, 2.0):
        assert np.allclose(cur.at(t)[0], ref.at(t)[0])


@pytest.mark.parametrize(
    ("msg", "why"),
    [
        (_msg(0.0, [0.1], [[1.0, 2.0]], [[0.0, 0.0]], names=()), "empty joint names"),
        (_msg(0.0, [0.1], [[1.0]], [[0.0]], names=("a",)), "1 joint names"),
        (_msg(0.0, [0.1], [[1.0, 2.0]], [[0.0, 0.0]], names=("a", "c")), "'c' is not one of"),
        (JtcMessage(NAMES, 0.0, ()), "empty trajectory"),
        (_msg(1.0, [0.1, 0.2], [[0, 0], [1, 1]], [[0, 0], [0, 0]]), "ends in the past"),
        (_msg(0.0, [0.1, 0.1], [[0, 0], [1, 1]], [[0, 0], [0, 0]]), "not strictly increasing"),
        (_msg(0.0, [0.2, 0.1], [[0, 0], [1, 1]], [[0, 0], [0, 0]]), "not strictly increasing"),
        (_msg(0.0, [0.1, 0.2], [[0, 0], [1, 1]], [[0, 0], [0.5, 0]]), "velocity of the last point of joint 'a'"),
    ],
)
def test_the_controller_rejection_rules(msg, why):
    """Each of the controller's refusals, arriving at t=2 s with the default parameters."""
    got = rejection(msg, NAMES, 2.0, DEFAULT)
    assert got is not None and why in got


def test_nonzero_end_velocity_is_accepted_only_when_allowed_and_sizes_are_checked():
    msg = _msg(0.0, [0.1, 0.2], [[0, 0], [1, 1]], [[0, 0], [0.5, 0]])
    assert rejection(msg, NAMES, 2.0, JtcParameters(allow_nonzero_velocity_at_trajectory_end=True)) is None
    bad = _msg(0.0, [0.1], [[0.0, 0.0]], [[0.0, 0.0, 0.0]])
    assert "3 velocities for 2 joints" in rejection(bad, NAMES, 0.0, DEFAULT)
    swapped = _msg(0.0, [0.1], [[1.0, 2.0]], [[0.0, 0.0]], names=("b", "a"))
    assert rejection(swapped, NAMES, 0.0, DEFAULT) is None
    cur = executed(swapped, 0.0, np.zeros(2), np.zeros(2), joints=NAMES)
    assert np.allclose(cur.at(1.0)[0], [2.0, 1.0])  # in the controller's joint order


def _committed():
    """A committed curve of two earlier steps (knots every 0.02 s, moving) ending on a stop tail."""
    rng = np.random.default_rng(4)
    T = np.round(0.02 * np.arange(11), 12)
    P = np.cumsum(rng.normal(0, 0.01, (11, 2)), axis=0)
    V = rng.normal(0, 0.3, (11, 2))
    V[-1] = 0.0
    return Spline.hermite(T, P, V)


@pytest.mark.parametrize("arrival_after_now", [0.0, 0.003, 0.0199, 0.05])
def test_a_step_message_replays_the_committed_curve_from_any_arrival(arrival_after_now):
    """Whenever the controller takes the message (after it was sent at `now`, before the step's start), what it
    executes until the step's start is the committed curve, the step's points are met, and it ends at rest
    within TAIL_FRACTION of the acceleration limits."""
    committed, now, t = _committed(), 0.031, 0.1
    offsets = 0.02 * np.arange(1, 6)
    vals = committed.state(t)[0] + np.outer(offsets, [0.2, -0.1])
    vel = np.tile([0.2, -0.1], (5, 1))  # the servo model's (the message carries the spline's instead)
    amax = np.array([3.0, 2.0])
    msg = step_message(committed, now, t, (offsets, vals, vel), amax, NAMES)
    assert rejection(msg, NAMES, now, DEFAULT) is None  # ends at rest: the default controller takes it
    arr = now + arrival_after_now
    p0, v0 = committed.state(arr)
    cur = executed(msg, arr, p0, v0)
    ts = np.linspace(arr, t, 200)
    assert np.allclose(cur.at(ts)[0], committed.at(ts)[0], atol=1e-12)
    assert np.allclose(cur.at(t + offsets[:-1])[0], vals[:-1])
    # the step's segments are one cubic spline: velocity and acceleration continuous at its points, the velocity at
    # its start the committed curve's, no acceleration at its end
    e = 1e-7
    for k in range(len(offsets) - 1):
        left, right = cur.at(t + offsets[k] - e), cur.at(t + offsets[k] + e)
        assert np.allclose(left[1], right[1], atol=1e-5) and np.allclose(left[2], right[2], atol=1e-2)
    assert np.allclose(cur.at(t + e)[1], committed.state(t)[1], atol=1e-5)
    assert np.allclose(cur.at(t + offsets[-1] - e)[2], 0.0, atol=1e-2)
    duration, rest = stop_tail(vals[-1], msg.points[-2].velocities, amax, offsets[0])
    assert cur.end == pytest.approx(t + offsets[-1] + duration)
    assert np.allclose(cur.at(cur.end + 1.0)[0], rest) and np.allclose(cur.at(cur.end + 1.0)[1], 0.0)
    tail = np.linspace(t + offsets[-1], cur.end, 50)[1:-1]
    assert np.all(np.abs(cur.at(tail)[2]) <= TAIL_FRACTION * amax + 1e-9)
    assert np.isclose(np.max(np.abs(cur.at(tail)[2]) / amax), TAIL_FRACTION)


def test_a_hold_keeps_the_committed_curve_or_rests():
    """A hold sends the committed curve's knots after now (the controller then executes it unchanged); at rest,
    one point at rest."""
    committed = _committed()
    msg = hold_message(committed, 0.05, 0.02, NAMES)
    cur = executed(msg, 0.05, *committed.state(0.05))
    ts = np.linspace(0.05, 0.3, 100)
    assert np.allclose(cur.at(ts)[0], committed.at(ts)[0], atol=1e-12)
    rest = hold_message(committed, 1.0, 0.02, NAMES)
    assert len(rest.points) == 1 and np.all(rest.points[0].velocities == 0.0)
    assert np.allclose(rest.points[0].positions, committed.positions[-1])


def test_controller_parameters_that_would_not_execute_the_verified_curve_are_named():
    """Interpolation other than splines, a commanded joint the controller lacks, and closed-loop control without
    a velocity state are each refused in one line naming the parameter; the defaults pass."""
    good = {"joints": ["a", "b"], "interpolation_method": "splines", "state_interfaces": ["position", "velocity"]}
    params, why = check_parameters(
        "jtc", good, NAMES
    )  # no release's marker: Humble, whose end-velocity default is true
    assert why == "" and params == JtcParameters(allow_nonzero_velocity_at_trajectory_end=True)
    for change, field in (
        ({"interpolation_method": "none"}, "jtc.interpolation_method"),
        ({"joints": ["a"]}, "jtc.joints: no b"),
        ({"state_interfaces": ["position"]}, "jtc.open_loop_control"),
    ):
        _, why = check_parameters("jtc", {**good, **change}, NAMES)
        assert why.startswith(field) and "\n" not in why
    open_loop = {**good, "state_interfaces": ["position"], "open_loop_control": True}
    assert check_parameters("jtc", open_loop, NAMES)[1] == ""
    params, _ = check_parameters("jtc", {**good, "allow_nonzero_velocity_at_trajectory_end": False}, NAMES)
    assert not params.allow_nonzero_velocity_at_trajectory_end


def _emulate(msg, arrival: float, before: dict, times: np.ndarray) -> np.ndarray:
    """Independent: what the test's JTC emulation (`jtc_core`, trajectory.cpp's sampling with its own polynomial
    solves) commands at `times` after adopting `msg` at `arrival` with the point before the trajectory `before`
    ({p, v, a}), on Humble (the command is the sample at the cycle time)."""
    from jtc_core import Pt, _Trajectory

    pts = [Pt(p.time_from_start, p.positions, p.velocities if p.velocities.size else None) for p in msg.points]
    traj = _Trajectory(pts, msg.stamp)
    traj.set_before(arrival, before)
    return np.array([traj.sample(float(c))["p"] for c in times])


def _before(curve: Spline, t: float) -> dict:
    p, v, a = curve.at(t)
    return {"p": p, "v": v, "a": a}


@pytest.mark.parametrize("lag", [0.0, 0.004, 0.012])
def test_a_step_computed_late_within_the_bound_executes_the_same_curve_whatever_the_lag(lag):
    """A step due at t, computed up to lead - margin late and arriving up to margin after it was sent, read by a
    controller whose state lags by `lag`: what the (independently emulated) controller commands from arrival on
    is, to 1e-12, the curve the bridge verified, and the same for every lateness and arrival: the committed curve
    until t, then the step."""
    # loop time 1 s on (a stamp of 0 would mean "now" to the controller)
    committed, t, lead, margin = _committed().shifted(1.0), 1.16, 0.15, 0.02
    offsets = 0.02 * np.arange(1, 6)
    vals = committed.state(t)[0] + np.outer(offsets, [0.2, -0.1])
    vel = np.tile([0.2, -0.1], (5, 1))
    amax = np.array([3.0, 2.0])
    reference = None
    cycles = 1.0 + np.arange(0.0, 0.6, 0.004)
    for late in np.linspace(0.0, lead - margin, 7):
        now = t - lead + late
        msg = step_message(committed, now, t, (offsets, vals, vel), amax, NAMES)
        assert msg.stamp <= now and rejection(msg, NAMES, now, DEFAULT) is None  # its first point is already due
        verified = executed(msg, now, *state_before(committed, now, lag))
        ts = cycles[cycles >= now]
        expect = verified.at(ts)[0]
        assert np.allclose(expect[ts < t], committed.at(ts[ts < t])[0], atol=1e-12)
        reference = expect[ts >= t - margin] if reference is None else reference
        assert np.allclose(expect[ts >= t - margin], reference, atol=1e-12)  # the same for every lateness
        for arrival in (now, now + margin / 2, now + margin):
            got = _emulate(msg, arrival, _before(committed, arrival - lag), ts[ts >= arrival])
            assert np.allclose(got, verified.at(ts[ts >= arrival])[0], atol=1e-12)


def test_the_state_lag_changes_the_point_before_and_the_model_follows_it():
    """A message whose first point lies after its arrival (as a hold at rest, or a message shaped the old way):
    the controller's lagged state changes what it executes (by more than 1e-6), and the model with `state_before`
    predicts the emulated controller to 1e-12 for each lag."""
    committed, now = _committed(), 0.031
    keep = committed.times > now
    T = committed.times[keep]
    msg = JtcMessage.from_arrays(NAMES, T[0], T - T[0], committed.positions[keep], np.array(committed.velocities)[keep])
    ts = np.arange(now, 0.25, 0.002)
    runs = {}
    for lag in (0.0, 0.004, 0.012):
        got = _emulate(msg, now, _before(committed, now - lag), ts)
        model = executed(msg, now, *state_before(committed, now, lag)).at(ts)[0]
        assert np.allclose(got, model, atol=1e-12)
        runs[lag] = got
    assert np.allclose(runs[0.0], committed.at(ts)[0], atol=1e-12)
    assert np.max(np.abs(runs[0.012] - runs[0.0])) > 1e-6


def test_a_due_knot_at_controller_clock_zero_is_not_sent_as_stamp_zero():
    """The committed knot due at the send time lies at controller clock 0 (ROS sim time starts there): a message
    stamped 0 would start "now" instead, so the message starts at the next knot, its stamp non-zero, and the
    model's executed curve (the point before the trajectory used) is still the committed curve."""
    committed = _committed()  # knots every 0.02 s from loop time 0
    epoch, now, t = 0.0, 0.031, 0.1
    plain = step_message(
        committed, now, t, (0.02 * np.arange(1, 3), np.zeros((2, 2)), np.zeros((2, 2))), np.ones(2), NAMES
    )
    assert plain.stamp == pytest.approx(0.02)  # the last knot at or before now
    shifted = committed.shifted(-0.02)  # now the due knot is at clock time 0
    pts = (0.02 * np.arange(1, 3), np.zeros((2, 2)), np.zeros((2, 2)))
    msg = step_message(shifted, now - 0.02, t - 0.02, pts, np.ones(2), NAMES, epoch)
    assert msg.stamp + epoch != 0.0 and msg.stamp == pytest.approx(0.02)
    cur = executed(msg, now - 0.02, *shifted.state(now - 0.02), epoch=epoch)
    ts = np.linspace(now - 0.02, t - 0.02, 50)
    assert np.allclose(cur.at(ts)[0], shifted.at(ts)[0], atol=1e-12)
