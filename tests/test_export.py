"""`crtraj export`: .casadi files and the compiled library reproduce the in-process functions."""

from __future__ import annotations

import json

import casadi as ca
import numpy as np
import pytest
from conftest import require_tool

from crtraj.cli import main

X_TEST = [
    np.zeros(5),
    np.array([0.3, -0.2, 1.1, 0.4, -120.0]),
    np.array([-2.0, 1.5, 0.01, -0.02, 60.0]),
]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    assert main(["export", "--out", str(out), "--batch", "4"]) == 0
    return out


def test_manifest_describes_every_function(exported, model):
    man = json.loads((exported / "manifest.json").read_text())
    names = {f["name"] for f in man["functions"]}
    assert names == {
        "config_to_cables",
        "cables_to_config",
        "bending",
        "tip",
        "tip_frame",
        "backbone",
        "jac_tip",
        "jac_cables",
        "limits",
        "backbone_map",
    }
    by = {f["name"]: f for f in man["functions"]}
    assert by["backbone"]["inputs"] == [{"name": "x", "shape": [5, 1], "units": by["backbone"]["inputs"][0]["units"]}]
    assert by["backbone"]["outputs"][0]["shape"] == [3, model.n_points]
    assert by["config_to_cables"]["outputs"][0]["shape"] == [7, 1]
    assert by["backbone_map"]["inputs"][0]["shape"] == [5, 4]
    assert man["robot"]["name"] == "cdsr2" and man["casadi_version"] == ca.__version__
    assert all(f["inputs"][0]["units"] for f in man["functions"])
    for f in man["functions"]:
        assert (exported / f["file"]).is_file()


def test_casadi_files_round_trip(exported, model):
    for name in ("tip", "backbone", "jac_tip", "config_to_cables", "limits", "tip_frame", "bending"):
        loaded = ca.Function.load(str(exported / f"{name}.casadi"))
        ref = getattr(model, name)
        for x in X_TEST:
            np.testing.assert_allclose(np.asarray(loaded(x)), np.asarray(ref(x)), atol=1e-10, rtol=0)


def test_compiled_library_round_trip(exported, model):
    require_tool("cc", "gcc", "clang", hint="Debian: apt-get install gcc")
    man = json.loads((exported / "manifest.json").read_text())
    lib = exported / man["library"]
    assert lib.is_file()
    for name in ("tip", "backbone", "jac_tip", "cables_to_config", "limits"):
        ext = ca.external(name, str(lib))
        ref = getattr(model, name)
        for x in X_TEST:
            arg = model.cables(x) if name == "cables_to_config" else x
            np.testing.assert_allclose(np.asarray(ext(arg)), np.asarray(ref(arg)), atol=1e-10, rtol=0)
    bmap = ca.external("backbone_map", str(lib))
    X = np.array([*X_TEST, X_TEST[1] * 0.5]).T
    P = np.asarray(bmap(X)).reshape(3, 4, model.n_points).transpose(1, 2, 0)
    np.testing.assert_allclose(P, model.points(X.T), atol=1e-10)


def test_c_source_and_header_written(exported):
    assert (exported / "cdsr2_model.c").read_text().count("casadi_real") > 10
    assert "backbone" in (exported / "cdsr2_model.h").read_text()


def test_no_compile_writes_source_only(tmp_path):
    assert main(["export", "--out", str(tmp_path), "--no-compile"]) == 0
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["library"] is None
    assert not list(tmp_path.glob("*.so"))
    assert (tmp_path / "cdsr2_model.c").is_file()
