"""Modules imported on first use: a heavy dependency that only some commands need costs the others nothing.

``control = lazy_module("control")`` at a module's top binds a module object whose real import runs
when one of its attributes is first read (`importlib.util.LazyLoader`). Start-up matters because every
command is a new process: python-control alone pulls in SciPy's signal and stats packages and
matplotlib's pyplot, about half a second, which `crtraj plan` never uses.
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType


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
