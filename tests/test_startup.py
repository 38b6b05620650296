"""What keeps `crtraj plan` quick to start: modules imported on first use, and the result JSON written by the
C encoder with the same content as before."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from crtraj.core.fileio import atomic_write_json, json_document, to_jsonable
from crtraj.core.lazy import lazy_module


def test_lazy_module_runs_on_first_attribute(tmp_path, monkeypatch):
    (tmp_path / "lazy_probe_mod.py").write_text(
        "import pathlib\npathlib.Path(__file__).with_name('ran').write_text('yes')\nVALUE = 42\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "lazy_probe_mod", raising=False)
    mod = lazy_module("lazy_probe_mod")
    assert not (tmp_path / "ran").exists()
    assert mod.VALUE == 42 and (tmp_path / "ran").read_text() == "yes"
    assert lazy_module("lazy_probe_mod") is sys.modules["lazy_probe_mod"]
    with pytest.raises(ImportError, match="no_such_module_here"):
        lazy_module("no_such_module_here")


def test_the_plan_command_does_not_import_what_it_never_uses():
    """python-control (with SciPy's signal and stats, and matplotlib's pyplot), toppra, SciPy's interpolate
    and spatial packages (our own splines replace the first; the KD-tree loads with a large tree) and the
    3-D view's meshcat load only when used."""
    code = (
        "import sys, crtraj.app.plan\n"
        # (`control` and `scipy.interpolate` are in sys.modules as lazy stand-ins; their submodules load with them)
        "heavy = ('control.statesp', 'toppra', 'matplotlib.pyplot', 'scipy.signal', 'scipy.interpolate._bsplines',\n"
        "         'scipy.spatial.transform', 'scipy.special', 'meshcat', 'zmq')\n"
        "print(sorted(m for m in heavy if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    # and the lazily bound module still works where it is used
    from crtraj.control.tracking import _design as tracking

    assert callable(tracking.control.dlqr)


def test_json_document_round_trips_and_keeps_top_level_lines(tmp_path):
    doc = {
        "kind": "plan",
        "values": np.array([[1.5, -2.0], [np.nan, np.inf]]),
        "ints": np.arange(3),
        "nested": {"a": [1, 2, {"b": np.float64(0.1)}]},
        "empty": [],
    }
    data = to_jsonable(doc)
    assert data["values"] == [[1.5, -2.0], [None, None]] and data["ints"] == [0, 1, 2]
    text = json_document(data)
    assert json.loads(text) == data
    lines = text.strip().splitlines()
    assert lines[0] == "{" and lines[-1] == "}" and len(lines) == 2 + len(doc)
    assert lines[1] == '"kind": "plan",'
    path = atomic_write_json(tmp_path / "d.json", doc)
    assert json.loads(path.read_text()) == data
    # finite float arrays take the fast path: the same numbers, bit for bit
    a = np.random.default_rng(0).normal(size=(50, 7))
    assert to_jsonable(a) == a.tolist() and all(math.isfinite(v) for row in to_jsonable(a) for v in row)
    assert json_document([1, 2]) == "[1, 2]\n" and json_document({}) == "{}\n"
