"""The package layout is the data flow: no import from a lower layer to a higher one, no hidden imports.

Layers, low to high (docs/architecture.md): core < model < world < planning < control < hardware < io
< {viz, bench} < app < cli. A module may import its own package and any lower layer, never a higher one
nor a sibling of the same rank (viz and bench stay independent). Imports sit at module level, except for
optional extras whose absence must not break the rest (OMPL, Dask, ROS, Dynamixel, matplotlib in headless
paths): the AST of every module is read, so an import hidden in a function is seen too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parent.parent / "crtraj"

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


def _modules() -> list[Path]:
    return sorted(p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts)


def _layer_of_file(path: Path) -> str:
    rel = path.relative_to(PKG)
    if len(rel.parts) == 1:
        return "cli" if rel.stem == "cli" else ""
    return rel.parts[0]


def _layer_of_module(name: str) -> str | None:
    parts = name.split(".")
    if parts[0] != "crtraj":
        return None
    if len(parts) == 1:
        return ""
    return "cli" if parts[1] == "cli" else parts[1]


def _imported(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
        return [node.module]
    return []


def test_every_package_has_a_layer():
    found = {p.relative_to(PKG).parts[0] for p in _modules() if len(p.relative_to(PKG).parts) > 1}
    assert found <= set(RANK), f"packages without a layer: {sorted(found - set(RANK))}"
    assert not [p for p in _modules() if len(p.relative_to(PKG).parts) == 1 and p.stem not in ("__init__", "cli")]


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_no_upward_or_sideways_import(path):
    own = _layer_of_file(path)
    tree = ast.parse(path.read_text(encoding="utf-8"))
    bad = []
    for node in ast.walk(tree):
        for name in _imported(node):
            layer = _layer_of_module(name)
            if layer is None or layer == own or layer == "":
                continue
            if RANK[layer] >= RANK[own]:
                bad.append(f"line {node.lineno}: {name} ({layer}) from {own or 'crtraj'}")
        if isinstance(node, ast.ImportFrom) and node.level:
            bad.append(f"line {node.lineno}: relative import")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_no_hidden_imports(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    hidden = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            for name in _imported(node):
                if name.split(".")[0] not in OPTIONAL:
                    hidden.append(f"line {node.lineno}: {name} in {fn.name}()")
    assert not hidden, "imports inside functions (move them to module level):\n" + "\n".join(sorted(set(hidden)))


def test_the_checker_sees_an_upward_import(tmp_path):
    # The rule itself must be able to fail: a model module importing the planning layer is caught.
    src = "import numpy\n\ndef f():\n    from crtraj.planning.rrt import RRT\n    return RRT\n"
    tree = ast.parse(src)
    names = [n for node in ast.walk(tree) for n in _imported(node)]
    assert "crtraj.planning.rrt" in names
    assert RANK[_layer_of_module("crtraj.planning.rrt")] > RANK["model"]


# Sizes that keep a module readable (DESIGN.md): a function over this many lines of code (docstring excluded),
# private ones included, carries a comment starting with "# long" just above its def (or on it), saying why; a class
# is at most MAX_CLASS_LINES lines and a module at most MAX_MODULE_LINES lines, with no exception.
MAX_FUNCTION_LINES = 60
MAX_CLASS_LINES = 400
MAX_MODULE_LINES = 600


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


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_long_functions_say_why(path):
    long = _long_functions_in(path.read_text(encoding="utf-8"))
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines without a '# long: reason' comment: {long}"


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PKG)))
def test_classes_and_modules_stay_small(path):
    src = path.read_text(encoding="utf-8")
    n = len(src.splitlines())
    assert n <= MAX_MODULE_LINES, f"{n} lines: a module is at most {MAX_MODULE_LINES} (split it by job)"
    big = _long_classes_in(src)
    assert not big, f"classes over {MAX_CLASS_LINES} lines (one job per class): {big}"


def test_the_size_checks_can_fail():
    # A private 61-line function without a reason, and a 401-line class, are both caught; a reason lets the first pass.
    body = "".join(f"    x{i} = {i}\n" for i in range(61))
    assert _long_functions_in(f"def _f():\n{body}") == ["_f (line 1, 61 lines)"]
    assert _long_functions_in(f"# long: a table of cases\ndef _f():\n{body}") == []
    methods = "".join(f"    def m{i}(self):\n        return {i}\n" for i in range(200))
    assert _long_classes_in(f"class C:\n{methods}") == ["C (line 1, 401 lines)"]
