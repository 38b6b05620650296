"""Stream a trajectory to the simulated device, then drive it step by step as a replanner would.

Run: python examples/stream_sim.py        (about 6 s; everything stays on 127.0.0.1)

1. Builds a plan-style result (waypoints with t and q) from the real model:
   the straight robot bends both segments and lowers its base by 8 mm in 3 s.
2. Admits it (`crtraj.admit_result`) and streams it with
   `Streamer.run_path` to a `SimDevice` that drops 5 % of the datagrams and
   corrupts 2 %, and prints the report.
3. Streams a live sequence with the control-step API (`start`,
   `send_setpoint`, `finish`, `close`): each step sends the next set-point
   of a circling bend, 0.3 s ahead of the stream.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import crtraj
from crtraj.core import atomic_write_json, to_jsonable

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out" / "stream_demo"


def demo_result(robot, model, duration=3.0, n=16):
    """A result file dict: the straight pose to a bent one along a cosine time law."""
    x0 = robot.straight(0.0)
    x1 = np.array([0.35, -0.25, -0.2, 0.45, -8.0])
    s = np.linspace(0.0, 1.0, n)
    X = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    Q, P = model.cables(X), model.tip_position(X)
    wps = [{"t": duration * s[k], "tip": P[k], "x": X[k], "q": Q[k]} for k in range(n)]
    doc = {
        "kind": "plan",
        "robot": robot.to_dict(),
        "scene": crtraj.Scene().to_dict(),
        "status": "success",
        "success": True,
    }
    return to_jsonable(doc | {"waypoints": wps})


def main() -> None:
    robot = crtraj.load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    model = crtraj.Model(robot)
    acts = crtraj.Actuators.from_robot(robot)
    result = demo_result(robot, model)
    atomic_write_json(OUT / "result.json", result)
    print(f"wrote {OUT / 'result.json'}; try: crtraj stream {OUT / 'result.json'} --dry-run {OUT / 'frames.bin'}")

    with crtraj.SimDevice(acts, faults=crtraj.Faults(drop=0.05, corrupt=0.02), seed=1) as dev:
        # --- 1. a whole planned trajectory
        motion = crtraj.admit_result(result)  # refuses failed, colliding, ... results
        rep = crtraj.Streamer.open(dev.url, acts, log=OUT / "run_path.jsonl").run_path(motion)
        print(
            f"run_path: {rep.status} ({rep.message}); {rep.moves} set-points, device {rep.device}, "
            f"final error {rep.final_error:.2g}"
        )

        # --- 2. control steps, as `crtraj replan --stream` does
        opts = crtraj.StreamOptions(prebuffer=0.3)
        with crtraj.Streamer.open(dev.url, acts, opts, log=OUT / "live.jsonl") as s:
            s.start()  # handshake; s.position is where the device stands
            x_start = robot.config(acts.actuation(s.position))
            t0 = time.monotonic()
            for k in range(201):  # 2 s at 100 Hz
                t = 0.01 * k
                w = 0.5 - 0.5 * np.cos(np.pi * t / 2.0)  # starts and ends at rest
                x = x_start.copy()
                x[2:4] += 0.2 * w * np.array([np.cos(np.pi * w), np.sin(np.pi * w)])
                s.send_setpoint(t, robot.cables(x))
                time.sleep(max(0.0, t0 + t - time.monotonic()))  # a real replanner spends this time solving
            s.finish()
            s.wait(5.0)
            rep = s.close()
        print(
            f"live:     {rep.status} ({rep.message}); {rep.moves} set-points, {rep.holds} holds, "
            f"max tick lateness {rep.max_lateness * 1000:.1f} ms"
        )
    print(f"run records: {OUT / 'run_path.jsonl'}, {OUT / 'live.jsonl'}")


if __name__ == "__main__":
    main()
