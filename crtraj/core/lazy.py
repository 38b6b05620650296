"""Modules imported on first use: a heavy dependency that only some commands need costs the others nothing.

``control = lazy_module("control")`` at a module's top binds a module object whose real import runs
when one of its attributes is first read (`importlib.util.LazyLoader`). Start-up matters because every
command is a new process: python-control alone pulls in SciPy's signal and stats packages and
matplotlib's pyplot, about half a second, which `crtraj plan` never uses.

``__all__, __getattr__, __dir__ = lazy_exports(__name__, {...})`` in a package's ``__init__`` gives the
package its public names the same way: each is imported from its defining module when first read (PEP 562).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable, Mapping, Sequence
from types import ModuleType
from typing import Any


def lazy_module(name: str) -> ModuleType:
    """Module `name`, loaded on first attribute access (already imported: that module itself).

    A missing module raises ImportError here, at the binding, as a plain import would.
    """
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        raise ImportError(f"No module named {name!r}")
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


def lazy_exports(
    package: str, homes: Mapping[str, Sequence[str]]
) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``__all__`` and the PEP 562 ``__getattr__`` and ``__dir__`` of `package`, whose public names are
    defined in the modules `homes` lists them under (module -> names).

    A name's module is imported when the name is first read, then the name is bound on the package, so later
    reads cost nothing: ``import crtraj.planning`` stays cheap, and a package's ``__init__`` imports none of
    its modules, so no import cycle can start there. A name listed under two modules raises ValueError (one
    home per public name).
    """
    where: dict[str, str] = {}
    for module, names in homes.items():
        for name in names:
            if name in where:
                raise ValueError(f"{package}: {name!r} is listed under {where[name]} and {module}")
            where[name] = module

    def module_getattr(name: str) -> Any:
        home = where.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(sys.modules[package], name, value)
        return value

    def module_dir() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return list(where), module_getattr, module_dir
