"""Tracking controller cost per control period and closed-loop settling.

Run: python benchmarks/tracking_step.py [--calls 2000] [--repeats 7]

Prints the median / p90 time of one `TrackingController.step` (configuration
and tip mode), one `ServoModel.advance`, the one-off LQR design, and how a
closed loop settles from an offset on the default robot. The budget is the
20 ms control period of the replanner loop.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from crtraj.control.tracking import TrackingOptions
from crtraj.control.tracking._controller import TrackingController
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model

ROBOT = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"


def _per_call(fn, calls: int, repeats: int) -> np.ndarray:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn()
        out.append((time.perf_counter() - t0) / calls)
    return np.array(out)


def _row(name: str, s: np.ndarray, budget: float) -> None:
    med, p90 = np.median(s), np.percentile(s, 90)
    print(f"{name:<34} median {med * 1e6:8.1f} us   p90 {p90 * 1e6:8.1f} us   budget/median {budget / med:8.0f}x")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    model = Model(load_robot(ROBOT))
    rng = np.random.default_rng(0)
    x = np.array([0.3, -0.2, 0.1, 0.4, -30.0])
    ref = x + rng.normal(0, [0.05, 0.05, 0.05, 0.05, 5.0])
    budget = TrackingOptions().dt
    print(f"robot {model.robot.name}, nx={model.nx}, nq={model.nq}, control period {budget * 1e3:.0f} ms")
    t0 = time.perf_counter()
    ctl = TrackingController(model)
    print(f"{'controller build + LQR design':<34} {(time.perf_counter() - t0) * 1e3:8.2f} ms (once)")
    periods = iter(0.02 + 1e-9 * np.arange(20 * args.repeats))  # a new dt each call: no cache hits
    design = _per_call(lambda: ctl.design(next(periods)), 20, args.repeats)
    print(f"{'LQR design (c2d + dlqr) per dt':<34} median {np.median(design) * 1e3:8.2f} ms (cached per dt)")
    q = ctl.initial_command(x)
    _row("step, configuration mode", _per_call(lambda: ctl.step(x, q, ref), args.calls, args.repeats), budget)
    tip = TrackingController(model, TrackingOptions(mode="tip"))
    _row("step, tip mode (DLS, eq. 17)", _per_call(lambda: tip.step(x, q, ref), args.calls, args.repeats), budget)
    _row("servo advance", _per_call(lambda: ctl.servo.advance(q, q, 0.02), args.calls, args.repeats), budget)
    for name, c in (("configuration", ctl), ("tip", tip)):
        run = c.simulate(x, ref, 300)
        settled = int(np.nonzero(run.tip_error > 0.01)[0][-1]) + 1
        s = run.summary()
        print(
            f"closed loop ({name} mode): initial tip error {run.tip_error[0]:.1f} mm, "
            f"< 0.01 mm after {settled} periods ({settled * c.options.dt:.2f} s), "
            f"final {s['final_tip_error_mm']:.2e} mm, rate-limited periods {s['rate_limited_steps']}"
        )
    d = ctl.design()
    print(f"closed-loop spectral radius {np.max(np.abs(d.eigenvalues)):.3f} per period")


if __name__ == "__main__":
    main()
