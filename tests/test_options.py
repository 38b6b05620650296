"""The one options style (crtraj.core.options): declared bounds read from files and checked in Python alike."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import pytest

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.options import Options, option
from crtraj.planning.options import PlannerOptions


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
    # every options section of the package derives from Options and declares every field with option()
    import crtraj.planning.options as po

    for cls in (po.PlannerOptions,):
        assert issubclass(cls, Options)
        for f in dataclasses.fields(cls):
            assert "crtraj.option" in f.metadata, f"{cls.__name__}.{f.name} is not declared with option()"
    p = PlannerOptions.from_table(Table({"max_speed": 30, "range": 90.0}, "planner"))
    assert p.max_speed == 30.0 and p.range == 90.0 and PlannerOptions.from_table(Table(p.to_dict(), "planner")) == p
