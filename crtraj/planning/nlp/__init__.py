"""The NLP layer shared by steer and horizon: the `NLPBackend` interface and CasADi functions compiled to C once.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.planning.nlp._backend": ("NLPBackend",),
        "crtraj.planning.nlp._compiled": (
            "CODEGEN_QP",
            "CompiledFunction",
            "compiled_library",
        ),
    },
)
