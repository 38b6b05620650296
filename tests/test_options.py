"""The one options style (crtraj.core.options): declared bounds read from files and checked in Python alike."""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from typing import ClassVar

import numpy as np
import pytest

import crtraj.bench.records
import crtraj.bench.scenarios
import crtraj.control.tracking
import crtraj.planning.options
import crtraj.planning.steer
import crtraj.world.feed
from crtraj.bench.records import BenchOptions
from crtraj.bench.scenarios import ScenarioOptions
from crtraj.control.tracking import TrackingOptions
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.options import Options, option
from crtraj.planning.options import PlannerOptions
from crtraj.planning.steer import SteerOptions
from crtraj.world.feed import FeedOptions

# every options section of the package (ReplanOptions, ViewOptions, StreamOptions join when converted)
SECTION_CLASSES = (PlannerOptions, SteerOptions, TrackingOptions, BenchOptions, ScenarioOptions, FeedOptions)


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
    for module in (
        crtraj.planning.options,
        crtraj.planning.steer,
        crtraj.control.tracking,
        crtraj.bench.records,
        crtraj.bench.scenarios,
        crtraj.world.feed,
    ):
        assert not {"_FLOATS", "_INTS", "_BOOLS", "_STRS"} & set(vars(module)), module.__name__
    p = PlannerOptions.from_table(Table({"max_speed": 30, "range": 90.0}, "planner"))
    assert p.max_speed == 30.0 and p.range == 90.0 and PlannerOptions.from_table(Table(p.to_dict(), "planner")) == p


# The defaults as the classes had them before the conversion (written out here, not read from the classes).
_OLD_DEFAULTS = {
    SteerOptions: dict(
        solver="ipopt", damping=0.3, obstacle_coefficient=20.0, damping_scale=0.02, obstacle_scale=0.02,
        max_step=100.0, tolerance=0.5, margin=0.0, n_points=None, max_iter=100, tol=1e-6, qpsol="daqp", jit=False,
        warm_start=None, fallback=True, predictor=True, feasibility_tolerance=1e-5, dls_gain=1.0,
        dls_iterations=200, ipopt=(), sqp=(),
    ),
    TrackingOptions: dict(
        dt=0.02, mode="configuration", servo_tau=0.05, servo_tau_z=0.1, max_cable_rate=10.0, max_z_rate=50.0,
        bending_error_scale=0.01, z_error_scale=0.5, effort_weight=1.0, damping=0.3,
    ),
    BenchOptions: dict(
        counts=(1, 3, 5, 7), scenarios=100, planners=crtraj.bench.records.BUILTIN.names, time_limit=5.0, seed=0,
        goal_tolerance=1.0, verify_points=128, verify_dt=0.01, verify_step=1.0, verify_margin=0.0,
    ),
    ScenarioOptions: dict(
        seed=0, radius_mean=(30.0, 50.0), radius_amplitude=(10.0, 20.0), omega=1.0, travel=(50.0, 100.0),
        mean_speed=(5.0, 15.0), fraction=(0.2, 0.8), max_tilt=math.pi / 6, min_tip_distance=150.0,
        tip_box_lo=(-130.0, -130.0, 150.0), tip_box_hi=(130.0, 130.0, 450.0), safety_distance=5.0,
        start_window=1.0, goal_margin=5.0, max_attempts=200,
    ),
    FeedOptions: dict(max_speed=500.0, velocity_window=0.25, min_span=0.05, max_skew=0.5),
}  # fmt: skip

# One object per class with every kind of field set away from its default.
_CHANGED = (
    SteerOptions(
        solver="sqp", damping=0.5, margin=2, n_points=12, max_iter=50, qpsol="qrqp", jit=True, warm_start=False,
        fallback=False, dls_iterations=7, ipopt=(("print_level", 5), ("mu_init", 0.1)),
        sqp=(("hessian_approximation", "limited-memory"),),
    ),
    TrackingOptions(dt=0.01, mode="tip", servo_tau=0.2, damping=0.0),
    BenchOptions(counts=(0, 2), scenarios=3, planners=("cspace", "rrt"), time_limit=1.5, seed=7, verify_margin=0.5),
    ScenarioOptions(
        seed=5, radius_mean=(20.0, 40.0), travel=(10.0, 20.0), tip_box_lo=(-100.0, -90.0, 100.0), max_attempts=50
    ),
    FeedOptions(max_speed=80.0, min_span=0.02, max_skew=2.0),
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
