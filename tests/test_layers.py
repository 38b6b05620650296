"""The package layout is the design, checked over the whole tree in a few tests.

- Layers, low to high (docs/architecture.md): core < model < world < planning < control < hardware < io
  < {viz, bench} < app < cli. A module may import its own package and any lower layer, never a higher one
  nor a sibling of the same rank (viz and bench stay independent).
- Imports sit at module level, except for optional extras whose absence must not break the rest (OMPL, Dask,
  ROS, Dynamixel, matplotlib in headless paths): the AST of every module is read, so an import hidden in a
  function is seen too.
- Rooms: a concept with several modules is a subpackage; no folder holds more than MAX_FOLDER_MODULES modules;
  every package's ``__init__`` has ``__all__``.
- A private module (``_x.py``) is imported only from inside its own package: never by another package of
  crtraj, nor by the examples or the docs, which use the package's public names. A subpackage's own tests may
  import its private modules: `TEST_OWNERS` names them by test file prefix.
- Sizes: functions, classes and modules stay readable (MAX_*_LINES).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent  # the repository: crtraj/, tests/, examples/, docs/
PKG = ROOT / "crtraj"

RANK = {
    "": 0,  # crtraj/__init__.py: the version only
    "core": 0,
    "model": 1,
    "world": 2,
    "planning": 3,
    "control": 4,
    "hardware": 5,
    "io": 6,
    "viz": 7,
    "bench": 7,
    "app": 8,
    "cli": 9,
}
# Optional extras (pyproject [project.optional-dependencies]), headless-only plotting and trimesh (seconds to
# import, needed only when a mesh or PLY file is read): the only imports allowed inside functions.
OPTIONAL = {
    "trimesh",
    "ompl",
    "distributed",
    "dask",
    "rclpy",
    "dynamixel_sdk",
    "matplotlib",
    "std_msgs",
    "sensor_msgs",
    "trajectory_msgs",
    "visualization_msgs",
    "geometry_msgs",
    "builtin_interfaces",
    "nav_msgs",
    "rcl_interfaces",
    "mcap",
    "toppra",
}


def _modules(root: Path = ROOT) -> list[Path]:
    """Every module of the crtraj package under the repository `root`."""
    return sorted(p for p in (root / "crtraj").rglob("*.py") if "__pycache__" not in p.parts)


def _rel(path: Path) -> tuple[str, ...]:
    """`path`'s parts below its crtraj package folder (the last folder of that name above it)."""
    parts = path.parts
    i = len(parts) - 1 - parts[::-1].index("crtraj")
    return parts[i + 1 :]


def _layer_of_file(path: Path) -> str:
    rel = _rel(path)
    if len(rel) == 1:
        return "cli" if Path(rel[0]).stem == "cli" else ""
    return rel[0]


def _layer_of_module(name: str) -> str | None:
    parts = name.split(".")
    if parts[0] != "crtraj":
        return None
    if len(parts) == 1:
        return ""
    return "cli" if parts[1] == "cli" else parts[1]


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"))


def _imported(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
        return [node.module]
    return []


def _over_tree(check, root: Path = ROOT) -> dict[str, list[str]]:
    """`check` over every module of crtraj: {module path: what it found}, the modules it found nothing in left out."""
    found = {"/".join(_rel(p)): check(p) for p in _modules(root)}
    return {k: v for k, v in found.items() if v}


def _report(title: str, bad: dict) -> str:
    """One failure message naming every offending module."""
    return f"{title}:\n" + "\n".join(f"{k}: {v}" for k, v in bad.items())


# ------------------------------------------------------------------------------------------------ layers
def _unlayered(root: Path = ROOT) -> list[str]:
    """Packages without a rank, and modules at the top of crtraj but its __init__."""
    rels = [_rel(p) for p in _modules(root)]
    packages = sorted({r[0] for r in rels if len(r) > 1} - set(RANK))
    loose = sorted(r[0] for r in rels if len(r) == 1 and Path(r[0]).stem not in ("__init__", "cli"))
    return packages + loose


def _upward_imports(path: Path) -> list[str]:
    own = _layer_of_file(path)
    bad = []
    for node in ast.walk(_tree(path)):
        for name in _imported(node):
            layer = _layer_of_module(name)
            if layer is None or layer == own or layer == "":
                continue
            if RANK[layer] >= RANK[own]:
                bad.append(f"line {node.lineno}: {name} ({layer}) from {own or 'crtraj'}")
        if isinstance(node, ast.ImportFrom) and node.level:
            bad.append(f"line {node.lineno}: relative import")
    return bad


def _hidden_imports(path: Path) -> list[str]:
    hidden = []
    for fn in ast.walk(_tree(path)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            for name in _imported(node):
                if name.split(".")[0] not in OPTIONAL:
                    hidden.append(f"line {node.lineno}: {name} in {fn.name}()")
    return sorted(set(hidden))


def test_every_package_has_a_layer():
    assert not _unlayered(), f"packages without a layer, or loose modules in crtraj/: {_unlayered()}"


def test_no_upward_or_sideways_import():
    bad = _over_tree(_upward_imports)
    assert not bad, _report("upward or sideways imports", bad)


def test_no_hidden_imports():
    bad = _over_tree(_hidden_imports)
    assert not bad, _report("imports inside functions (move them to module level)", bad)


# Sizes that keep a module readable (DESIGN.md): a function over this many lines of code (docstring excluded),
# private ones included, carries a comment starting with "# long" just above its def (or on it), saying why; a class
# is at most MAX_CLASS_LINES lines, with no exception; a module over MAX_MODULE_LINES lines is one concept and says
# so in a "# long: reason" comment among its first LONG_MODULE_HEAD lines.
MAX_FUNCTION_LINES = 60
MAX_CLASS_LINES = 400
MAX_MODULE_LINES = 600
LONG_MODULE_HEAD = 10


def _long_functions_in(src: str) -> list[str]:
    lines = src.splitlines()
    tree = ast.parse(src)
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        body = node.body
        first = body[0]
        if isinstance(first, ast.Expr) and isinstance(getattr(first, "value", None), ast.Constant):
            body = body[1:] or body  # the docstring does not count
        start, end = body[0].lineno, node.end_lineno or node.lineno
        if end - start + 1 <= MAX_FUNCTION_LINES:
            continue
        around = lines[max(0, node.lineno - 3) : body[0].lineno]
        if not any(ln.strip().lower().startswith("# long") or "# long:" in ln.lower() for ln in around):
            out.append(f"{node.name} (line {node.lineno}, {end - start + 1} lines)")
    return out


def _long_classes_in(src: str) -> list[str]:
    return [
        f"{n.name} (line {n.lineno}, {n.end_lineno - n.lineno + 1} lines)"
        for n in ast.walk(ast.parse(src))
        if isinstance(n, ast.ClassDef) and (n.end_lineno or n.lineno) - n.lineno + 1 > MAX_CLASS_LINES
    ]


def _too_big(path: Path) -> list[str]:
    src = path.read_text(encoding="utf-8")
    lines = src.splitlines()
    out = []
    long_ok = any(ln.strip().lower().startswith("# long:") for ln in lines[:LONG_MODULE_HEAD])
    if len(lines) > MAX_MODULE_LINES and not long_ok:
        out.append(
            f"{len(lines)} lines: a module is at most {MAX_MODULE_LINES} (split it along a seam, or say why it is "
            "one concept in a '# long: reason' at its top)"
        )
    long = _long_functions_in(src)
    if long:
        out.append(f"functions over {MAX_FUNCTION_LINES} lines without a '# long: reason' comment: {long}")
    big = _long_classes_in(src)
    if big:
        out.append(f"classes over {MAX_CLASS_LINES} lines (one job per class): {big}")
    return out


def test_functions_classes_and_modules_stay_small():
    bad = _over_tree(_too_big)
    assert not bad, _report("too big", bad)


# ------------------------------------------------------------------------------------------------- rooms
MAX_FOLDER_MODULES = 15
# The tests of a subpackage may import its private modules; a test file names its subpackage by its file name's
# prefix (test_horizon_* tests crtraj.control.horizon). A test file not listed here reaches a subpackage only
# through its public names, as a user does.
TEST_OWNERS = {
    "test_horizon_": ("crtraj.control.horizon",),
    "test_replan": ("crtraj.control.loop",),
    "test_loop_": ("crtraj.control.loop",),
    "test_reference_": ("crtraj.control.loop",),
    "test_tracking": ("crtraj.control.tracking",),
    "test_compiled_tracking": ("crtraj.control.tracking",),
    "test_startup": ("crtraj.control.tracking",),  # python-control loads only when the controller is built
    "test_steer": ("crtraj.planning.steer",),
    "test_compiled_solvers": ("crtraj.planning.nlp",),
    "test_planner": ("crtraj.planning.planners",),
    "test_compiled_paths": ("crtraj.planning.planners",),
    "test_ompl_log": ("crtraj.planning.planners",),
    "test_compiled_validity": ("crtraj.planning.validity",),
    "test_vectorised_checks": ("crtraj.planning.validity",),
    "test_broad_phase": ("crtraj.planning.validity",),
    "test_paper_mode": ("crtraj.planning.validity",),
    "test_compiled_ik": ("crtraj.planning.ik",),
    "test_stream": ("crtraj.hardware.stream",),
    "test_dynamixel": ("crtraj.hardware.dynamixel",),
    "test_homing": ("crtraj.hardware.dynamixel",),
    "test_drive_mode": ("crtraj.hardware.dynamixel",),
    "test_sim_dynamixel": ("crtraj.hardware.dynamixel",),
    "test_faults": ("crtraj.hardware.dynamixel",),  # the link's faults, injected into its SDK port
    "dxl_helpers": ("crtraj.hardware.dynamixel",),
    "test_device": ("crtraj.hardware.sim",),
    "devlink": ("crtraj.hardware.sim",),
    "test_ros_": ("crtraj.hardware.ros",),
    "test_cosserat": ("crtraj.model.cosserat",),
    "test_rod_": ("crtraj.model.cosserat",),
    "test_calibrate": ("crtraj.model.calibration", "crtraj.app.lab"),
    "test_verify_cosserat": ("crtraj.app.lab",),
    "test_viz_live": ("crtraj.viz.live",),
    "test_geometry": ("crtraj.world.geometry",),
}


def _packages(root: Path = ROOT) -> list[Path]:
    return sorted(p.parent for p in (root / "crtraj").rglob("__init__.py") if "__pycache__" not in p.parts)


def _dotted(path: Path, root: Path = ROOT) -> str:
    rel = path.relative_to(root).with_suffix("")
    return ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)


def _private_home(module: str) -> str | None:
    """The package whose private module `module` is (crtraj.a.b._x -> crtraj.a.b), or None for a public one."""
    parts = module.split(".")
    for i, part in enumerate(parts[1:], start=1):
        if part.startswith("_") and not part.startswith("__"):
            return ".".join(parts[:i])
    return None


def _is_module(package: str, name: str, root: Path = ROOT) -> bool:
    """Whether ``from package import name`` imports a module of crtraj (not a name defined in one)."""
    folder = root.joinpath(*package.split("."))
    return package.split(".")[0] == "crtraj" and ((folder / f"{name}.py").is_file() or (folder / name).is_dir())


def _private_reaches(code: str, allowed: set[str], root: Path = ROOT) -> list[str]:
    """Imports in `code` of a private module of a crtraj package not in `allowed` (nor inside one of them):
    ``import crtraj.a._x``, ``from crtraj.a._x import N`` and ``from crtraj.a import _x`` alike."""
    out = []
    for node in ast.walk(ast.parse(code)):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            targets = [node.module]
            targets += [f"{node.module}.{a.name}" for a in node.names if _is_module(node.module, a.name, root)]
        for name in targets:
            home = _private_home(name) if name.split(".")[0] == "crtraj" else None
            if home and not any(home == a or home.startswith(a + ".") for a in allowed):
                out.append(f"line {node.lineno}: {name}")
    return sorted(set(out))


def _allowed_for(path: Path, root: Path = ROOT) -> set[str]:
    """The packages whose private modules `path` may import: its own package (a module of crtraj), the
    subpackages its name owns (a test), none (an example, a doc)."""
    rel = path.relative_to(root)
    if rel.parts[0] == "crtraj":
        return {_dotted(path.parent / "__init__.py", root)}
    if rel.parts[0] == "tests":
        return {pkg for prefix, pkgs in TEST_OWNERS.items() if path.stem.startswith(prefix) for pkg in pkgs}
    return set()


def _python_of(path: Path) -> list[str]:
    text = path.read_text(encoding="utf-8")
    return [text] if path.suffix == ".py" else re.findall(r"```python\n(.*?)```", text, flags=re.S)


def _crowded(root: Path = ROOT) -> dict[str, int]:
    """Folders of crtraj holding more than MAX_FOLDER_MODULES modules: {folder: modules}."""
    counts = {
        str(pkg.relative_to(root)): len([p for p in pkg.glob("*.py") if p.stem not in ("__init__", "__main__")])
        for pkg in _packages(root)
    }
    return {k: n for k, n in counts.items() if n > MAX_FOLDER_MODULES}


def _has_all(init: Path) -> bool:
    """Whether the __init__ assigns __all__ (a list, or the first of lazy_exports' three values)."""
    for node in _tree(init).body:
        for target in node.targets if isinstance(node, ast.Assign) else []:
            names = target.elts if isinstance(target, ast.Tuple) else [target]
            if any(isinstance(n, ast.Name) and n.id == "__all__" for n in names):
                return True
    return False


def _without_all(root: Path = ROOT) -> list[str]:
    return [str(pkg.relative_to(root)) for pkg in _packages(root) if not _has_all(pkg / "__init__.py")]


def _reaches(root: Path = ROOT) -> dict[str, list[str]]:
    """Every private-module import from outside its package, in the library, the tests (but a subpackage's own,
    TEST_OWNERS), the examples and the docs' Python: {file: imports}."""
    sources = [
        *_modules(root),
        *sorted((root / "tests").glob("*.py")),
        *sorted((root / "examples").glob("*.py")),
        *sorted((root / "docs").rglob("*.py")),
        *sorted((root / "docs").rglob("*.md")),
        *[p for p in [root / "README.md"] if p.is_file()],
    ]
    bad = {}
    for path in sources:
        found = [r for code in _python_of(path) for r in _private_reaches(code, _allowed_for(path, root), root)]
        if found:
            bad[str(path.relative_to(root))] = found
    return bad


def test_no_folder_holds_more_than_15_modules():
    """A concept of several modules is a subpackage, not a file-name prefix in a crowded folder."""
    assert not _crowded(), f"folders over {MAX_FOLDER_MODULES} modules (make rooms): {_crowded()}"


def test_every_package_lists_its_public_names():
    assert not _without_all(), f"packages without __all__: {_without_all()}"


def test_no_private_module_is_reached_from_outside_its_package():
    bad = _reaches()
    assert not bad, _report("private modules imported from outside their package", bad)


def test_the_room_checks_can_fail():
    """A reach into another package's private module is caught in each spelling; its own package and an owner
    may; a public import is fine."""
    code = (
        "import crtraj.a._x\nfrom crtraj.b._y import N\nfrom crtraj.control.horizon import _build\n"
        "from crtraj.d import Public\n"
    )
    reaches = ["line 1: crtraj.a._x", "line 2: crtraj.b._y", "line 3: crtraj.control.horizon._build"]
    assert _private_reaches(code, set()) == reaches
    assert _private_reaches(code, {"crtraj.a", "crtraj.b", "crtraj.control.horizon"}) == []
    assert _private_home("crtraj.control.horizon._build") == "crtraj.control.horizon"
    assert _private_home("crtraj.control.horizon") is None
    owned = _allowed_for(ROOT / "tests" / "test_horizon_stage.py")
    assert owned == {"crtraj.control.horizon"} and _allowed_for(ROOT / "examples" / "x.py") == set()


# ------------------------------------------------------------------------- every rule, on a planted tree
def _plant(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


def test_every_rule_fails_on_a_planted_violation(tmp_path):
    """A small repository with one violation of each rule (and, beside each, the same thing done within the
    rules): every whole-tree check reports exactly the planted offenders, each in its one message."""
    ok = '__all__ = ["A"]\n'
    fn = "".join(f"    x{i} = {i}\n" for i in range(MAX_FUNCTION_LINES + 1))
    methods = "".join(f"    def m{i}(self):\n        return {i}\n" for i in range(MAX_CLASS_LINES // 2))
    lines = "".join(f"X{i} = {i}\n" for i in range(MAX_MODULE_LINES))
    crowd = {f"crtraj/world/crowd/m{i}.py": "A = 1\n" for i in range(MAX_FOLDER_MODULES + 1)}
    _plant(
        tmp_path,
        {
            "crtraj/__init__.py": ok,
            "crtraj/loose.py": "A = 1\n",
            "crtraj/extra/__init__.py": ok,
            "crtraj/model/__init__.py": ok,
            "crtraj/model/up.py": "import numpy\nfrom crtraj.planning import A\n",
            "crtraj/model/relative.py": "from . import up\n",
            "crtraj/model/hidden.py": "def f():\n    import json\n    from ompl import base\n    return json, base\n",
            "crtraj/model/long_fn.py": f"def f():\n{fn}",
            "crtraj/model/long_fn_ok.py": f"# long: one table of cases\ndef f():\n{fn}",
            "crtraj/model/big_class.py": f"class C:\n{methods}",
            "crtraj/model/big.py": '"""A module."""\n' + lines,
            "crtraj/model/big_ok.py": '"""A module."""\n# long: one concept\n' + lines,
            "crtraj/planning/__init__.py": "A = 1\n",
            "crtraj/planning/down.py": "from crtraj.model import A\nfrom crtraj.world._p import B\n",
            "crtraj/world/__init__.py": ok,
            "crtraj/world/_p.py": "B = 1\n",
            "crtraj/world/own.py": "from crtraj.world._p import B\nfrom crtraj.world import _p\n",
            "crtraj/world/crowd/__init__.py": ok,
            **crowd,
            "crtraj/control/horizon/__init__.py": ok,
            "crtraj/control/horizon/_build.py": "B = 1\n",
            "tests/test_horizon_x.py": "from crtraj.control.horizon._build import B\n",
            "tests/test_other.py": "from crtraj.control.horizon import _build\n",
            "examples/ex.py": "import crtraj.world._p\n",
            "docs/page.md": "Text.\n\n```python\nfrom crtraj.world._p import B\n```\n\n```python\nimport crtraj\n```\n",
        },
    )
    assert _unlayered(tmp_path) == ["extra", "loose.py"]
    up = _over_tree(_upward_imports, tmp_path)
    assert up == {
        "model/up.py": ["line 2: crtraj.planning (planning) from model"],
        "model/relative.py": ["line 1: relative import"],
    }
    assert _over_tree(_hidden_imports, tmp_path) == {"model/hidden.py": ["line 2: json in f()"]}
    big = _over_tree(_too_big, tmp_path)
    assert sorted(big) == ["model/big.py", "model/big_class.py", "model/long_fn.py"]
    assert big["model/long_fn.py"][0].endswith(f"['f (line 1, {MAX_FUNCTION_LINES + 1} lines)']")
    assert big["model/big_class.py"][0].endswith(f"['C (line 1, {MAX_CLASS_LINES + 1} lines)']")
    assert big["model/big.py"][0].startswith(f"{MAX_MODULE_LINES + 1} lines: a module is at most")
    assert _crowded(tmp_path) == {"crtraj/world/crowd": MAX_FOLDER_MODULES + 1}
    assert _without_all(tmp_path) == ["crtraj/planning"]
    assert _reaches(tmp_path) == {
        "crtraj/planning/down.py": ["line 2: crtraj.world._p"],
        "tests/test_other.py": ["line 1: crtraj.control.horizon._build"],
        "examples/ex.py": ["line 1: crtraj.world._p"],
        "docs/page.md": ["line 1: crtraj.world._p"],
    }
    # one message names every offender
    message = _report("too big", big)
    assert all(name in message for name in big)
