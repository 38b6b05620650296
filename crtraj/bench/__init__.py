"""Benchmarks and scenario suites. Above: io.

Public names load on first use (`crtraj.core.lazy.lazy_exports`).
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.bench.records": ("BenchOptions", "RunRecord"),
        "crtraj.bench.check": ("DenseCheck", "dense_check"),
        "crtraj.bench.scenarios": ("Scenario", "ScenarioGenerator", "ScenarioOptions"),
        "crtraj.bench.runner": ("Table1Bench",),
        "crtraj.bench.suite": ("SuiteOptions", "SuiteRunner"),
    },
)
