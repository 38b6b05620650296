"""The steer's backends: chosen once from the options, the IPOPT rescue re-solves the same problem, warm starts."""

from __future__ import annotations

import numpy as np
import pytest
from test_steer import sim1_scene, witness_problems

from crtraj.planning.nlp import NLPBackend
from crtraj.planning.steer._backends import DlsBackend, IpoptBackend, RescuedBackend, SqpBackend
from crtraj.planning.steer._options import SteerOptions
from crtraj.planning.steer._solver import SteerSolver


@pytest.mark.parametrize(
    ("options", "kind", "name"),
    [
        ({}, IpoptBackend, "ipopt"),
        ({"solver": "sqp", "fallback": False}, SqpBackend, "sqp"),
        ({"solver": "sqp"}, RescuedBackend, "sqp>ipopt"),
        ({"solver": "dls"}, DlsBackend, "dls"),
    ],
)
def test_backend_is_chosen_once_from_the_options(model, options, kind, name):
    """The options pick one backend class when the solver is built; every solve goes through that object."""
    solver = SteerSolver(model, 2, SteerOptions(**options))
    backend = solver.backend
    assert type(backend) is kind and backend.name == name
    assert isinstance(backend, NLPBackend)
    if kind is RescuedBackend:
        assert type(backend.primary) is SqpBackend and type(backend.rescue) is IpoptBackend
    scene = sim1_scene()
    for xp, target in witness_problems(model, scene, 3, seed=5):
        r = solver.solve(xp, target, scene)
        assert r.is_success(), r.message
        assert r.solver == ("sqp" if kind is RescuedBackend else name)
    assert solver.backend is backend


def test_rescue_is_ipopt_on_the_sqp_problem(model):
    """A failed sqp solve is re-solved by IPOPT from the same start: the result is IPOPT's own solve from that
    start, the iterations add up and the message says why."""
    scene = sim1_scene()
    xp, target = witness_problems(model, scene, 1, seed=23)[0]
    # one sqp iteration cannot converge from the predictor; IPOPT gets 100
    rescued = SteerSolver(model, 2, SteerOptions(solver="sqp", max_iter=1, ipopt=(("max_iter", 100),)))
    alone = SteerSolver(model, 2, SteerOptions(solver="sqp", max_iter=1, fallback=False))
    ipopt = SteerSolver(model, 2, SteerOptions(max_iter=1, ipopt=(("max_iter", 100),)))
    r = rescued.solve(xp, target, scene)
    first = alone.solve(xp, target, scene)
    direct = ipopt.solve(xp, target, scene, x0=rescued.predict(xp, target))
    assert not first.converged and first.solver == "sqp" and first.iterations == 1
    assert r.solver == "sqp>ipopt" and r.is_success(), r.message
    assert r.message.startswith(f"sqp: {first.solver_status} after 1 iterations; re-solved by IPOPT. reached")
    np.testing.assert_array_equal(r.x, direct.x)
    assert r.iterations == 1 + direct.iterations and r.solver_status == direct.solver_status


def test_reset_warm_start_gives_a_cold_solve(model):
    """After `reset_warm_start` a solve equals a fresh solver's first solve; without it, IPOPT starts from the
    previous multipliers (warm_start_init_point) and takes other iterates."""
    scene = sim1_scene()
    (xa, ta), (xb, tb) = witness_problems(model, scene, 2, seed=31)
    opts = SteerOptions(warm_start=True)
    fresh = SteerSolver(model, 2, opts).solve(xb, tb, scene)
    solver = SteerSolver(model, 2, opts)
    solver.solve(xa, ta, scene)
    warm = solver.solve(xb, tb, scene)
    solver.solve(xa, ta, scene)
    solver.reset_warm_start()
    again = solver.solve(xb, tb, scene)
    np.testing.assert_array_equal(again.x, fresh.x)
    assert again.iterations == fresh.iterations
    assert not np.array_equal(warm.x, fresh.x)


def test_given_backend_is_used(model):
    """A backend passed to the constructor is the one that solves (here DLS under the IPOPT options): none
    is built from the options."""
    dls = SteerSolver(model, 2, SteerOptions(solver="dls"))
    scene = sim1_scene()
    xp, target = witness_problems(model, scene, 1, seed=41)[0]
    solver = SteerSolver(model, 2, SteerOptions(), backend=dls.backend)
    assert solver.backend is dls.backend
    r = solver.solve(xp, target, scene)
    assert r.solver == "dls"
    np.testing.assert_array_equal(r.x, SteerSolver(model, 2, SteerOptions(solver="dls")).solve(xp, target, scene).x)
