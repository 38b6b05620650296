"""Streamer timing against the simulated device on 127.0.0.1: send-interval jitter, round trip, tick cost;
with --dynamixel, against simulated Dynamixel servos on a pseudo-terminal through the official SDK.

Run: python benchmarks/stream_timing.py [--seconds 5] [--rate 100]
     python benchmarks/stream_timing.py --dynamixel [--seconds 5] [--rates 100,200,300] [--bauds 1000000,4000000]
                                        [--return-delays 250,0]
Prints medians / p90 / max from one run. Timings depend on the machine's load.

The Dynamixel figures: the 7 servos of problems/robots/cdsr2.toml at 1 and 4 Mbaud, `crtraj sim-dynamixel` in its
own process (as real servos are their own hardware), with Return Delay Time 250 (the factory default, 500 us per
reply) and 0 (what crtraj sets at connect). A pty has no baud rate: the simulator delays every reply by the wire
time of the request and the replies (10 bits per byte, one transfer at a time) plus each servo's Return Delay
Time, so the rate is the one a real bus allows (with a 1 ms USB latency timer). Per tick
the streamer does one Group Sync Write (49 bytes) and one Group Sync Read of 9 bytes per servo (21 + 7 x 20
bytes): 210 bytes, 2.1 ms of wire time, so at most ~470 set-points/s on the wire alone.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import MotionRecord, admit
from crtraj.hardware.limits import LimitsGate
from crtraj.hardware.protocol import MOVE, Frame
from crtraj.hardware.sim._device import SimDevice
from crtraj.hardware.stream import StreamOptions
from crtraj.hardware.stream._streamer import Streamer
from crtraj.hardware.transport import TransportError
from crtraj.io.problem import load_robot
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


def _stats(name: str, a: np.ndarray, unit: str = "ms", scale: float = 1e3) -> None:
    a = np.asarray(a) * scale
    print(
        f"{name:<38} median {np.median(a):8.3f} {unit}   p90 {np.percentile(a, 90):8.3f} {unit}   "
        f"max {np.max(a):8.3f} {unit}   (n={a.size})"
    )


def _record(robot, seconds: float) -> MotionRecord:
    """A synthetic motion among no obstacles, as a successful plan of this robot would be."""
    x0, x1 = robot.straight(0.0), np.array([0.3, -0.2, 0.1, 0.4, -10.0])
    s = np.linspace(0, 1, 21)
    X = x0 + (x1 - x0) * (0.5 - 0.5 * np.cos(np.pi * s))[:, None]
    return MotionRecord("", "plan", "success", True, True, 0, 0, robot, Scene(), seconds * s, robot.cables(X))


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process `pid` (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _start_sim(baud: int) -> tuple[subprocess.Popen, str]:
    """`crtraj sim-dynamixel` at `baud` in its own process; (process, device path)."""
    sim = subprocess.Popen(
        [sys.executable, "-m", "crtraj.cli", "sim-dynamixel", "--pty", "--duration", "600", "--baud", str(baud)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    line = sim.stdout.readline()
    print(line.strip())
    return sim, re.search(r"/dev/pts/\d+", line).group(0)


def _one_rate(args, robot, acts: Actuators, dev: str, baud: int, delay: int, rate: float, sim_pid: int):
    """Stream at `rate` over the link (Return Delay Time `delay`); print one row; (host, sim) CPU ms per tick."""
    from crtraj.hardware.dynamixel._link import open_dynamixel  # the optional extra: only for this mode

    motion = admit(_record(robot, args.seconds), acts, rate=rate)
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "run.jsonl"
        try:
            # its own simulator, started in place: no power-up to check (that check is timed nowhere here)
            url = f"dynamixel://{dev}?baud={baud}"
            tr = open_dynamixel(url, acts, return_delay=delay, stop_torque="off", power_up_check=False)
        except TransportError as exc:  # a loaded machine: the simulator missed its replies
            print(f"{rate:6.0f}   no connection: {exc}")
            return None
        cpu0, sim0 = time.process_time(), _cpu_seconds(sim_pid)
        rep = Streamer(tr, acts, StreamOptions(rate=rate), log).run_path(motion, approach=True)
        host_cpu, sim_cpu = time.process_time() - cpu0, _cpu_seconds(sim_pid) - sim0
        tx = [json.loads(x) for x in log.read_text().splitlines()]
    walls = np.array([r["wall"] for r in tx if r["type"] == "tx" and r.get("kind") == "move"])
    if len(walls) < 2 or not tr.timings:
        print(f"{rate:6.0f}   no stream: {rep.status}: {rep.message}")
        return None
    achieved = (len(walls) - 1) / (walls[-1] - walls[0])
    reads = np.array([t[1] for t in tr.timings]) * 1e3
    jit = np.abs(np.diff(walls) - 1.0 / rate) * 1e3
    host, dev_cpu = host_cpu / rep.frames * 1e3, sim_cpu / rep.frames * 1e3
    print(
        f"{rate:6.0f} {achieved:8.1f}/s {rep.late_ticks:6d} {np.median(reads):13.2f} ms "
        f"{np.percentile(reads, 90):7.2f} {reads.max():7.2f} {np.median(jit):22.3f} ms "
        f"{np.percentile(jit, 90):7.3f}   ({rep.status}, {rep.moves} set-points, "
        f"{tr.counts['timeouts']} timeouts; CPU per tick: host {host:.2f} ms, simulator {dev_cpu:.2f} ms)"
    )
    return host, dev_cpu


def dynamixel(args: argparse.Namespace, robot, acts: Actuators) -> None:
    """Achieved set-point rate, sync-read round trip and send jitter over the Dynamixel link, per bus rate,
    Return Delay Time and stream rate."""
    for baud in (int(b) for b in args.bauds.split(",")):
        sim, dev = _start_sim(baud)
        try:
            for delay in (int(d) for d in args.return_delays.split(",")):
                wire = 210 * 10 / baud * 1e3 + 7 * delay * 2e-3  # bytes on the wire + 7 return delays, ms
                print(f"-- {baud} baud, Return Delay Time {delay} ({delay * 2} us): {wire:.2f} ms per tick modelled")
                print(
                    f"{'rate':>6} {'achieved':>9} {'late':>6} {'read rtt median':>16} {'p90':>7} {'max':>7} "
                    f"{'|interval-period| median':>25} {'p90':>7}"
                )
                cost = [
                    _one_rate(args, robot, acts, dev, baud, delay, float(r), sim.pid) for r in args.rates.split(",")
                ]
                cost = [c for c in cost if c is not None]
                if cost:
                    host, _ = np.median(np.array(cost), axis=0)
                    print(f"   real servos (replies in hardware): about {1e3 / (wire + host):.0f} set-points/s")
        finally:
            sim.terminate()
            sim.wait(10)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--dynamixel", action="store_true", help="time the Dynamixel link instead (needs the extra)")
    ap.add_argument("--rates", default="100,200,300", help="with --dynamixel: stream rates to try, Hz")
    ap.add_argument("--bauds", default="1000000,4000000", help="with --dynamixel: bus rates to try")
    ap.add_argument("--return-delays", default="250,0", help="with --dynamixel: Return Delay Times (2 us units)")
    args = ap.parse_args()
    robot = load_robot(ROOT / "problems" / "robots" / "cdsr2.toml")
    acts = Actuators.from_robot(robot)
    print(time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), f"load average {os.getloadavg()[0]:.1f}")
    if args.dynamixel:
        dynamixel(args, robot, acts)
        return
    record = _record(robot, args.seconds)
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
