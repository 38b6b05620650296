"""Scene: obstacle states against closed forms, clearance against brute force, swept bounds, packing, TOML."""

from __future__ import annotations

import math
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import Problem
from crtraj.world import margin, packing
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import DEFAULT_WORKSPACE, Scene

ROOT = Path(__file__).resolve().parent.parent


def paper_dynamic_scene(a: float = 0.5, b: float = 0.3) -> Scene:
    """Simulation 2: radii 60 + 10 sin(a t) and 45 + 15 cos(b t)."""
    return Scene(
        obstacles=(
            Obstacle(center=(0, 90, 330), radius=60, amplitude=10, omega=a, phase=0.0, name="upper"),
            Obstacle(center=(-10, -70, 250), radius=45, amplitude=15, omega=b, phase=math.pi / 2, name="lower"),
        )
    )


def moving_scene() -> Scene:
    return Scene(
        obstacles=(
            Obstacle(center=(0, 0, 200), radius=30, to=(60, 0, 200), duration=4.0, profile="linear", name="lin"),
            Obstacle(
                center=(0, 50, 300), radius=20, amplitude=5, omega=1.0, to=(0, 50, 380), duration=3.0, profile="cos"
            ),
            Obstacle(
                center=(50, 50, 100),
                radius=25,
                amplitude=-10,
                omega=2.0,
                phase=0.3,
                to=(50, -30, 100),
                duration=2.0,
                profile="sin",
            ),
        ),
        safety_distance=4.0,
    )


def brute_clearance(points: np.ndarray, centers: np.ndarray, radii: np.ndarray, inflate: float, dsf: float) -> float:
    """Independent double loop over points and obstacles (plain Python math)."""
    best = math.inf
    for p in points:
        for c, r in zip(centers, radii, strict=True):
            d = math.sqrt(sum((float(p[k]) - float(c[k])) ** 2 for k in range(3)))
            best = min(best, d - float(r) - inflate - dsf)
    return best


# ------------------------------------------------------------------ states
def test_paper_radii_closed_form():
    a, b = 0.5, 0.3
    scene = paper_dynamic_scene(a, b)
    for t in [0.0, 0.7, 2.0, 5.5, 13.0]:
        centers, radii = scene.states(t)
        assert radii[0] == pytest.approx(60 + 10 * math.sin(a * t), abs=1e-12)
        assert radii[1] == pytest.approx(45 + 15 * math.cos(b * t), abs=1e-12)
        np.testing.assert_allclose(centers, [[0, 90, 330], [-10, -70, 250]])


def test_motion_profiles_closed_form():
    scene = moving_scene()
    c0 = np.array([o.center for o in scene.obstacles])
    to = np.array([o.to for o in scene.obstacles])
    # linear (D = 4): s = clip(t/4); cos (D = 3): s = (1 - cos(pi t/3))/2, at `to` for t = 3;
    # sin (D = 2): s = sin(pi t/4), at `to` for t = 2 and at the mirror point 2 c0 - to for t = 6
    s_by_t = {
        0.0: (0.0, 0.0, 0.0),
        2.0: (0.5, 0.75, 1.0),
        3.0: (0.75, 1.0, math.sqrt(0.5)),
        4.0: (1.0, 0.75, 0.0),
        6.0: (1.0, 0.0, -1.0),
        9.0: (1.0, 1.0, math.sqrt(0.5)),
    }
    cases = {t: [c0[k] + s[k] * (to[k] - c0[k]) for k in range(3)] for t, s in s_by_t.items()}
    for t, want in cases.items():
        centers, _ = scene.states(t)
        np.testing.assert_allclose(centers, np.array(want), atol=1e-9, err_msg=f"t={t}")


def test_states_vectorised_matches_scalar():
    scene = moving_scene()
    ts = np.linspace(-1.0, 12.0, 37).reshape(37)
    C, R = scene.states(ts)
    assert C.shape == (37, 3, 3) and R.shape == (37, 3)
    for k, t in enumerate(ts):
        c, r = scene.states(float(t))
        np.testing.assert_allclose(C[k], c, atol=1e-12)
        np.testing.assert_allclose(R[k], r, atol=1e-12)
    C2, R2 = scene.states(ts.reshape(37, 1, 1))
    assert C2.shape == (37, 1, 1, 3, 3) and R2.shape == (37, 1, 1, 3)


def test_speed_bounds_match_finite_differences():
    scene = moving_scene()
    ts = np.linspace(0.0, 20.0, 200001)
    C, R = scene.states(ts)
    dt = ts[1] - ts[0]
    v = np.linalg.norm(np.diff(C, axis=0), axis=-1).max(axis=0) / dt
    rdot = np.abs(np.diff(R, axis=0)).max(axis=0) / dt
    vb, rb = scene.speed_bounds()
    assert np.all(v <= vb + 1e-6) and np.allclose(v, vb, rtol=1e-3)
    assert np.all(rdot <= rb + 1e-6) and np.allclose(rdot, rb, rtol=1e-3)
    np.testing.assert_allclose(vb, [15.0, 80 * math.pi / 6, 80 * math.pi / 4])
    np.testing.assert_allclose(rb, [0.0, 5.0, 20.0])


def test_time_shift():
    scene = moving_scene()
    shifted = scene.with_time_shift(2.5)
    for t in [0.0, 1.0, 3.3]:
        for a, b in zip(shifted.states(t), scene.states(t + 2.5), strict=True):
            np.testing.assert_allclose(a, b, atol=1e-12)
    again = Scene.from_table(Table(shifted.to_dict(), "scene"))
    np.testing.assert_allclose(again.states(1.0)[0], scene.states(3.5)[0], atol=1e-12)


# --------------------------------------------------------------- clearance
def test_clearance_points_matches_brute_force():
    scene = moving_scene()
    rng = np.random.default_rng(3)
    pts = rng.uniform([-100, -100, 0], [150, 150, 450], size=(6, 9, 3))
    for t in [0.0, 1.3, 7.0]:
        got = scene.clearance_points(pts, t, inflate=2.0)
        assert got.shape == (6,)
        c, r = scene.states(t)
        want = [brute_clearance(pts[k], c, r, 2.0, scene.safety_distance) for k in range(6)]
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_clearance_points_time_broadcast():
    scene = moving_scene()
    rng = np.random.default_rng(4)
    pts = rng.uniform(-100, 300, size=(5, 4, 3))
    ts = np.array([0.0, 0.5, 1.0, 2.0, 3.5])
    got = scene.clearance_points(pts, ts)
    want = [scene.clearance_points(pts[k], ts[k]) for k in range(5)]
    np.testing.assert_allclose(got, want, atol=1e-12)
    # one point set seen at many times
    many = scene.clearance_points(pts[0], ts)
    np.testing.assert_allclose(many, [scene.clearance_points(pts[0], t) for t in ts], atol=1e-12)


def test_clearance_of_configurations_uses_body_radius(model):
    scene = paper_dynamic_scene()
    rng = np.random.default_rng(5)
    lo, hi = model.robot.config_box()
    X = rng.uniform(lo * 0.3, hi * 0.3, size=(7, model.nx))
    got = scene.clearance(model, X, 1.0)
    pts = model.points(X)
    c, r = scene.states(1.0)
    want = [brute_clearance(pts[k], c, r, model.robot.body_radius, 5.0) for k in range(7)]
    np.testing.assert_allclose(got, want, atol=1e-9)
    single = scene.clearance(model, X[0], 1.0)
    assert np.ndim(single) == 0 and float(single) == pytest.approx(want[0])
    dense = scene.clearance(model, X, 1.0, n_points=199)
    assert np.all(dense <= got + 1e-9)  # 199 evenly spread points contain the 10 (9 divides 198)


def test_empty_scene_is_infinitely_clear(model):
    scene = Scene()
    assert scene.n_obstacles == 0
    assert np.isinf(scene.clearance_points(np.zeros((3, 4, 3)), 0.0)).all()
    assert np.isinf(scene.clearance_over(model, model.robot.straight(), 0.0, 1.0))
    np.testing.assert_array_equal(packing.unpack(scene.pack(0.0, 2))[2], [0, 0])


def test_bad_points_and_times_raise():
    scene = moving_scene()
    with pytest.raises(InputError, match="points"):
        scene.clearance_points(np.zeros((4, 2)), 0.0)
    with pytest.raises(InputError, match="points"):
        scene.clearance_points(np.full((2, 3), np.nan), 0.0)
    with pytest.raises(InputError, match="t: "):
        scene.states(float("nan"))


# ------------------------------------------------------ swept lower bound
obstacle_st = st.builds(
    lambda c, A, frac, w, p, d, dur, prof, moving: Obstacle(
        center=tuple(c),
        radius=A,
        amplitude=frac * A,
        omega=w,
        phase=p,
        to=tuple(np.add(c, d)) if moving else None,
        duration=dur,
        profile=prof,
    ),
    st.lists(st.floats(-100, 100), min_size=3, max_size=3),
    st.floats(5, 60),
    st.floats(-1, 1),
    st.floats(-3, 3),
    st.floats(-math.pi, math.pi),
    st.lists(st.floats(-80, 80), min_size=3, max_size=3),
    st.floats(0.2, 6),
    st.sampled_from(["linear", "sin", "cos"]),
    st.booleans(),
)


@settings(max_examples=60, deadline=None)
@given(
    obstacles=st.lists(obstacle_st, min_size=1, max_size=3),
    t0=st.floats(-2, 10),
    dt=st.floats(0, 4),
    seed=st.integers(0, 2**31 - 1),
    origin=st.floats(-5, 5),
)
def test_clearance_over_is_a_lower_bound(obstacles, t0, dt, seed, origin):
    scene = Scene(obstacles=tuple(obstacles), safety_distance=3.0, time_origin=origin)
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-200, 200, size=(4, 6, 3))
    t1 = t0 + dt
    bound = scene.clearance_points_over(pts, t0, t1, inflate=1.5)
    ts = np.linspace(t0, t1, 801)
    dense = np.stack([scene.clearance_points(pts, t, inflate=1.5) for t in ts]).min(axis=0)
    assert np.all(bound <= dense + 1e-9)
    # at least as strong as the paper's check at both ends
    assert np.all(bound <= scene.clearance_points(pts, t0, inflate=1.5) + 1e-12)
    assert np.all(bound <= scene.clearance_points(pts, t1, inflate=1.5) + 1e-12)
    # exact radius range against dense sampling
    rlo, rhi = scene.radius_range(t0, t1)
    _, R = scene.states(ts)
    assert np.all(rhi >= R.max(axis=0) - 1e-9) and np.allclose(rhi, R.max(axis=0), atol=1e-3 * (1 + dt))
    assert np.all(rlo <= R.min(axis=0) + 1e-9) and np.allclose(rlo, R.min(axis=0), atol=1e-3 * (1 + dt))


def test_clearance_over_is_tight_for_static_obstacles(model):
    scene = Scene(obstacles=(Obstacle(center=(0, 90, 330), radius=65),))
    rng = np.random.default_rng(8)
    lo, hi = model.robot.config_box()
    X = rng.uniform(lo * 0.3, hi * 0.3, size=(5, model.nx))
    np.testing.assert_allclose(scene.clearance_over(model, X, 0.0, 3.0), scene.clearance(model, X, 1.0), atol=1e-9)


def test_clearance_over_sees_motion_between_the_ends():
    # the obstacle passes through the point and comes back: both ends are clear,
    # the swept bound is not
    ob = Obstacle(center=(0, 0, 0), radius=10, to=(100, 0, 0), duration=1.0, profile="cos")
    scene = Scene(obstacles=(ob,), safety_distance=0.0)
    pt = np.array([[[100.0, 0.0, 0.0]]])
    assert scene.clearance_points(pt, 0.0)[0] == pytest.approx(90.0)
    assert scene.clearance_points(pt, 2.0)[0] == pytest.approx(90.0)
    assert scene.clearance_points_over(pt, 0.0, 2.0)[0] == pytest.approx(-10.0)


# ---------------------------------------------------------------- packing
def test_pack_layout_and_padding_is_inert():
    scene = moving_scene()
    packed = scene.pack(1.7, 6)
    assert packed.shape == (6 * packing.WIDTH,)
    centers, radii, active = packing.unpack(packed)
    c, r = scene.states(1.7)
    np.testing.assert_allclose(centers[:3], c)
    np.testing.assert_allclose(radii[:3], r)
    np.testing.assert_array_equal(active, [1, 1, 1, 0, 0, 0])
    # treating every slot as a real obstacle (ignoring the flag) changes nothing near the robot
    rng = np.random.default_rng(9)
    pts = rng.uniform(-600, 600, size=(20, 10, 3))
    padded = Scene(
        obstacles=tuple(Obstacle(center=tuple(cc), radius=float(rr)) for cc, rr in zip(centers, radii, strict=True)),
        safety_distance=scene.safety_distance,
    )
    np.testing.assert_allclose(padded.clearance_points(pts, 0.0), scene.clearance_points(pts, 1.7), atol=1e-9)
    # and the eq. 18 penalty of a padding slot is negligible
    d2 = np.sum((pts.reshape(-1, 3) - centers[5]) ** 2, axis=-1)
    assert np.max((0 + 5 + 3) ** 2 / d2) < 1e-10


def test_pack_too_many_obstacles_raises():
    with pytest.raises(InputError, match="at most 2"):
        moving_scene().pack(0.0, 2)


def test_pack_over_encloses_the_swept_volume():
    scene = moving_scene()
    centers, radii, _ = packing.unpack(scene.pack_over(0.5, 2.5, 3))
    C, R = scene.states(np.linspace(0.5, 2.5, 2001))
    reach = np.linalg.norm(C - centers, axis=-1) + R  # farthest surface point from the slot centre
    assert np.all(reach <= radii + 1e-9)


def test_packing_keeps_leading_dims_and_slots_read_back_in_casadi():
    # one row per horizon step, as the replanner packs: (N, m, 3) + (N, m) -> (N, WIDTH * M)
    rng = np.random.default_rng(4)
    c, r = rng.uniform(-100, 100, (7, 2, 3)), rng.uniform(1, 50, (7, 2))
    packed = packing.pack(c, r, 3)
    assert packed.shape == (7, 3 * packing.WIDTH)
    cc, rr, aa = packing.unpack(packed)
    np.testing.assert_array_equal(cc[:, :2], c)
    np.testing.assert_array_equal(rr[:, :2], r)
    np.testing.assert_array_equal(aa, np.tile([1.0, 1.0, 0.0], (7, 1)))
    np.testing.assert_array_equal(cc[:, 2], np.tile(packing.PAD_CENTER, (7, 1)))
    assert np.all(rr[:, 2] == 0.0)
    # the NLPs index a CasADi symbol with `slot`: evaluated, it reads the same numbers as `unpack`
    sym = ca.SX.sym("obs", 3 * packing.WIDTH)
    row = packed[4]
    for i in range(3):
        ci, ri, ai = packing.slot(sym, i)
        got = ca.Function("f", [sym], [ci, ri, ai])(row)
        np.testing.assert_array_equal(np.asarray(got[0]).ravel(), cc[4, i])
        assert float(got[1]) == rr[4, i] and float(got[2]) == aa[4, i]
    np.testing.assert_array_equal(packing.active_flags(row), [True, True, False])
    np.testing.assert_array_equal(packing.padding(2), packing.pack(np.zeros((0, 3)), np.zeros(0), 2))


def test_slot_count_and_capacity():
    assert [packing.slot_count(n) for n in (0, 1, 8, 9, 16, 17)] == [8, 8, 8, 16, 16, 24]
    assert packing.check_capacity(np.int64(3), 3) == 3
    for bad in (True, -1, 2.0):
        with pytest.raises(InputError, match="max_obstacles"):
            packing.check_capacity(bad, 0)
    with pytest.raises(InputError, match="the replanner was built for at most 1"):
        packing.pack(np.zeros((2, 3)), np.zeros(2), 1, "the replanner")


def test_margin_forms_agree_and_match_the_scene_clearance():
    # integers: every form is exact, so the three compositions must agree exactly
    assert margin.inflation(5.0, 3.0, 2.0, 1.0) == 11.0
    assert margin.keep_out_radius(40.0, 5.0, 3.0, 1.0) == 49.0
    assert margin.clearance(20.0, 5.0, 3.0) == 12.0
    # random values: equal up to rounding
    rng = np.random.default_rng(5)
    R, dsf, body, m, d = rng.uniform(0.1, 80.0, (5, 200))
    np.testing.assert_allclose(margin.keep_out_radius(R, dsf, body, m), R + margin.inflation(dsf, body, 0.0, m), 1e-14)
    np.testing.assert_allclose(margin.clearance(d, dsf, body), d - margin.inflation(dsf, body), atol=1e-12)
    # the scene's clearance is |p - c| - R - body - D_sf, brute force
    scene = Scene(obstacles=(Obstacle(center=(10.0, -20.0, 300.0), radius=40.0),), safety_distance=7.5)
    pts = rng.uniform(-200, 200, (50, 1, 3)) + np.array([0.0, 0.0, 300.0])
    dist = np.linalg.norm(pts[:, 0] - [10.0, -20.0, 300.0], axis=-1)
    np.testing.assert_allclose(scene.clearance_points(pts, 0.0, inflate=3.0), dist - 40.0 - 3.0 - 7.5, atol=1e-12)


def test_default_safety_distance_is_the_margin_default():
    assert margin.DEFAULT_SAFETY_DISTANCE == 5.0  # the paper's D_sf
    assert Scene().safety_distance == margin.DEFAULT_SAFETY_DISTANCE
    assert Scene.from_table(Table({}, "scene")).safety_distance == margin.DEFAULT_SAFETY_DISTANCE


# ------------------------------------------------------------- TOML I/O
def test_round_trip_through_table():
    scene = moving_scene()
    again = Scene.from_table(Table(scene.to_dict(), "scene"))
    assert again == scene
    for t in [0.0, 1.1, 5.0]:
        for a, b in zip(again.states(t), scene.states(t), strict=True):
            np.testing.assert_allclose(a, b)


def test_period_is_converted_to_duration():
    def one(profile: str, period: float) -> Obstacle:
        return Scene.from_table(Table(_mo(period=period, profile=profile), "scene")).obstacles[0]

    assert one("cos", 8.0).duration == 4.0
    assert one("sin", 8.0).duration == 2.0


def test_defaults():
    scene = Scene.from_table(Table({}, "scene"))
    assert scene.safety_distance == 5.0 and not hasattr(scene, "time_step")
    lo, hi = scene.workspace
    np.testing.assert_array_equal(lo, DEFAULT_WORKSPACE[0])
    np.testing.assert_array_equal(hi - lo, [300, 300, 500])
    assert scene.in_workspace([[0, 0, 250], [0, 200, 250]]).tolist() == [True, False]


def _ob(**fields) -> dict:
    """A scene table with one obstacle: centre [0,0,0], radius 5 mm, plus/overriding `fields`."""
    ob = {"center": [0, 0, 0], "radius": 5}
    ob.update(fields)
    return {"obstacle": [{k: v for k, v in ob.items() if v is not None}]}


def _mo(**motion) -> dict:
    """A scene table with one moving obstacle (`to` = [1,0,0] plus `motion`)."""
    return _ob(motion={"to": [1, 0, 0], **motion})


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"safety_distance": -1}, "scene.safety_distance"),
        ({"time_step": 0}, "scene.time_step"),
        ({"time_step": 1.0}, "scene.time_step"),
        (_ob(center=[1e308, 0, 0]), "scene.obstacle[0].center[0]"),
        (_ob(center=[0, 0, 10**400]), "scene.obstacle[0].center[2]"),
        (_ob(radius=1e300), "scene.obstacle[0].radius"),
        ({"obstacle": [{"center": [0, 0, 0], "radius": 1}] * 101}, "scene.obstacle"),
        (_mo(duration=1e-300), "scene.obstacle[0].motion.duration"),
        (_ob(radius={"mean": 5, "amplitude": 1, "omega": 1e300}), "scene.obstacle[0].radius.omega"),
        ({"workspace": {"lo": [-1e300, 0, 0], "hi": [1, 1, 1]}}, "scene.workspace.lo[0]"),
        ({"time_origin": 1e300}, "scene.time_origin"),
        ({"colour": "red"}, "scene.colour"),
        ({"workspace": {"lo": [0, 0, 0], "hi": [1, 1]}}, "scene.workspace.hi"),
        ({"workspace": {"lo": [0, 0, 5], "hi": [1, 1, 1]}}, "scene.workspace.hi"),
        ({"workspace": {"lo": [0, 0, 0], "hi": [1, 1, 1], "mid": [0, 0, 0]}}, "scene.workspace.mid"),
        (_ob(center=None), "scene.obstacle[0].center"),
        (_ob(radius=None), "scene.obstacle[0].radius"),
        (_ob(center=[0, 0]), "scene.obstacle[0].center"),
        (_ob(radius=-5), "scene.obstacle[0].radius"),
        (_ob(radius={"mean": 5, "amplitude": 6}), "scene.obstacle[0].radius.amplitude"),
        (_ob(radius={"mean": 5, "freq": 6}), "scene.obstacle[0].radius.freq"),
        (_ob(spin=1), "scene.obstacle[0].spin"),
        (_mo(), "scene.obstacle[0].motion.duration"),
        (_mo(duration=0), "scene.obstacle[0].motion.duration"),
        (_mo(duration=1, profile="zigzag"), "scene.obstacle[0].motion.profile"),
        (_mo(period=2), "scene.obstacle[0].motion.period"),
        (_mo(period=2, duration=1, profile="sin"), "scene.obstacle[0].motion.period"),
        (_mo(duration=1, speed=3), "scene.obstacle[0].motion.speed"),
        ({"obstacle": [{"name": "a", **_ob()["obstacle"][0]}] * 2}, "scene.obstacle"),
        ({"obstacle": {"center": [0, 0, 0], "radius": 5}}, "scene.obstacle"),
    ],
)
def test_toml_errors_name_the_field(data, field):
    with pytest.raises(InputError) as err:
        Scene.from_table(Table(data, "scene"))
    msg = str(err.value)
    assert msg.startswith(field + ":"), msg
    assert "\n" not in msg


@pytest.mark.parametrize("name", ["paper_static", "paper_dynamic", "paper_prototype"])
def test_problem_files_parse(name):
    prob = Problem.load(ROOT / "problems" / f"{name}.toml")
    scene = prob.options(Scene, "scene")
    assert scene.n_obstacles == 2
    task = prob.require_task()
    assert np.all(scene.in_workspace(np.stack([task.start, task.goal])))
    # the task points themselves keep the safety distance at t = 0
    assert np.all(scene.clearance_points(np.stack([task.start, task.goal])[:, None, :], 0.0) > 0)


def test_paper_dynamic_file_matches_the_paper():
    prob = Problem.load(ROOT / "problems" / "paper_dynamic.toml")
    scene = prob.options(Scene, "scene")
    a, b = scene.obstacles[0].omega, scene.obstacles[1].omega
    for t in np.linspace(0, 30, 13):
        _, r = scene.states(t)
        assert r[0] == pytest.approx(60 + 10 * math.sin(a * t))
        assert r[1] == pytest.approx(45 + 15 * math.cos(b * t))
