"""Streamer timing against the simulated device on 127.0.0.1: send-interval jitter, round trip, tick cost.

Run: python benchmarks/stream_timing.py [--seconds 5] [--rate 100]
Prints medians / p90 / max from one run. Timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.limits import LimitsGate
from crtraj.hardware.protocol import MOVE, Frame
from crtraj.hardware.sim_device import SimDevice
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.io.problem import load_robot
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


def _stats(name: str, a: np.ndarray, unit: str = "ms", scale: float = 1e3) -> None:
    a = np.asarray(a) * scale
    print(
        f"{name:<38} median {np.median(a):8.3f} {unit}   p90 {np.percentile(a, 90):8.3f} {unit}   "
        f"max {np.max(a):8.3f} {unit}   (n={a.size})"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rate", type=float, default=100.0)
    args = ap.parse_args()
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    acts = Actuators.from_robot(robot)
    x0, x1 = robot.straight(0.0), np.array([0.3, -0.2, 0.1, 0.4, -10.0])
    s = np.linspace(0, 1, 21)
    X = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    # a synthetic motion among no obstacles, admitted as a successful plan of this robot would be
    record = MotionRecord("", "plan", "success", True, True, 0, 0, robot, Scene(), args.seconds * s, robot.cables(X))
    motion = admit(record, acts, rate=args.rate)  # verified at the rate it is streamed at
    path = motion.path

    # per-tick CPU cost of the limits gate + frame encoding (no I/O)
    stamps, values = path.sample(args.rate)
    gate = LimitsGate(acts, 1.0 / args.rate)
    gate.reset(values[0])
    t = time.perf_counter()
    for k in range(values.shape[0]):
        assert gate.check(MOVE, values[k], stamps[k]) is None
        Frame(MOVE, k + 1, stamps[k], values[k]).encode()
        gate.commit(MOVE, values[k])
    per_tick = (time.perf_counter() - t) / values.shape[0]
    t = time.perf_counter()
    for _ in range(20):
        gate.check_path(values, stamps)
    preflight = (time.perf_counter() - t) / 20

    with tempfile.TemporaryDirectory() as tmp, SimDevice(acts) as dev:
        log = Path(tmp) / "run.jsonl"
        rep = Streamer.open(dev.url, acts, StreamOptions(rate=args.rate), log=log).run_path(motion)
        lines = [json.loads(x) for x in log.read_text().splitlines()]
    tx = [r for r in lines if r["type"] == "tx" and r["kind"] == "move"]
    rx = [r for r in lines if r["type"] == "rx"]
    walls = np.array([r["wall"] for r in tx])
    dt = 1.0 / args.rate
    jitter = np.abs(np.diff(walls) - dt)
    # round trip: from sending seq to the first telemetry acknowledging it (includes telemetry period)
    rx_w = np.array([r["wall"] for r in rx])
    rx_ack = np.array([r["ack"] for r in rx])
    rtt = []
    for r in tx:
        j = np.flatnonzero(rx_ack >= r["seq"])
        if j.size:
            rtt.append(rx_w[j[0]] - r["wall"])
    print(
        f"stream: {rep.status}, {rep.moves} set-points at {args.rate:g} Hz over {args.seconds:g} s, "
        f"final error {rep.final_error:.2g}, late ticks {rep.late_ticks}"
    )
    _stats("|send interval - period|", jitter)
    _stats("send -> telemetry ack (incl. 10 ms period)", np.array(rtt))
    _stats("gate check + encode per frame", np.array([per_tick]), "us", 1e6)
    _stats(f"preflight check of {values.shape[0]} set-points", np.array([preflight]), "ms", 1e3)


if __name__ == "__main__":
    main()
