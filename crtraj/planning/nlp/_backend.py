"""One interface for the ways crtraj solves a parametric NLP that is built once (toppra's `SolverWrapper` idea).

The steer step (`planning.steer`) and the receding-horizon step (`control.horizon`) each build their NLP once and
then solve it many times with new parameters (obstacles, targets, the previous configuration). How a solve is
carried out (IPOPT, an SQP with the daqp QP solver, generated C, a damped-least-squares step, or one backend with a
second as a rescue) is a strategy chosen once when the solver is built, not an if-branch taken on every call. Each
way is one class that satisfies `NLPBackend`; the owning solver keeps exactly one instance.

A query and a solution are small frozen dataclasses of the owning solver (its units: mm, rad, s), so a backend's
`solve` takes one argument and returns one object instead of many positional values.
"""

from __future__ import annotations

from typing import Protocol, TypeVar, runtime_checkable

QueryT = TypeVar("QueryT", contravariant=True)
SolutionT = TypeVar("SolutionT", covariant=True)


@runtime_checkable
class NLPBackend(Protocol[QueryT, SolutionT]):
    """A way to solve one built NLP for one query.

    `name` is the backend's label as reported in results and `describe()` output (for example "ipopt", "sqp",
    "sqp>ipopt", "compiled", "dls"). `solve` never raises for a solver that did not converge: it returns a
    solution whose status says so; it raises `crtraj.core.errors.InputError` only for a query that is malformed.
    """

    name: str

    def solve(self, query: QueryT) -> SolutionT:
        """Solve the NLP for `query` and return the solver's solution (status always set)."""
        ...
