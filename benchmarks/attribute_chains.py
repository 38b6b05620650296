"""Count attribute chains that reach more than one dot into another object's part (issue 37).

A chain is a maximal ``a.b.c...`` expression (an `ast.Attribute` whose parent is not one). It reaches into a
part when it has three attributes after ``self``/``cls`` (``self.part.sub.attr``) or two after any other local
name (``obj.part.attr``). Chains rooted in a module name bound by an import (``np.linalg.norm``) are not
counted; neither is a chain whose first attribute is ``__class__`` or a name ending in ``options``/``opts``
when it reads one option field (frozen option data, not a part). Prints date, machine and load, then the
count per file and the total; ``--list`` prints every chain. Usage::

    python benchmarks/attribute_chains.py [--list] [paths ...]   # default: crtraj/
"""

from __future__ import annotations

import ast
import os
import platform
import sys
import time
from pathlib import Path


def _imported(tree: ast.Module) -> set[str]:
    """Names bound by import statements anywhere in the module."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.update(a.asname or a.name for a in node.names)
    return names


def _chain(node: ast.Attribute) -> tuple[str, list[str]] | None:
    """(root name, attributes) of a chain rooted in a plain name, else None (a call, subscript, ...)."""
    attrs: list[str] = []
    cur: ast.expr = node
    while isinstance(cur, ast.Attribute):
        attrs.append(cur.attr)
        cur = cur.value
    if not isinstance(cur, ast.Name):
        return None
    return cur.id, attrs[::-1]


def reaches(path: Path) -> list[tuple[int, str]]:
    """(line, chain text) of every chain in `path` that reaches more than one dot into a part."""
    tree = ast.parse(path.read_text(), str(path))
    modules = _imported(tree)
    inner = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or id(node) in inner:
            continue
        got = _chain(node)
        if got is None:
            continue
        root, attrs = got
        if root in modules:
            continue
        own = root in ("self", "cls")
        into = attrs[1:] if own else attrs
        if len(into) < 2:
            continue
        if into[0].endswith(("options", "opts")) and len(into) == 2:
            continue
        found.append((node.lineno, ".".join([root, *attrs])))
    return found


def main(argv: list[str]) -> int:
    show = "--list" in argv
    roots = [Path(a) for a in argv if a != "--list"] or [Path("crtraj")]
    print(f"# {time.strftime('%Y-%m-%d %H:%M:%S %Z')} {platform.node()} load {os.getloadavg()}")
    total = 0
    for root in roots:
        for path in sorted(root.rglob("*.py")) if root.is_dir() else [root]:
            hits = reaches(path)
            if not hits:
                continue
            total += len(hits)
            print(f"{len(hits):4d} {path}")
            if show:
                for line, text in hits:
                    print(f"       {line}: {text}")
    print(f"total {total}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
