"""Fault matrix on the simulated Dynamixel bus (issue 38): the worst tendon tension for each fault, and the motion
after each kill.

Run: python benchmarks/faults.py [--times 8] [--kills 50] [--seed 38] [--each]

Sim 1 (``crtraj plan problems/paper_static.toml --seed 1``) streamed to the 7 simulated servos of
problems/robots/cdsr2.toml (tendons capped at max_tension 20 N, min_tension 2 N, each holding a 7 N pretension),
homed at the plan's start, in process on one virtual clock (the same run on any machine, under any load). Each
fault is injected at `--times` random (seeded) times of the stream:

- jam: spool s1c1 jams (its shaft stops, its current rises to its mode's cap);
- cut: tendon s1c3 is cut (its load drops to 0);
- heat: servo s2c2 reads 76 deg C (5 below its Temperature Limit);
- supply: the supply sags to 9.9 V (0.4 V above Min Voltage Limit);
- unplug: the USB adapter is pulled out (every port call fails as pyserial's do);
- kill: the host dies (SIGKILL: nothing more reaches the bus);
- Ctrl-C: SIGINT (the stream brakes with its verified stop, then holds).

The tension of a tendon is its servo's true Present Current (read from the simulator at every packet, and every
1 ms for 1 s after the stream ended, or after the bus fell silent until every servo rests) through the torque
constant and the spool radius (`ForceCaps.tension`); "worst" is the largest over every tendon, time and run.

Then `--kills` kills (seeded random times), all from one stream (`crtraj.hardware.faults.SilencePort`), each
stop measured densely (`measure_stop`, 1 ms): the largest deceleration over the limit, the stop distance (spools
in rad, the stage in mm, from the silence to rest) and the smallest clearance of the body (beyond D_sf) on the
way. Prints date, machine and load first.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import datetime
import io
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

from crtraj.app.devices import admit_result
from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import HomingState, home_in_place, open_dynamixel, robot_chain, state_path
from crtraj.hardware.dynamixel import _link as link
from crtraj.hardware.dynamixel._safety import ForceCaps
from crtraj.hardware.faults import FaultPort, SilencePort, measure_stop
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.io.problem import load_robot

ROOT = Path(__file__).resolve().parent.parent
PRETENSION = 20  # units (53.8 mA): 7.0 N on a 10 mm spool of the XM430-W210
HOLD = 1.0  # s sampled after a stream ended


class Clock(VirtualClock):
    """Virtual time the simulated servos also read; with `interrupt_at`, one Ctrl-C when it first sleeps past it."""

    def __init__(self, start: float, interrupt_at: float | None = None) -> None:
        super().__init__(start)
        self.interrupt_at = interrupt_at

    def __call__(self) -> float:
        return self.now()

    def sleep(self, s: float) -> None:
        super().sleep(s)
        if self.interrupt_at is not None and self.now() >= self.interrupt_at:
            self.interrupt_at = None
            raise KeyboardInterrupt


def _setup(tmp: Path):
    """(plan, robot file, taut chain homed at the plan's start, device time reached, admitted motion)."""
    plan = tmp / "plan.json"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["plan", str(ROOT / "problems/paper_static.toml"), "--seed", "1", "--out", str(plan)]) == 0
    text = (ROOT / "problems/robots/cdsr2.toml").read_text()
    text = text.replace("max_tension = 20.0 ", "min_tension = 2.0\nmax_tension = 20.0 ")
    robot_file = tmp / "robot.toml"
    robot_file.write_text(text)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    motion = admit_result(str(plan), str(robot_file), rate=100.0)
    chain = robot_chain(robot, acts, motion.values[0])
    homed, reached = home_in_place(robot, acts, chain, motion.values[0])
    HomingState(tuple(homed)).save(state_path(robot_file))
    for i in chain.ids[:6]:
        chain.set_load(i, PRETENSION)
    return robot_file, chain, reached, motion


def _stream(port, clock, motion, robot_file):
    """Stream `motion` through `port`; the report."""
    link.port_factory = lambda sdk, name: port
    state = HomingState.load(state_path(robot_file))
    tr = open_dynamixel("dynamixel:///dev/sim", motion.actuators, homing=state, clock=clock, warn=lambda m: None)
    return Streamer(tr, motion.actuators, StreamOptions(rate=motion.rate), None, clock=clock).run_path(motion)


def _worst(caps: ForceCaps, currents: np.ndarray) -> float:
    """The largest tendon tension (N) of (m, n) currents (units): spools only (the stage carries no tendon)."""
    spools = np.abs(np.atleast_2d(currents))[:, :6]
    return max(caps.tension(k, spools[:, k].max()) for k in range(6))


def _faulted(name: str, at: float, setup) -> tuple[str, float]:
    """One run with fault `name` at `at` s after the start: (the stream's status, the worst tension, N)."""
    robot_file, chain0, reached, motion = setup
    caps = ForceCaps(motion.actuators)
    chain = copy.deepcopy(chain0)
    faults = {
        "jam": lambda c, t: c.jam(1, t),
        "cut": lambda c, t: c.cut(3, t),
        "heat": lambda c, t: c.heat(5, 76, t),
        "supply": lambda c, t: c.supply(9.9, t),
        "unplug": lambda c, t: None,
        "Ctrl-C": lambda c, t: None,
    }
    clock = Clock(reached, reached + at if name == "Ctrl-C" else None)
    port = FaultPort(chain, clock, reached + at, faults[name], name="/dev/sim")
    if name == "unplug":
        port.unplug_at = reached + at
    rep = _stream(port, clock, motion, robot_file)
    seen = np.array([c for t, c in port.currents if t >= reached + at] or [np.zeros(7)])
    after = measure_stop(chain, motion.actuators, clock.now(), horizon=HOLD, currents=True).current
    return rep.status, max(_worst(caps, seen), _worst(caps, after))


def _kills(setup, n: int, seed: int, each: bool) -> tuple[float, list]:
    """`n` kills of one stream: (the worst tension, N; a row per kill)."""
    robot_file, chain0, reached, motion = setup
    caps = ForceCaps(motion.actuators)
    rng = np.random.default_rng(seed)
    offsets = np.sort(rng.uniform(0.5, float(motion.stamps[-1]), n))
    clock = Clock(reached)
    port = SilencePort(copy.deepcopy(chain0), clock, [reached + x for x in offsets], name="/dev/sim")
    rep = _stream(port, clock, motion, robot_file)
    assert rep.status == "done", rep.message
    ver = motion.verifier
    rows, worst = [], 0.0
    for at, first, chain in port.silent:

        def clearance(values, t=first - reached):
            configs, _ = ver.configurations(values)
            return ver.scene.clearance_points(ver.model.points(configs), t, inflate=motion.robot.body_radius)

        m = measure_stop(chain, motion.actuators, first, clearance=clearance, currents=True)
        worst = max(worst, _worst(caps, m.current))
        rows.append((at - reached, float(np.max(m.decel)), float(np.max(m.distance[:6])), float(m.distance[6])))
        rows[-1] += (m.clearance, m.rest, m.tripped)
        if each:
            print("  kill at {:6.2f} s: decel/limit {:.3f}, stop {:.4f} rad / {:.3f} mm, clearance {:.2f} mm, "
                  "rest after {:.3f} s, watchdog {}".format(*rows[-1]))  # fmt: skip
    return worst, rows


def main_() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--times", type=int, default=8, help="random times per fault (default 8)")
    ap.add_argument("--kills", type=int, default=50, help="kills measured after one stream (default 50)")
    ap.add_argument("--seed", type=int, default=38)
    ap.add_argument("--each", action="store_true", help="print every kill's row")
    args = ap.parse_args()
    print(f"date {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; {platform.node()}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores; load {os.getloadavg()[0]:.2f}; "
          f"python {sys.version.split()[0]}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        setup = _setup(Path(tmp))
        duration = float(setup[3].stamps[-1])
        rng = np.random.default_rng(args.seed)
        print(f"sim 1: {duration:.2f} s; tendon cap 20 N, min 2 N, pretension 7.0 N; {args.times} times per fault\n")
        print("| fault | stream status | worst tendon tension (N) |")
        print("| --- | --- | --- |")
        for name in ("jam", "cut", "heat", "supply", "unplug", "Ctrl-C"):
            runs = [_faulted(name, float(at), setup) for at in rng.uniform(0.5, duration - 0.5, args.times)]
            statuses = ", ".join(sorted({s for s, _ in runs}))
            print(f"| {name} | {statuses} | {max(t for _, t in runs):.2f} |")
        worst, rows = _kills(setup, args.kills, args.seed, args.each)
        print(f"| kill ({args.kills} times) | (host dead: the Bus Watchdog stops) | {worst:.2f} |\n")
        a = np.array([r[:6] for r in rows])
        print(f"after {len(rows)} kills (the bus silent from the kill on; 1 ms samples until rest):\n")
        print("| | max deceleration / limit | stop distance, spools (rad) | stop distance, stage (mm) | "
              "min clearance beyond D_sf (mm) | rest after (s) |")  # fmt: skip
        print("| --- | --- | --- | --- | --- | --- |")
        for what, f in (("worst", np.max), ("median", np.median)):
            pick = f(a, axis=0)
            if what == "worst":
                pick[4] = a[:, 4].min()
            print(f"| {what} | {pick[1]:.3f} | {pick[2]:.4f} | {pick[3]:.3f} | {pick[4]:.2f} | {pick[5]:.3f} |")
        print(f"\nevery servo's watchdog tripped after every kill: {all(r[6] for r in rows)}")


if __name__ == "__main__":
    main_()
