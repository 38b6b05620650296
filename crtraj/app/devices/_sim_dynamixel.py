"""Use case: run simulated Dynamixel servos on a pseudo-terminal until Ctrl-C or --duration (`crtraj sim-dynamixel`).

The servos are the robot file's bus (`[robot.actuators]` ids, model numbers and declared Drive Modes); each
``hard_stop`` of ``[robot.homing]`` is a mechanical stop at its reference
(`crtraj.hardware.dynamixel._sim_robot`). ``--at RESULT`` starts them homed at the result's first set-point: they
power up there, crtraj's own homing runs against them (the stage presses its stop, the spools are unwrapped)
and they move back, so the servos present what a homed robot presents (homed markers lit, the Homing Offsets
the homing computed), and the homing state it produced is written where ``crtraj home`` writes it (``--state``,
default beside ``--robot``). ``--power-cycle-at T`` power-cycles every servo after T s (the readings then fall
within one turn). Prints the device path to pass to ``crtraj stream RESULT --dynamixel PATH``.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from types import MappingProxyType
from typing import Any

import numpy as np

from crtraj.core import interrupt
from crtraj.core.errors import InputError
from crtraj.core.fileio import check_output_file, check_outputs_not_inputs
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import (
    HW_ERROR_NAMES,
    HomingState,
    ServoChain,
    SimDynamixel,
    home_in_place,
    robot_chain,
    state_path,
)
from crtraj.io.problem import load_robot
from crtraj.io.results import read_result

# voltage, overheating, encoder, shock, overload
_BITS = MappingProxyType({name.split()[-1]: bit for bit, name in HW_ERROR_NAMES})


def _hardware_error(text: str, ids: tuple[int, ...]) -> tuple[int, int]:
    """``ID:NAME`` (e.g. ``3:overload``) as (id, bits); one-line `InputError` otherwise."""
    dxl_id, sep, name = text.partition(":")
    # isascii + isdecimal: str.isdigit is true for superscripts, which int() refuses
    if not sep or not (dxl_id.isascii() and dxl_id.isdecimal()) or int(dxl_id) not in ids or name not in _BITS:
        raise InputError(
            f"--hardware-error: expected ID:NAME with ID one of {', '.join(map(str, ids))} and NAME one of "
            f"{', '.join(_BITS)}; got {text!r}"
        )
    return int(dxl_id), _BITS[name]


def _start(args: argparse.Namespace, acts: Actuators) -> np.ndarray | None:
    """The actuator values (rad, mm) of ``--at``'s first set-point; None without ``--at``."""
    if not args.at:
        if args.state is not None:
            raise InputError("--state: only with --at (the homing state of the servos it starts homed)")
        return None
    q = read_result(args.at).q
    if q is None:
        raise InputError(f"{args.at}: waypoints[0].q: missing (the actuation to start the servos at)")
    return acts.command(q[0])


def _homed(
    args: argparse.Namespace, robot: Any, acts: Actuators, chain: ServoChain, start: np.ndarray
) -> Callable[[], float]:
    """Home `chain` where it stands and write the homing state (``--state``, default beside ``--robot``); the
    device clock (s) of the served chain, continuing from the time the homing took."""
    out = state_path(args.robot) if args.state is None else args.state
    check_outputs_not_inputs({"--state": out}, {"--robot": args.robot, "--at": args.at})
    check_output_file(out, "--state")
    old = HomingState.load(out)
    homed, reached = home_in_place(robot, acts, chain, start)
    old.merged(homed).save(out)
    for s in homed:
        print(f"homed {s.name} (id {s.id}) by {s.method}: homing offset {s.offset} ticks; homing state: {out}")
    origin = time.monotonic() - reached
    return lambda: time.monotonic() - origin


def sim_dynamixel_command(args: argparse.Namespace) -> int:
    """`crtraj sim-dynamixel --pty ...` (arguments from `crtraj.cli`); returns the exit code."""
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(f"{args.robot}: robot.actuators: missing; add a [robot.actuators] table")
    acts = Actuators.from_robot(robot)
    if acts.bus is None:
        raise InputError(f"{args.robot}: robot.actuators: no Dynamixel ids (add id, ticks_per_rev, model per servo)")
    bus = acts.bus
    start = _start(args, acts)
    faults = [_hardware_error(h, bus.ids) for h in args.hardware_error or ()]
    for m in args.missing or ():
        if m not in bus.ids:
            raise InputError(f"--missing: {m} is not one of the robot's ids ({', '.join(map(str, bus.ids))})")
    chain = robot_chain(robot, acts, start, tau=args.tau, baud=args.baud)
    clock = _homed(args, robot, acts, chain, start) if start is not None else time.monotonic
    for m in args.missing or ():
        chain.remove(m)
    for dxl_id, bits in faults:
        chain.set_hardware_error(dxl_id, bits)
    for flag, value in (("--silent-after", args.silent_after), ("--corrupt-after", args.corrupt_after)):
        if value is not None and not 0 <= value <= 10**9:
            raise InputError(f"{flag}: must be in 0..1000000000 packets, got {value}")
    chain.silent_after, chain.corrupt_after = args.silent_after, args.corrupt_after
    at = args.power_cycle_at
    if at is not None and not (math.isfinite(at) and 0 <= at <= 1e6):
        raise InputError(f"--power-cycle-at: must be in 0..1000000 s, got {at}")
    sim = SimDynamixel(chain, clock=clock, wire_time=not args.no_wire_time, power_cycle_at=at)
    wire = "wire time of a real bus modelled" if not args.no_wire_time else "no wire time"
    print(
        f"sim-dynamixel on {sim.path} ({len(bus.ids)} servos, ids {', '.join(map(str, bus.ids))}, "
        f"{args.baud} baud, {wire})",
        flush=True,
    )
    try:
        sim.serve(args.duration)
    except KeyboardInterrupt:
        interrupt.acknowledge()  # Ctrl-C is a server's normal end: exit 0
    finally:
        sim.stop()
    c = chain.counts
    print(
        f"sim-dynamixel stopped: {c['packets']} packets, {c['replies']} replies, {c['sync_writes']} sync writes, "
        f"{sim.bad_packets} bad",
        flush=True,
    )
    return 0
