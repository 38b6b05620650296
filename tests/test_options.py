"""The one options style (crtraj.core.options): declared bounds read from files and checked in Python alike."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import typing
from typing import ClassVar

import casadi as ca
import numpy as np
import pytest

from crtraj.bench.records import BenchOptions
from crtraj.bench.scenarios import ScenarioOptions
from crtraj.control.horizon import MOVED_TO_LOOP, Replanner, ReplanOptions
from crtraj.control.loop import LoopOptions
from crtraj.control.tracking import TrackingController, TrackingOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.options import Options, option
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.planning import BUILTIN
from crtraj.planning.options import CheckOptions, CSpaceOptions, IKOptions, PlannerOptions, RRTOptions
from crtraj.planning.steer import SteerOptions, SteerSolver
from crtraj.viz import ViewOptions
from crtraj.world.feed import FeedOptions

# every options section of the package
SECTION_CLASSES = (
    PlannerOptions,
    IKOptions,
    CheckOptions,
    CSpaceOptions,
    RRTOptions,
    SteerOptions,
    TrackingOptions,
    BenchOptions,
    ScenarioOptions,
    FeedOptions,
    ReplanOptions,
    LoopOptions,
    StreamOptions,
    ViewOptions,
)


@dataclasses.dataclass(frozen=True)
class _Demo(Options):
    SECTION: ClassVar[str] = "demo"

    rate: float = option(2.0, gt=0.0, le=10.0)
    count: int = option(3, ge=1, le=5)
    name: str = option("a", choices=("a", "b"))
    on: bool = option(True)
    cap: float | None = option(None, ge=0.0)
    raw: tuple = option((), read=False)

    @classmethod
    def _read_extra(cls, t: Table) -> dict:
        return {"raw": tuple(t.vec("raw", None, ()))}

    def _check(self) -> None:
        if self.cap is not None and self.cap > self.rate:
            raise InputError("demo.cap: must not exceed demo.rate")


def test_file_and_python_give_the_same_one_line_errors():
    for bad, msg in (
        ({"rate": 0.0}, r"^demo\.rate: must be > 0, got 0$"),
        ({"rate": 11}, r"^demo\.rate: must be <= 10, got 11$"),
        ({"count": 6}, r"^demo\.count: must be <= 5, got 6$"),
        ({"count": 0}, r"^demo\.count: must be >= 1, got 0$"),
        ({"name": "c"}, r"^demo\.name: must be one of a, b; got 'c'$"),
        ({"on": 1}, r"^demo\.on: expected true or false"),
        ({"cap": 3.0}, r"^demo\.cap: must not exceed demo\.rate$"),
    ):
        with pytest.raises(InputError, match=msg):
            _Demo.from_table(Table(bad, "demo"))
        with pytest.raises(InputError, match=msg):
            _Demo(**bad)
    with pytest.raises(InputError, match=r"^demo\.colour: unknown key"):
        _Demo.from_table(Table({"colour": 1}, "demo"))
    with pytest.raises(InputError, match=r"^demo\.size: unknown option$"):
        _Demo().with_(size=1)


def test_round_trip_and_defaults():
    d = _Demo.from_table(Table({"rate": 4, "raw": [1, 2], "cap": 1.5}, "demo"))
    assert d == _Demo(rate=4.0, raw=(1.0, 2.0), cap=1.5) and isinstance(d.rate, float)
    assert _Demo.from_table(Table(d.to_dict(), "demo")) == d
    assert "cap" not in _Demo().to_dict()  # None means "the default" and is left out
    assert _Demo.from_table(Table({}, "demo")) == _Demo()


def test_an_unbounded_int_option_is_a_programming_error():
    @dataclasses.dataclass(frozen=True)
    class Bad(Options):
        n: int = option(1, ge=0)

    with pytest.raises(TypeError, match="upper bound"):
        Bad.from_table(Table({}, "bad"))


def test_every_section_class_uses_the_one_style():
    # every options section derives from Options, declares every field with option(), bounds every int
    sections = [cls.SECTION for cls in SECTION_CLASSES]
    assert len(set(sections)) == len(sections) and "options" not in sections
    for cls in SECTION_CLASSES:
        assert issubclass(cls, Options) and cls.__dataclass_params__.frozen
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            assert "crtraj.option" in f.metadata, f"{cls.__name__}.{f.name} is not declared with option()"
            spec = f.metadata["crtraj.option"]
            if spec.read and hints[f.name] in (int, int | None):
                assert spec.le is not None, f"{cls.__name__}.{f.name}: an int without an upper bound"
    # no private bounds tables are left beside the declarations
    # the modules that define the sections and those of the classes that read them
    readers = (SteerSolver, TrackingController, Replanner, Streamer)
    for module in {sys.modules[c.__module__] for c in (*SECTION_CLASSES, *readers)}:
        assert not {"_FLOATS", "_INTS", "_BOOLS", "_STRS"} & set(vars(module)), module.__name__
    p = PlannerOptions.from_table(Table({"max_speed": 30, "cspace": {"range": 90.0}}, "planner"))
    assert p.max_speed == 30.0 and p.cspace.range == 90.0
    assert PlannerOptions.from_table(Table(p.to_dict(), "planner")) == p


# The defaults as the classes had them before the conversion (written out here, not read from the classes).
_OLD_DEFAULTS = {
    SteerOptions: dict(
        solver="ipopt", damping=0.3, obstacle_coefficient=20.0, damping_scale=0.02, obstacle_scale=0.02,
        max_step=100.0, tolerance=0.5, margin=0.0, n_points=None, max_iter=100, tol=1e-6, qpsol="daqp", jit=False,
        compiled=False, warm_start=None, fallback=True, predictor=True, feasibility_tolerance=1e-5, dls_gain=1.0,
        dls_iterations=200, ipopt=(), sqp=(),
    ),
    TrackingOptions: dict(
        dt=0.02, mode="configuration", servo_tau=0.05, servo_tau_z=0.1, max_cable_rate=10.0, max_z_rate=50.0,
        bending_error_scale=0.01, z_error_scale=0.5, effort_weight=1.0, damping=0.3,
    ),
    BenchOptions: dict(
        counts=(1, 3, 5, 7), scenarios=100, planners=BUILTIN.names, time_limit=5.0, seed=0,
        goal_tolerance=1.0, verify_points=128, verify_dt=0.01, verify_step=1.0,
        verify_margin=None,  # issue 15: success means safe, so the dense check demands the scene's D_sf
        cpu_budget=False,
    ),
    ScenarioOptions: dict(
        seed=0, radius_mean=(30.0, 50.0), radius_amplitude=(10.0, 20.0), omega=1.0, travel=(50.0, 100.0),
        mean_speed=(5.0, 15.0), fraction=(0.2, 0.8), max_tilt=math.pi / 6, min_tip_distance=150.0,
        tip_box_lo=(-130.0, -130.0, 150.0), tip_box_hi=(130.0, 130.0, 450.0), safety_distance=5.0,
        start_window=1.0, goal_margin=5.0, max_attempts=200,
    ),
    FeedOptions: dict(max_speed=500.0, velocity_window=0.25, min_span=0.05, max_skew=0.5),
    ReplanOptions: dict(
        horizon=10, dt=0.1, points=16, margin=1.5, tip_weight=1.0, config_weight=0.01, velocity_weight=0.02,
        smooth_weight=0.2, terminal_weight=10.0, max_cable_speed=8.0, max_z_speed=40.0, solver="ipopt",
        qpsol="daqp", hessian="gauss-newton", max_iter=60, max_calls=1, max_solve_time=0.5, limit_fraction=0.9,
        rescue=True, safety=True, compiled=False, fused=True, step_deadline=0.0,
        # issue 14: the QP keeps the 3 closest points per obstacle and step, and stops at a dual residual of
        # 1e-4 (mm^2 per unit of x) instead of 1e-6, both for the replan iteration's time
        closest_points=3, tol=1e-4,
        # issue 29: a QP of 3 obstacle slots, filled by the broad phase (31 obstacles within 2x of 1)
        qp_obstacles=3,
    ),
    LoopOptions: dict(
        duration=60.0, replan_period=0.0, planner_time=1.0, stall_time=3.0, reference_speed=0.7,
        max_body_speed=50.0, check_resolution=1.0, check_points=21, settle_time=0.5, reference_delay=0.0,
    ),
    StreamOptions: dict(
        rate=100.0, watchdog=0.1, connect_timeout=1.0, prebuffer=0.1, settle_tolerance=0.01, settle_timeout=2.0,
        ack_timeout=0.25, following_tolerance=5.0, fsync=False,
    ),
    ViewOptions: dict(
        backbone_radius=None, disc_spacing=20.0, disc_thickness=2.0, disc_radius=None,
        segment_colors=("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#17becf"), obstacle_color="#d62728",
        obstacle_opacity=0.3, shell_opacity=0.08, closest_color="#000000", ghost_opacity=0.35,
        start_color="#ffb000", goal_color="#e000e0", path_color="#8a8a8a",
        trail_color="#ff7f0e", tree_color="#8c8c8c", marker_radius=4.0, show_tree=None, play=True,
    ),
}  # fmt: skip

# One object per class with every kind of field set away from its default.
_CHANGED = (
    SteerOptions(
        solver="sqp", damping=0.5, margin=2, n_points=12, max_iter=50, qpsol="qrqp", jit=True, compiled=True,
        warm_start=False, fallback=False, dls_iterations=7, ipopt=(("print_level", 5), ("mu_init", 0.1)),
        sqp=(("hessian_approximation", "limited-memory"),),
    ),
    TrackingOptions(dt=0.01, mode="tip", servo_tau=0.2, damping=0.0),
    BenchOptions(counts=(0, 2), scenarios=3, planners=("cspace", "rrt"), time_limit=1.5, seed=7, verify_margin=0.5),
    ScenarioOptions(
        seed=5, radius_mean=(20.0, 40.0), travel=(10.0, 20.0), tip_box_lo=(-100.0, -90.0, 100.0), max_attempts=50
    ),
    FeedOptions(max_speed=80.0, min_span=0.02, max_skew=2.0),
    ReplanOptions(
        horizon=6, dt=0.05, points=12, margin=0, solver="sqp", qpsol="qrqp", hessian="exact", max_iter=20,
        limit_fraction=0.5, rescue=False, safety=False, compiled=True, step_deadline=0.05,
    ),
    LoopOptions(
        duration=2.5, replan_period=0.5, reference_speed=0.5, check_points=9, settle_time=0.0, reference_delay=0.3
    ),
    StreamOptions(rate=50, watchdog=0.5, prebuffer=0.0, following_tolerance=20.0, fsync=True),
    ViewOptions(disc_radius=3.0, segment_colors=["#000000", "#ABCDEF"], obstacle_opacity=1, tree_color="#ffffff",
                show_tree=False),
)  # fmt: skip


@pytest.mark.parametrize("cls", list(_OLD_DEFAULTS), ids=lambda c: c.__name__)
def test_defaults_are_unchanged_from_file_and_python(cls):
    want = _OLD_DEFAULTS[cls]
    assert {f.name for f in dataclasses.fields(cls)} == set(want)
    for obj in (cls(), cls.from_table(Table({}, cls.SECTION))):
        for name, value in want.items():
            got = getattr(obj, name)
            assert got == pytest.approx(value) if isinstance(value, float) else got == value, (cls, name)


@pytest.mark.parametrize("obj", _CHANGED, ids=lambda o: type(o).__name__)
def test_round_trip_through_the_toml_schema(obj):
    cls = type(obj)
    assert obj != cls()  # the object really differs from the defaults
    data = json.loads(json.dumps(obj.to_dict()))  # plain data: survives JSON unchanged
    assert data == obj.to_dict()
    assert cls.from_table(Table(data, cls.SECTION)) == obj
    assert cls.from_table(Table(cls().to_dict(), cls.SECTION)) == cls()
    # with_ changes one field and keeps the rest; it checks like the constructor
    name = next(f.name for f in dataclasses.fields(cls) if getattr(obj, f.name) == getattr(cls(), f.name))
    assert obj.with_(**{name: getattr(obj, name)}) == obj
    with pytest.raises(InputError, match=rf"^{cls.SECTION}\.no_such: unknown option$"):
        obj.with_(no_such=1)


def test_steer_raw_solver_tables_are_sub_tables_in_the_file():
    o = _CHANGED[0]
    d = o.to_dict()
    assert d["ipopt"] == {"print_level": 5, "mu_init": 0.1} and d["sqp"] == {"hessian_approximation": "limited-memory"}
    assert "ipopt" not in SteerOptions().to_dict() and "n_points" not in SteerOptions().to_dict()
    assert SteerOptions(ipopt=[["tol", 1e-3]]).ipopt == (("tol", 1e-3),)  # lists from Python become pairs


# (class, values, error): the same one line from a file and from Python
_BAD = (
    (SteerOptions, {"solver": "snopt"}, r"^steer\.solver: must be one of ipopt, sqp, dls; got 'snopt'$"),
    (SteerOptions, {"damping": -1.0}, r"^steer\.damping: must be >= 0, got -1$"),
    (SteerOptions, {"max_step": 2e6}, r"^steer\.max_step: must be within \+-1e\+06"),
    (SteerOptions, {"n_points": 1}, r"^steer\.n_points: must be >= 2, got 1$"),
    (SteerOptions, {"n_points": 201}, r"^steer\.n_points: must be <= 200, got 201$"),
    (SteerOptions, {"max_iter": 100_001}, r"^steer\.max_iter: must be <= 100000, got 100001$"),
    (SteerOptions, {"dls_gain": 1.5}, r"^steer\.dls_gain: must be <= 1, got 1\.5$"),
    (SteerOptions, {"dls_iterations": 0}, r"^steer\.dls_iterations: must be >= 1, got 0$"),
    (SteerOptions, {"warm_start": "yes"}, r"^steer\.warm_start: expected true or false"),
    (SteerOptions, {"tol": float("nan")}, r"^steer\.tol: must be finite"),
    (TrackingOptions, {"dt": 2.0}, r"^tracking\.dt: must be <= 1, got 2$"),
    (TrackingOptions, {"servo_tau_z": 0.0}, r"^tracking\.servo_tau_z: must be > 0, got 0$"),
    (TrackingOptions, {"mode": "joint"}, r"^tracking\.mode: must be one of configuration, tip; got 'joint'$"),
    (BenchOptions, {"scenarios": 0}, r"^bench\.scenarios: must be >= 1, got 0$"),
    (BenchOptions, {"verify_points": 1}, r"^bench\.verify_points: must be >= 2, got 1$"),
    (BenchOptions, {"verify_points": 1001}, r"^bench\.verify_points: must be <= 1000, got 1001$"),
    (BenchOptions, {"time_limit": 0.0}, r"^bench\.time_limit: must be > 0, got 0$"),
    (BenchOptions, {"verify_margin": -1.0}, r"^bench\.verify_margin: must be >= 0, got -1$"),
    (BenchOptions, {"counts": [1, 1]}, r"^bench\.counts: duplicate obstacle count in \[1, 1\]$"),
    (BenchOptions, {"counts": []}, r"^bench\.counts: expected 1 to 101 obstacle counts"),
    (BenchOptions, {"counts": [1, -2]}, r"^bench\.counts: each must be an integer in \[0, 100\], got -2$"),
    (BenchOptions, {"counts": [1, 101]}, r"^bench\.counts: each must be an integer in \[0, 100\], got 101$"),
    (BenchOptions, {"counts": [True]}, r"^bench\.counts: each must be an integer"),
    (BenchOptions, {"planners": []}, r"^bench\.planners: expected 1 to 64 planner names"),
    (BenchOptions, {"planners": ["rrt", "rrt"]}, r"^bench\.planners: duplicate planner in \['rrt', 'rrt'\]$"),
    (BenchOptions, {"planners": ["rrt", 3]}, r"^bench\.planners: a planner name is 1 to 100 characters, got 3$"),
    (ScenarioOptions, {"seed": -1}, r"^scenarios\.seed: must be >= 0, got -1$"),
    (ScenarioOptions, {"max_attempts": 100_001}, r"^scenarios\.max_attempts: must be <= 100000"),
    (ScenarioOptions, {"start_window": 0.0}, r"^scenarios\.start_window: must be > 0, got 0$"),
    (ScenarioOptions, {"omega": -1.0}, r"^scenarios\.omega: must be >= 0, got -1$"),
    (ScenarioOptions, {"radius_mean": [50.0, 30.0]}, r"^scenarios\.radius_mean: expected finite \[low, high\]"),
    (ScenarioOptions, {"travel": [-1.0, 100.0]}, r"^scenarios\.travel: expected finite \[low, high\] with 0 <="),
    (ScenarioOptions, {"fraction": [0.2, 1.5]}, r"^scenarios\.fraction: must lie within \[0, 1\]"),
    (ScenarioOptions, {"mean_speed": [0.0, 15.0]}, r"^scenarios\.mean_speed: low must be > 0 mm/s, got 0$"),
    (ScenarioOptions, {"mean_speed": [1.0]}, r"^scenarios\.mean_speed: expected 2 numbers, got 1$"),
    (ScenarioOptions, {"radius_amplitude": [10.0, 40.0]}, r"^scenarios\.radius_amplitude: largest B 40 mm exceeds"),
    (ScenarioOptions, {"tip_box_lo": [0.0, 0.0, 500.0]}, r"^scenarios\.tip_box_lo: must be below tip_box_hi"),
    (ScenarioOptions, {"tip_box_hi": [1e7, 1.0, 1.0]}, r"^scenarios\.tip_box_hi\[0\]: must be within \+-1e\+06"),
    (FeedOptions, {"max_speed": 1e6}, r"^feed\.max_speed: must be <= 100000, got 1e\+06$"),
    (ReplanOptions, {"horizon": 0}, r"^replan\.horizon: must be >= 1, got 0$"),
    (ReplanOptions, {"points": 201}, r"^replan\.points: must be <= 200, got 201$"),
    (ReplanOptions, {"dt": 1e-4}, r"^replan\.dt: must be >= 0\.001, got 0\.0001$"),
    (ReplanOptions, {"max_cable_speed": 0.0}, r"^replan\.max_cable_speed: must be > 0, got 0$"),
    (ReplanOptions, {"limit_fraction": 1.5}, r"^replan\.limit_fraction: must be <= 1, got 1\.5$"),
    (ReplanOptions, {"hessian": "bfgs"}, r"^replan\.hessian: must be one of gauss-newton, exact; got 'bfgs'$"),
    (
        ReplanOptions,
        {"qpsol": "highs"},
        r"^replan\.qpsol: must be one of daqp, qrqp, osqp, qpoases, hpipm; got 'highs'$",
    ),
    (ReplanOptions, {"safety": 0}, r"^replan\.safety: expected true or false"),
    (LoopOptions, {"duration": 0.0}, r"^loop\.duration: must be > 0, got 0$"),
    (LoopOptions, {"reference_speed": 1.5}, r"^loop\.reference_speed: must be <= 1, got 1\.5$"),
    (LoopOptions, {"check_points": 1}, r"^loop\.check_points: must be >= 2, got 1$"),
    (LoopOptions, {"check_points": 1001}, r"^loop\.check_points: must be <= 1000, got 1001$"),
    (LoopOptions, {"check_resolution": 0.001}, r"^loop\.check_resolution: must be >= 0\.01, got 0\.001$"),
    (LoopOptions, {"reference_delay": -0.1}, r"^loop\.reference_delay: must be >= 0, got -0\.1$"),
    (LoopOptions, {"reference_delay": 61.0}, r"^loop\.reference_delay: must be <= 60, got 61$"),
    (StreamOptions, {"rate": 2e4}, r"^stream\.rate: must be <= 10000, got 20000$"),
    (StreamOptions, {"watchdog": 0.0}, r"^stream\.watchdog: must be > 0, got 0$"),
    (StreamOptions, {"prebuffer": -0.1}, r"^stream\.prebuffer: must be >= 0, got -0\.1$"),
    (StreamOptions, {"fsync": "no"}, r"^stream\.fsync: expected true or false"),
    (ViewOptions, {"obstacle_opacity": 0.0}, r"^view\.obstacle_opacity: must be > 0, got 0$"),
    (ViewOptions, {"disc_radius": -1.0}, r"^view\.disc_radius: must be > 0, got -1$"),
    (ViewOptions, {"tree_color": "grey"}, r'^view\.tree_color: expected a colour "#rrggbb", got \'grey\'$'),
    (ViewOptions, {"segment_colors": []}, r"^view\.segment_colors: give at least one colour$"),
    (ViewOptions, {"segment_colors": ["#000000", "red"]}, r"^view\.segment_colors\[1\]: expected a colour"),
    (ViewOptions, {"segment_colors": ["#000000"] * 101}, r"^view\.segment_colors: at most 100 colours, got 101$"),
    (FeedOptions, {"max_skew": 0.0}, r"^feed\.max_skew: must be > 0, got 0$"),
    (FeedOptions, {"min_span": 1.0}, r"^feed\.min_span: must not exceed feed\.velocity_window \(0\.25 s\), got 1$"),
)  # fmt: skip


@pytest.mark.parametrize(("cls", "bad", "msg"), _BAD, ids=lambda v: getattr(v, "__name__", None))
def test_section_bounds_and_rules_give_one_line_from_file_and_python(cls, bad, msg):
    with pytest.raises(InputError, match=msg) as from_file:
        cls.from_table(Table(bad, cls.SECTION))
    as_python = {k: tuple(v) if isinstance(v, list) else v for k, v in bad.items()}
    with pytest.raises(InputError, match=msg) as from_python:
        cls(**as_python)
    assert str(from_file.value) == str(from_python.value) and "\n" not in str(from_file.value)


_LARGE_INT_BOUNDS = (
    ({"scenarios": 10**7}, "bench.scenarios: must be <= 1000000, got 10000000"),
    ({"seed": 2**32}, "bench.seed: must be <= 4294967295, got 4294967296"),
)


def test_large_int_bounds_from_a_file():
    for bad, msg in _LARGE_INT_BOUNDS:
        with pytest.raises(InputError) as info:
            BenchOptions.from_table(Table(bad, "bench"))
        assert str(info.value) == msg
        with pytest.raises(InputError, match=msg.split(" <= ")[0]):  # Python refuses too (wording: see below)
            BenchOptions(**bad)


# Known defect of the shared reader (crtraj/core/options.py, not part of this conversion): for an object built
# in Python, _check_int formats an int bound with :g ("must be <= 1e+06", "<= 4.29497e+09"), while the file
# reader writes it whole ("<= 1000000"). Strict: this fails once the reader is fixed; then drop the mark.
def test_large_int_bounds_read_the_same_from_python():
    for bad, msg in _LARGE_INT_BOUNDS:
        with pytest.raises(InputError) as info:
            BenchOptions(**bad)
        assert str(info.value) == msg


def test_list_fields_must_be_lists_in_a_file_and_unknown_keys_fail():
    with pytest.raises(InputError, match=r"^bench\.counts: expected a list, got 3$"):
        BenchOptions.from_table(Table({"counts": 3}, "bench"))
    with pytest.raises(InputError, match=r"^scenarios\.time_step: no longer supported"):
        ScenarioOptions.from_table(Table({"time_step": 1.0}, "scenarios"))
    for cls in SECTION_CLASSES:
        with pytest.raises(InputError, match=rf"^{cls.SECTION}\.colour: unknown key"):
            cls.from_table(Table({"colour": 1}, cls.SECTION))


def test_steer_raw_solver_options_are_checked_from_file_and_python():
    for value, msg in (
        (float("inf"), r"^steer\.ipopt\.mu_init: must be finite, got inf$"),
        (1e30, r"^steer\.ipopt\.mu_init: must be within \+-1e20, got 1e\+30$"),
        ("x" * 1001, r"^steer\.ipopt\.mu_init: longer than 1000 characters$"),
        ({"a": 1}, r"^steer\.ipopt\.mu_init: expected a string, number or boolean, got \{'a': 1\}$"),
    ):
        with pytest.raises(InputError, match=msg):
            SteerOptions.from_table(Table({"ipopt": {"mu_init": value}}, "steer"))
        with pytest.raises(InputError, match=msg):
            SteerOptions(ipopt=(("mu_init", value),))
    with pytest.raises(InputError, match=r"^steer\.sqp: at most 1000 solver options, got 1001$"):
        SteerOptions.from_table(Table({"sqp": {f"k{i}": i for i in range(1001)}}, "steer"))
    with pytest.raises(InputError, match=r"^steer\.sqp\[0\]: expected a \(name, value\) pair"):
        SteerOptions(sqp=(("tol",),))
    with pytest.raises(InputError, match=r"^steer\.ipopt: expected at most 1000 \(name, value\) pairs"):
        SteerOptions(ipopt={"tol": 1.0})


def test_python_values_are_stored_as_the_file_would_give_them():
    # ints for float fields become floats, numpy ints become ints, lists become tuples: equal to the file's
    s = ScenarioOptions(
        seed=np.int64(3), max_attempts=np.int32(9), radius_mean=[30, 50], tip_box_hi=np.array([1, 2, 500])
    )
    assert type(s.seed) is int and type(s.max_attempts) is int and s.radius_mean == (30.0, 50.0)
    assert s == ScenarioOptions.from_table(Table(json.loads(json.dumps(s.to_dict())), "scenarios"))
    b = BenchOptions(counts=[np.int64(0), 2], planners=["rrt"])
    assert b.counts == (0, 2) and all(type(c) is int for c in b.counts) and b.planners == ("rrt",)
    t = TrackingOptions(dt=1)
    assert t.dt == 1.0 and isinstance(t.dt, float)


def test_replan_keeps_its_moved_to_loop_error_and_qp_solver_check():
    for key in MOVED_TO_LOOP:
        with pytest.raises(InputError) as info:
            ReplanOptions.from_table(Table({key: 2}, "replan"))
        assert str(info.value) == f"replan.{key}: moved to the [loop] section; write it under [loop]"
        value = 1 if key == "reference_speed" else 2
        assert LoopOptions.from_table(Table({key: value}, "loop")).to_dict()[key] == value  # read under [loop]
    # every QP solver this CasADi build lacks is refused for "sqp" (one line), from a file and from Python
    for qp in ("daqp", "qrqp", "osqp", "qpoases", "hpipm"):
        if ca.has_conic(qp):
            assert ReplanOptions(solver="sqp", qpsol=qp).qpsol == qp
        else:
            msg = rf"^replan\.qpsol: QP solver '{qp}' is not available in this CasADi build$"
            with pytest.raises(InputError, match=msg):
                ReplanOptions(solver="sqp", qpsol=qp)
            with pytest.raises(InputError, match=msg):
                ReplanOptions.from_table(Table({"solver": "sqp", "qpsol": qp}, "replan"))
            assert ReplanOptions(qpsol=qp).solver == "ipopt"  # ipopt never uses it


def test_loop_steps_and_stream_period_survive_the_conversion():
    assert LoopOptions(duration=2.5).steps(0.1) == 25 and LoopOptions(duration=1e4).steps(0.1) == 100_000
    msg = r"^loop\.duration: 10000 s is 100011 steps of replan\.dt 0\.09999 s, more than 100000; shorten it"
    with pytest.raises(InputError, match=msg):
        LoopOptions(duration=1e4).steps(0.09999)
    assert StreamOptions(rate=50).dt == pytest.approx(0.02)


def test_view_segment_colours_must_be_a_list_of_strings_in_a_file():
    with pytest.raises(InputError, match=r'^view\.segment_colors: expected a list of "#rrggbb" strings, got 3$'):
        ViewOptions.from_table(Table({"segment_colors": 3}, "view"))
    with pytest.raises(InputError, match=r'^view\.segment_colors: expected a list of "#rrggbb" strings'):
        ViewOptions.from_table(Table({"segment_colors": ["#000000", 1]}, "view"))
    with pytest.raises(InputError, match=r'^view\.segment_colors: expected a list of "#rrggbb" strings'):
        ViewOptions(segment_colors="#000000")
