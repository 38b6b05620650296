"""The public API: ``import crtraj`` is the front door.

Every name of ``crtraj.__all__`` resolves, once, to the object of the sub-package that defines it; ``import crtraj``
loads none of it (no CasADi); every sub-package lists its own public names in ``__all__``; the static stub
(``crtraj/__init__.pyi``) and the API reference list exactly ``crtraj.__all__``; and the examples, the README's
Python and the tutorials' Python use only public names (read with ast, independently of the package's tables).
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import re
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import crtraj
from crtraj.core.lazy import lazy_exports

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "crtraj"
SUBPACKAGES = sorted(p.parent.name for p in PKG.glob("*/__init__.py"))
LIBRARY = [p for p in SUBPACKAGES if p != "cli"]  # the command's package is its parser, not a library


def _public(names) -> list[str]:
    return [n for n in names if n != "__version__"]


# ------------------------------------------------------------------------------------------------ crtraj
def test_every_name_of_crtraj_resolves_once():
    """Unique names, each resolving to a distinct object: no object has two public names."""
    names = crtraj.__all__
    assert len(names) == len(set(names))
    assert {"Problem", "Model", "Scene", "plan_executable", "ClosedLoop", "admit_plan", "Streamer"} <= set(names)
    objects = {}
    for name in _public(names):
        obj = getattr(crtraj, name)
        assert id(obj) not in objects, f"{name} and {objects.get(id(obj))} are the same object"
        objects[id(obj)] = name
    assert set(names) <= set(dir(crtraj))


def test_each_name_of_crtraj_has_one_home_sub_package():
    """crtraj.X is the very object of exactly one sub-package's __all__, the one whose modules define it."""
    for name in _public(crtraj.__all__):
        homes = [p for p in LIBRARY if name in importlib.import_module(f"crtraj.{p}").__all__]
        assert len(homes) == 1, f"{name}: listed by {homes}"
        assert getattr(crtraj, name) is getattr(importlib.import_module(f"crtraj.{homes[0]}"), name)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        _ = crtraj.no_such_name
    assert not hasattr(crtraj.planning, "no_such_name")


def test_import_crtraj_loads_nothing_heavy():
    """In a fresh interpreter: ``import crtraj`` loads no sub-package and no CasADi or numpy; reading one name
    loads what that name needs (so the check can see an import)."""
    code = (
        "import sys, crtraj\n"
        "before = sorted(m for m in sys.modules if m.startswith(('crtraj.', 'casadi', 'numpy')))\n"
        "crtraj.Model\n"
        "print(before, 'casadi' in sys.modules, 'crtraj.model.kinematics' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert out.split() == ["[]", "True", "True"]


def test_the_stub_lists_exactly_the_public_names():
    """crtraj/__init__.pyi (what type checkers and the API reference read) imports each public name from the
    module that defines that very object, and its __all__ is crtraj.__all__."""
    tree = ast.parse((PKG / "__init__.pyi").read_text(encoding="utf-8"))
    imported: dict[str, str] = {}
    stub_all = None
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                assert alias.asname == alias.name, f"{alias.name}: a stub re-export is `import X as X`"
                assert alias.name not in imported, f"{alias.name} imported twice"
                imported[alias.name] = node.module
        elif isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "__all__":
            stub_all = ast.literal_eval(node.value)
    assert stub_all is not None and sorted(stub_all) == sorted(crtraj.__all__)
    assert sorted(imported) == sorted(_public(crtraj.__all__))
    for name, module in imported.items():
        assert getattr(importlib.import_module(module), name) is getattr(crtraj, name), name


# ------------------------------------------------------------------------------------------- sub-packages
@pytest.mark.parametrize("package", SUBPACKAGES)
def test_every_sub_package_lists_its_public_names(package):
    """__all__ exists, is unique, every name resolves and is defined inside the sub-package (one home: no
    sub-package re-exports another's names), and no name shadows a module of the package."""
    mod = importlib.import_module(f"crtraj.{package}")
    names = mod.__all__
    assert names and len(names) == len(set(names))
    folder = PKG / package
    modules = {p.stem for p in folder.glob("*.py")} | {p.parent.name for p in folder.glob("*/__init__.py")}
    assert not set(names) & modules, f"names equal to a module of crtraj.{package}: {set(names) & modules}"
    for name in names:
        obj = getattr(mod, name)
        if inspect.isclass(obj) or inspect.isfunction(obj):
            home = obj.__module__
            assert home.startswith(f"crtraj.{package}.") or home == f"crtraj.{package}", f"{package}.{name}: {home}"
    assert set(names) <= set(dir(mod))


def test_sub_packages_load_lazily():
    """``import crtraj.planning`` imports none of its modules; the first read of a name does, and binds it."""
    code = (
        "import sys, crtraj.planning as p\n"
        "print('crtraj.planning.context' in sys.modules, end=' ')\n"
        "c = p.PlanningContext\n"
        "print('crtraj.planning.context' in sys.modules, 'PlanningContext' in vars(p))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert out.split() == ["False", "True", "True"]


def test_lazy_exports_refuses_a_name_with_two_homes():
    with pytest.raises(ValueError, match=r"'X' is listed under a\.b and a\.c"):
        lazy_exports("a", {"a.b": ("X",), "a.c": ("X", "Y")})


def test_lazy_exports_loads_and_binds_on_first_read(monkeypatch):
    pkg = types.ModuleType("crtraj_probe_pkg")
    monkeypatch.setitem(sys.modules, "crtraj_probe_pkg", pkg)
    names, getattr_, dir_ = lazy_exports("crtraj_probe_pkg", {"json": ("dumps",), "textwrap": ("dedent",)})
    assert names == ["dumps", "dedent"] and {"dumps", "dedent"} <= set(dir_())
    import json

    assert getattr_("dumps") is json.dumps and vars(pkg)["dumps"] is json.dumps
    with pytest.raises(AttributeError, match="loads"):
        getattr_("loads")  # in json, but not listed


# ----------------------------------------------------------------------------------- examples and docs
def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(encoding="utf-8"), flags=re.S)


def _uses(code: str) -> list[str]:
    """The crtraj names `code` reaches, as dotted paths: ``from crtraj.io import X`` -> crtraj.io:X,
    ``crtraj.Model`` -> crtraj:Model, ``import crtraj.io.problem`` -> crtraj.io.problem (a module import)."""
    tree = ast.parse(code)
    aliases = {"crtraj"}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "crtraj":
                    if a.name != "crtraj":
                        out.append(a.name)
                    aliases.add(a.asname or "crtraj")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "crtraj":
            out += [f"{node.module}:{a.name}" for a in node.names]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
            out.append(f"crtraj:{node.attr}")
    return out


def _private(uses: list[str]) -> list[str]:
    """The uses that are not public: a package's name outside its __all__, a module reached directly, or the
    command line (a script calls the library, never `crtraj.cli.main`)."""
    bad = []
    for use in uses:
        module, _, name = use.partition(":")
        if not name or module.startswith("crtraj.cli") or not hasattr(importlib.import_module(module), "__path__"):
            bad.append(use)  # a module, not a package's public name
            continue
        public = getattr(importlib.import_module(module), "__all__", ())
        if name not in public and not (module == "crtraj" and name in SUBPACKAGES):
            bad.append(use)
    return bad


SOURCES = [*sorted((ROOT / "examples").glob("*.py")), ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_examples_and_docs_use_only_public_names(path):
    codes = [path.read_text(encoding="utf-8")] if path.suffix == ".py" else _python_blocks(path)
    for code in codes:
        assert not _private(_uses(code)), f"{path.name}: non-public names {_private(_uses(code))}"


def test_the_public_name_check_sees_a_deep_import():
    """The check above fails on what the examples used to do: a module path, a CLI entry, a private name."""
    code = (
        "import crtraj\nfrom crtraj.io.problem import Problem\nfrom crtraj.cli import main\n"
        "from crtraj.planning import ExecutablePlan\nimport crtraj.app.plan\ncrtraj.Model\ncrtraj._HOMES\n"
    )
    bad = ["crtraj.app.plan", "crtraj.io.problem:Problem", "crtraj.cli:main", "crtraj:_HOMES"]
    assert sorted(_private(_uses(code))) == sorted(bad)


def test_the_readme_quick_start_is_one_import():
    blocks = _python_blocks(ROOT / "README.md")
    assert blocks and all(_uses(b) and not _private(_uses(b)) for b in blocks)
    assert all(b.lstrip().startswith("import crtraj\n") for b in blocks)


def test_the_api_reference_documents_every_public_name_once():
    """docs/reference/api.md renders `::: crtraj` blocks whose member lists together are crtraj.__all__; a
    sub-package not (yet) at the front door (`crtraj.world.geometry`) may have its own block, of names that are
    in its own __all__ and not in crtraj's (one home per name)."""
    text = (ROOT / "docs" / "reference" / "api.md").read_text(encoding="utf-8")
    blocks = re.findall(r"^::: (\S+)\n(?:.*\n)*?\s*members: \[(.*?)\]", text, flags=re.M)
    assert len(blocks) == len(re.findall(r"^::: ", text, flags=re.M)), "every block lists its members"
    top = [n.strip() for home, group in blocks if home == "crtraj" for n in group.split(",")]
    assert len(top) == len(set(top))
    assert sorted(top) == sorted(_public(crtraj.__all__))
    for home, group in blocks:
        if home != "crtraj":
            names = [n.strip() for n in group.split(",")]
            assert set(names) <= set(importlib.import_module(home).__all__), home
            assert not set(names) & set(crtraj.__all__), f"{home}: a name with two homes"


# ------------------------------------------------------------------------------------------ library calls
@pytest.fixture(scope="module")
def cdsr2():
    robot = crtraj.load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    return robot, crtraj.Model(robot)


def _plan(robot, model, *, status=None, min_clearance=2.0, duration=3.0, n=16):
    """An executable plan made by hand: the straight robot bends and lowers its base along a cosine time law."""
    x0, x1 = robot.straight(0.0), np.array([0.35, -0.25, -0.2, 0.45, -8.0])
    s = np.linspace(0.0, 1.0, n)
    X = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    result = crtraj.PlanResult(
        status=crtraj.PlanStatus.EXACT if status is None else status,
        message="",
        planner="by hand",
        seed=0,
        t=duration * s,
        configs=X,
        tips=model.tip_position(X),
        cables=model.cables(X),
        min_clearance=min_clearance,
    )
    return crtraj.ExecutablePlan(result, None)


def test_admit_plan_admits_the_plans_own_motion(cdsr2):
    """The admitted frames run from the plan's first to its last waypoint, at the servo values the actuators'
    conversion gives for its first and last actuation (`Actuators.command`), one frame per 1/rate s."""
    robot, model = cdsr2
    plan = _plan(robot, model)
    context = types.SimpleNamespace(robot=robot, scene=crtraj.Scene())  # all admit_plan reads of a context
    motion = crtraj.admit_plan(plan, context, rate=50.0)
    acts = crtraj.Actuators.from_robot(robot)
    np.testing.assert_allclose(motion.stamps[[0, -1]], [0.0, 3.0], atol=1e-12)
    assert len(motion.stamps) == 151
    np.testing.assert_allclose(motion.values[0], acts.command(plan.result.cables[0]), atol=1e-9)
    np.testing.assert_allclose(motion.values[-1], acts.command(plan.result.cables[-1]), atol=1e-9)
    slow = crtraj.admit_plan(plan, context, rate=50.0, time_scale=2.0)
    np.testing.assert_allclose(slow.stamps[-1], 6.0, atol=1e-12)


def test_admit_plan_refuses_what_may_not_drive_a_device(cdsr2):
    robot, model = cdsr2
    context = types.SimpleNamespace(robot=robot, scene=crtraj.Scene())
    with pytest.raises(crtraj.AdmissionError, match="success: false"):
        crtraj.admit_plan(_plan(robot, model, status=crtraj.PlanStatus.TIMEOUT), context)
    with pytest.raises(crtraj.AdmissionError, match="safety_violations"):
        crtraj.admit_plan(_plan(robot, model, min_clearance=-0.5), context)
    # a sphere around the straight tip (400 mm up): the frames themselves are checked against the scene
    blocked = crtraj.Scene(obstacles=(crtraj.Obstacle(center=(0.0, 0.0, 400.0), radius=10.0),))
    with pytest.raises(crtraj.AdmissionError):
        crtraj.admit_plan(_plan(robot, model), context, scene=blocked)
    bare = dataclasses.replace(robot, actuators=None)
    with pytest.raises(crtraj.InputError, match=r"robot\.actuators: missing"):
        crtraj.admit_plan(_plan(robot, model), types.SimpleNamespace(robot=bare, scene=crtraj.Scene()))


def test_calibrate_robot_refuses_bad_outputs_before_any_work(tmp_path):
    robot_file = ROOT / "problems" / "robots" / "cdsr2.toml"
    data = tmp_path / "data.json"
    data.write_text("{}")
    with pytest.raises(crtraj.InputError, match=r"out: .* is also robot_file"):
        crtraj.calibrate_robot(data, robot_file, robot_file)  # would overwrite its own input
    with pytest.raises(crtraj.InputError, match="unknown parameter group 'stiffness'"):
        crtraj.calibrate_robot(data, robot_file, tmp_path / "cal.toml", fit="stiffness")
    assert not (tmp_path / "cal.toml").exists()
