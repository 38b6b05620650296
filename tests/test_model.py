"""The symbolic model against the paper's closed forms, finite differences and invariants."""

from __future__ import annotations

import ast
import math
import sys
import threading
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import PROBLEMS, calls_of
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot, Segment

XI = 2 * math.pi / 3


# ---------------------------------------------------------------- independent paper forms
def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def paper_segment(theta: float, phi: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1 (tip position) and eq. 7 (rotation), in the paper's singular theta/phi form."""
    p = (
        length
        / theta
        * np.array([(1 - math.cos(theta)) * math.cos(phi), (1 - math.cos(theta)) * math.sin(phi), math.sin(theta)])
    )
    R = rot_z(phi) @ rot_y(theta) @ rot_z(-phi)
    return p, R


def paper_chain(thetas, phis, lengths, z):
    """Chain the segments (eq. 7): tip position and rotation in the world frame."""
    R = np.eye(3)
    o = np.array([0.0, 0.0, z])
    for th, ph, L in zip(thetas, phis, lengths, strict=False):
        p, Rk = paper_segment(th, ph, L)
        o = o + R @ p
        R = R @ Rk
    return o, R


def paper_cables(theta, phi, L, r, phase=0.0):
    """Eq. 4: q_i = L - r theta cos(phi + (i-1) xi) (cable 1 at angle `phase`)."""
    return np.array([L - r * theta * math.cos(phi + phase + i * XI) for i in range(3)])


def paper_theta_phi(q, L, r):
    """Eq. 2-3 with q relative to L."""
    d = np.asarray(q) - L
    q1, q2, q3 = d
    theta = 2 * math.sqrt(q1**2 + q2**2 + q3**2 - q1 * q2 - q2 * q3 - q1 * q3) / (3 * r)
    phi = math.atan2(math.sqrt(3) * (q2 - q3), q2 + q3 - 2 * q1)
    return theta, phi


def two_seg(coupling: float = 0.0, phase2: float = 0.0) -> Robot:
    return Robot("t", 2.5, (Segment(200.0), Segment(150.0, cable_phase=phase2)), (-150.0, 100.0), coupling)


def config(thetas, phis, z):
    x = []
    for th, ph in zip(thetas, phis, strict=False):
        x += [th * math.cos(ph), th * math.sin(ph)]
    return np.array([*x, z])


POSES = [
    ((0.7, 1.3), (0.4, -2.0), -30.0),
    ((2.5, 0.2), (-3.0, 1.0), 50.0),
    ((0.05, 3.0), (1.0, 0.3), 0.0),
    ((1.0, 1.0), (0.0, math.pi), -100.0),
]


# ----------------------------------------------------------------------------- FK
@pytest.mark.parametrize("thetas,phis,z", POSES)
def test_fk_matches_paper_closed_form_uncoupled(thetas, phis, z):
    robot = two_seg(0.0)
    m = Model(robot)
    x = config(thetas, phis, z)
    p_ref, R_ref = paper_chain(thetas, phis, [200.0, 150.0], z)
    T = m.frame(x)
    np.testing.assert_allclose(m.tip_position(x), p_ref, atol=1e-9)
    np.testing.assert_allclose(T[:3, 3], p_ref, atol=1e-9)
    np.testing.assert_allclose(T[:3, :3], R_ref, atol=1e-12)


@pytest.mark.parametrize("thetas,phis,z", POSES)
def test_coupling_minus_one_is_paper_eq_10_11(thetas, phis, z):
    """c = -1 reproduces the magnitude (eq. 10) and angle (eq. 11) of the coupled proximal segment.

    Eq. 8 with equal K_B in both segments gives M_k = K_B theta_k; with K_B = 1 eq. 10 reads
    theta_bar_1^2 = theta_1^2 + theta_2^2 + 2 theta_1 theta_2 cos(phi_1 - phi_2 + pi). The paper's eq. 11 adds
    pi/2 to the atan2: that is its convention for phi (measured from the y axis in its Fig. 2); ours is measured
    from x, so we compare the atan2 without that offset.
    """
    robot = two_seg(-1.0)
    m = Model(robot)
    x = config(thetas, phis, z)
    (t1, t2), (p1, p2) = thetas, phis
    theta_bar = math.sqrt(t1**2 + t2**2 + 2 * t1 * t2 * math.cos(p1 - p2 + math.pi))
    phi_bar = math.atan2(
        t1 * math.sin(p1) + t2 * math.sin(p2 - math.pi), t1 * math.cos(p1) + t2 * math.cos(p2 - math.pi)
    )
    ub = np.asarray(m.bending(x)).ravel()
    assert np.hypot(ub[0], ub[1]) == pytest.approx(theta_bar, abs=1e-12)
    if theta_bar > 1e-9:
        assert math.atan2(ub[1], ub[0]) == pytest.approx(phi_bar, abs=1e-12)
    np.testing.assert_allclose(ub[2:], [t2 * math.cos(p2), t2 * math.sin(p2)], atol=1e-12)
    # and the geometry uses the coupled bending
    p_ref, R_ref = paper_chain([theta_bar, t2], [phi_bar, p2], [200.0, 150.0], z)
    np.testing.assert_allclose(m.tip_position(x), p_ref, atol=1e-9)
    np.testing.assert_allclose(m.frame(x)[:3, :3], R_ref, atol=1e-12)


@pytest.mark.parametrize("c", [0.0, -1.0, 0.5])
def test_coupling_recursion(c):
    """u_bar[k-1] = u[k-1] + c u_bar[k] for a three-segment robot."""
    robot = Robot("t3", 2.0, (Segment(100.0), Segment(80.0), Segment(60.0)), (0.0, 10.0), c)
    x = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6, 3.0])
    ub = robot.bending(x)
    u = x[:6].reshape(3, 2)
    expected = np.zeros((3, 2))
    expected[2] = u[2]
    expected[1] = u[1] + c * expected[2]
    expected[0] = u[0] + c * expected[1]
    np.testing.assert_allclose(ub, expected, atol=1e-15)
    np.testing.assert_allclose(np.asarray(Model(robot).bending(x)).ravel(), expected.ravel(), atol=1e-15)


def test_three_segment_fk_matches_chain():
    robot = Robot("t3", 2.0, (Segment(100.0), Segment(80.0), Segment(60.0)), (0.0, 10.0), 0.0)
    m = Model(robot)
    thetas, phis = (0.5, 1.5, 2.5), (0.1, -1.2, 2.9)
    x = config(thetas, phis, 5.0)
    p_ref, _ = paper_chain(thetas, phis, [100.0, 80.0, 60.0], 5.0)
    np.testing.assert_allclose(m.tip_position(x), p_ref, atol=1e-9)


# ---------------------------------------------------------------------- cables
@pytest.mark.parametrize("phase2", [0.0, math.pi / 3])
@pytest.mark.parametrize("thetas,phis,z", POSES)
def test_cables_match_eq_4_and_invert_by_eq_2_3(thetas, phis, z, phase2):
    robot = two_seg(-1.0, phase2)
    m = Model(robot)
    x = config(thetas, phis, z)
    q = m.cables(x)
    ref = np.concatenate(
        [
            paper_cables(thetas[0], phis[0], 200.0, 2.5),
            paper_cables(thetas[1], phis[1], 150.0, 2.5, phase2),
            [z],
        ]
    )
    np.testing.assert_allclose(q, ref, atol=1e-12)
    np.testing.assert_allclose(np.asarray(m.config_to_cables(x)).ravel(), ref, atol=1e-12)
    # round trip, numpy and CasADi
    np.testing.assert_allclose(m.config(q), x, atol=1e-12)
    np.testing.assert_allclose(np.asarray(m.cables_to_config(q)).ravel(), x, atol=1e-12)
    # eq. 2-3 recover theta, phi of segment 1 (cable 1 at angle 0)
    th, ph = paper_theta_phi(q[:3], 200.0, 2.5)
    assert th == pytest.approx(thetas[0], abs=1e-12)
    if thetas[0] > 1e-9:
        assert math.cos(ph - phis[0]) == pytest.approx(1.0, abs=1e-12)


def test_cable_jacobian_is_eq_6():
    robot = two_seg(0.0)
    m = Model(robot)
    theta, phi = 0.9, 2.2
    x = config((theta, 0.3), (phi, 0.1), 0.0)
    Jq = np.asarray(m.jac_cables(x))
    # chain rule from x to Phi = (theta, phi): du/dPhi
    du = np.array([[math.cos(phi), -theta * math.sin(phi)], [math.sin(phi), theta * math.cos(phi)]])
    J_phi = Jq[:3, :2] @ du
    r = 2.5
    eq6 = np.array([[-r * math.cos(phi + i * XI), r * theta * math.sin(phi + i * XI)] for i in range(3)])
    np.testing.assert_allclose(J_phi, eq6, atol=1e-12)
    assert Jq[-1, -1] == 1.0 and np.all(Jq[:3, 2:] == 0)


def test_inconsistent_cables_use_least_squares():
    """Adding the same length to all three cables of a segment does not bend it (eq. 2-3 ignore it)."""
    robot = two_seg(0.0)
    x = config((0.4, 0.8), (0.5, -1.0), 10.0)
    q = robot.cables(x)
    q[:3] += 1.7
    np.testing.assert_allclose(robot.config(q), x, atol=1e-12)


# ------------------------------------------------------------------- Jacobians
@pytest.mark.parametrize("c", [0.0, -1.0])
def test_task_jacobian_matches_central_differences(c):
    m = Model(two_seg(c))
    rng = np.random.default_rng(3)
    for _ in range(5):
        x = np.r_[rng.uniform(-1.5, 1.5, 4), rng.uniform(-100, 80)]
        J = m.jacobian(x)
        h = 1e-6
        fd = np.zeros((3, 5))
        for i in range(5):
            e = np.zeros(5)
            e[i] = h
            fd[:, i] = (m.tip_position(x + e) - m.tip_position(x - e)) / (2 * h)
        np.testing.assert_allclose(J, fd, atol=1e-5, rtol=1e-6)


def test_straight_pose_value_gradient_hessian_finite(model):
    x = ca.SX.sym("x", model.nx)
    tip = model.tip(x)
    pts = model.backbone(x)
    f = ca.sumsqr(tip) + ca.sumsqr(pts)
    F = ca.Function("F", [x], [f, ca.gradient(f, x), ca.hessian(f, x)[0], ca.jacobian(tip, x)])
    for z in (0.0, -50.0):
        x0 = np.zeros(model.nx)
        x0[-1] = z
        for out in F(x0):
            a = np.asarray(out, dtype=float)
            assert np.all(np.isfinite(a)), a
        # straight robot: tip straight above the base
        np.testing.assert_allclose(model.tip_position(x0), [0, 0, z + 400.0], atol=1e-12)


def test_straight_pose_jacobian_closed_form():
    """At the straight pose, d tip / d u for an uncoupled robot is known in closed form.

    Bending segment 1 by a small u_x moves its tip by L1 u_x / 2 and tilts segment 2 by u_x, which moves the
    tip by L2 u_x more: d p_x / d u1x = L1/2 + L2. Bending segment 2 moves the tip by L2/2.
    """
    m = Model(two_seg(0.0))
    J = m.jacobian(np.zeros(5))
    np.testing.assert_allclose(J[:, 0], [200.0 / 2 + 150.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(J[:, 1], [0, 200.0 / 2 + 150.0, 0], atol=1e-9)
    np.testing.assert_allclose(J[:, 2], [150.0 / 2, 0, 0], atol=1e-9)
    np.testing.assert_allclose(J[:, 4], [0, 0, 1.0], atol=1e-12)


def test_series_branch_is_continuous():
    """Either side of the series/exact switch (theta^2 = 1e-2) the FK agrees to round-off."""
    m = Model(two_seg(0.0))
    th = math.sqrt(1e-2)
    for eps in (1e-9, 1e-7):
        a = m.tip_position(config((th - eps, 0.5), (0.3, 0.0), 0.0))
        b = m.tip_position(config((th + eps, 0.5), (0.3, 0.0), 0.0))
        ref_a, _ = paper_chain((th - eps, 0.5), (0.3, 0.0), (200.0, 150.0), 0.0)
        ref_b, _ = paper_chain((th + eps, 0.5), (0.3, 0.0), (200.0, 150.0), 0.0)
        assert np.linalg.norm(a - b) < 2 * 350 * eps + 1e-9
        np.testing.assert_allclose(a, ref_a, atol=1e-10)
        np.testing.assert_allclose(b, ref_b, atol=1e-10)


# ---------------------------------------------------------------- properties
angles = st.floats(-math.pi, math.pi)
thetas = st.floats(0.0, math.pi)


@settings(max_examples=60, deadline=None)
@given(t1=thetas, t2=thetas, p1=angles, p2=angles, z=st.floats(-150, 100))
def test_properties_random_configurations(model, t1, t2, p1, p2, z):
    x = config((t1, t2), (p1, p2), z)
    T = model.frame(x)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    pts = model.points(x)
    np.testing.assert_allclose(pts[0], [0, 0, z], atol=1e-12)
    np.testing.assert_allclose(pts[-1], T[:3, 3], atol=1e-9)
    # chords never exceed the arc length between evenly spread points
    spacing = model.robot.total_length / (model.n_points - 1)
    assert np.all(np.linalg.norm(np.diff(pts, axis=0), axis=1) <= spacing + 1e-9)
    # tip inside the ball of radius total length around the base
    assert np.linalg.norm(T[:3, 3] - [0, 0, z]) <= model.robot.total_length + 1e-9
    # the coupled bending is what the geometry uses: compare with the chain of eq. 1/7
    ub = model.robot.bending(x)
    th = np.linalg.norm(ub, axis=1)
    if np.all(th > 1e-6):
        ph = np.arctan2(ub[:, 1], ub[:, 0])
        p_ref, R_ref = paper_chain(th, ph, [200.0, 200.0], z)
        np.testing.assert_allclose(T[:3, 3], p_ref, atol=1e-7)
        np.testing.assert_allclose(R, R_ref, atol=1e-9)


def test_batch_equals_single(model):
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-1, 1, (50, 4)), rng.uniform(-150, 100, 50)]
    P = model.points(X)
    tips = model.tip_position(X)
    J = model.jacobian(X)
    F = model.frame(X)
    for i in (0, 17, 49):
        np.testing.assert_array_equal(P[i], model.points(X[i]))
        np.testing.assert_array_equal(tips[i], model.tip_position(X[i]))
        np.testing.assert_array_equal(J[i], model.jacobian(X[i]))
        np.testing.assert_array_equal(F[i], model.frame(X[i]))
    dense = model.points(X[:3], 101)
    assert dense.shape == (3, 101, 3)
    np.testing.assert_allclose(dense[:, -1], tips[:3], atol=1e-9)


def test_limits_function_matches_numpy(model):
    rng = np.random.default_rng(1)
    lbg, ubg = model.limit_bounds()
    for _ in range(20):
        x = np.r_[rng.uniform(-7, 7, 4), rng.uniform(-250, 150)]
        g = np.asarray(model.limits(x)).ravel()
        inside_g = np.all(g <= ubg + 1e-9) and np.all(g >= lbg - 1e-9)
        lo, hi = model.robot.config_box()
        inside = inside_g and lo[-1] <= x[-1] <= hi[-1]
        assert inside == (model.robot.limit_violation(x)[0] <= 1e-9)


def test_wrong_shape_is_an_input_error(model):
    from crtraj.core.errors import InputError

    with pytest.raises(InputError, match="x: expected shape"):
        model.tip_position(np.zeros(4))
    with pytest.raises(InputError, match="NaN"):
        model.points(np.full(5, np.nan))


# Layers, low to high (DESIGN.md); a module may import only its own layer and those below.
_LAYERS = ("core", "model", "world", "planning", "control", "hardware", "io", "viz", "bench", "app")


@pytest.mark.parametrize("package", ["model", "world"])
def test_model_and_world_import_nothing_above_them_and_nothing_inside_functions(package):
    root = Path(__file__).resolve().parent.parent / "crtraj"
    allowed = set(_LAYERS[: _LAYERS.index(package) + 1])
    for path in sorted((root / package).glob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inner = [n for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom))]
                assert not inner, f"{path.name}:{inner[0].lineno if inner else 0}: import inside {node.name}()"
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                parts = name.split(".")
                if parts[0] == "crtraj" and len(parts) > 1:
                    assert parts[1] in allowed, f"{path.name}:{node.lineno}: {package} imports {name} (a higher layer)"


@pytest.mark.parametrize("name", ["cdsr1", "cdsr2", "cdsr3", "cdsr4"])
def test_segment_points_pick_every_backbone_point(name):
    """The point at a symbolic fraction of each segment (what the replanner's QP selects points by) is,
    at each backbone point's (segment, fraction), that backbone point; a straight robot's is a closed form."""
    m = Model(load_robot(PROBLEMS / "robots" / f"{name}.toml"))
    seg_fn = m.segment_point_function()
    rng = np.random.default_rng(3)
    for n in (2, 7, 16):
        seg, frac = m.arc_segments(m.arc_positions(n))
        assert seg[0] == 0 and frac[0] == 0.0 and seg[-1] == m.robot.n_segments - 1 and frac[-1] == 1.0
        for _ in range(5):
            x = np.append(rng.uniform(-0.8, 0.8, m.nx - 1), rng.uniform(-50.0, 50.0))
            P = m.points(x, n)
            cols = [np.asarray(seg_fn(x, f)).reshape(3, -1, order="F")[:, k] for k, f in zip(seg, frac, strict=True)]
            Q = np.array(cols)
            np.testing.assert_allclose(Q, P, rtol=0, atol=1e-9)
    # straight (no bending): fraction f of segment k is z + (start_k + f L_k) up the axis
    z = 12.5
    x = np.append(np.zeros(m.nx - 1), z)
    starts = np.cumsum([0.0] + [s.length for s in m.robot.segments])
    for f in (0.0, 0.3, 1.0):
        Q = np.asarray(seg_fn(x, f)).reshape(3, -1, order="F")
        want = [[0.0, 0.0, z + starts[k] + f * s.length] for k, s in enumerate(m.robot.segments)]
        np.testing.assert_allclose(Q.T, want, atol=1e-12)


# ---------------------------------------------------------------- threads (the loop's and a live view's)
def _on_another_thread(fn) -> None:
    th = threading.Thread(target=fn)
    th.start()
    th.join(60.0)
    assert not th.is_alive()


def test_another_threads_batch_sizes_leave_this_threads_evaluation_work_unchanged(model):
    """A live view evaluates the loop's model on its own thread with batches of every size: this thread's next
    evaluation makes exactly the calls it made before (its evaluators are neither evicted nor rebuilt), and
    both threads' results are the model's own CasADi function's."""
    m = Model(model.robot)
    x = np.linspace(-0.4, 0.4, m.nx)
    m.tip_position(x)  # builds this thread's evaluator
    before = calls_of(lambda: m.tip_position(x))
    seen = {}
    _on_another_thread(lambda: seen.update({n: m.tip_position(np.tile(x, (n, 1))) for n in range(2, 80)}))
    assert calls_of(lambda: m.tip_position(x)) == before
    expected = np.asarray(m.tip(x)).ravel()
    np.testing.assert_allclose(m.tip_position(x), expected, atol=1e-12)
    for n, tips in seen.items():
        np.testing.assert_allclose(tips, np.tile(expected, (n, 1)), atol=1e-12)


def test_an_evaluation_on_another_thread_between_set_res_and_the_call_leaves_this_result_right(model):
    """The interleaving a live view can cause, forced: right after this thread has pointed its evaluation buffer
    at its argument and result, another thread evaluates the same function at another configuration; this
    thread's call still writes its own tip (a shared buffer would have written the other's into the other's
    array and left this result unwritten)."""
    m = Model(model.robot)
    x, y = np.full(m.nx, 0.3), np.full(m.nx, -0.2)
    other = []
    m.tip_position(x)
    m.tip_position(y)

    def hook(frame, event, arg):
        if event == "return" and frame.f_code.co_name == "set_res" and not other:
            other.append(None)  # once
            _on_another_thread(lambda: other.append(m.tip_position(y)))

    sys.setprofile(hook)
    try:
        got = m.tip_position(x)
    finally:
        sys.setprofile(None)
    assert len(other) == 2, "the forced interleaving did not happen"
    np.testing.assert_allclose(got, np.asarray(m.tip(x)).ravel(), atol=1e-12)
    np.testing.assert_allclose(other[1], np.asarray(m.tip(y)).ravel(), atol=1e-12)
