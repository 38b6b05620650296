"""Use case: home a Dynamixel robot after its power-up (`crtraj home --dynamixel DEV`).

Reads the robot file's ``[robot.actuators]`` and ``[robot.homing]``
(`crtraj.hardware.dynamixel._homing_spec`), connects without the absolute-position check,
runs `crtraj.hardware.dynamixel.Homer` (hard-stop moves or operator-confirmed
marks, then the spools' unwrap), verifies every reading against its limits and
writes the homing state (`crtraj.hardware.dynamixel._homing_state`) atomically next to the
robot file. A failure is one line; the state file is then left as it was. The
torque goes off when the command ends (`DynamixelTransport.close`).
"""

from __future__ import annotations

import argparse
import sys

from crtraj.core.clock import default_clock
from crtraj.core.errors import InputError
from crtraj.core.fileio import check_output_file, check_outputs_not_inputs
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import (
    DEFAULT_BAUD,
    Homer,
    HomingState,
    ReadOnlyLink,
    homing_command,
    open_dynamixel,
    proven,
    read_homing,
    read_stop,
    state_path,
)
from crtraj.io.problem import load_robot


def confirm_on_stdin(text: str) -> bool:
    """Show `text` and wait for Enter; False when standard input is closed (nobody to confirm)."""
    print(f"{text} [Enter]", flush=True)
    line = sys.stdin.readline()
    return line != ""


def _check(url: str, acts: Actuators, state: HomingState, command: str) -> int:
    """`crtraj home --check`: one line per actuator, proven or why not; exit 0 when all are proven, else 1 with
    one stderr line naming them. Nothing is written to the servos or the state file."""
    link = ReadOnlyLink(url, acts)
    try:
        rows = proven(link, acts, state, command)
    finally:
        link.close()
    for name, why in rows:
        print(f"{name}: proven" if why is None else f"{name}: not proven: {why}")
    bad = [name for name, why in rows if why is not None]
    if bad:
        print(f"crtraj: home --check: position not proven for {', '.join(bad)}; run {command}", file=sys.stderr)
        return 1
    return 0


def home_command(args: argparse.Namespace) -> int:
    """`crtraj home --dynamixel DEV ...` (arguments from `crtraj.cli`); returns the exit code."""
    if not args.dynamixel:
        raise InputError("--dynamixel: must not be empty")
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(f"{args.robot}: robot.actuators: missing; add a [robot.actuators] table")
    acts = Actuators.from_robot(robot)
    if acts.bus is None:
        raise InputError(f"{args.robot}: robot.actuators: no Dynamixel ids (add id, ticks_per_rev, model per servo)")
    specs = dict(read_homing(robot, acts))
    out = state_path(args.robot) if args.state is None else args.state
    url = f"dynamixel://{args.dynamixel}?baud={args.baud or DEFAULT_BAUD}"
    if getattr(args, "check", False):
        return _check(url, acts, HomingState.load(out), homing_command(args.robot, args.dynamixel))
    check_outputs_not_inputs({"--state": out}, {"--robot": args.robot})
    check_output_file(out, "--state")
    old = HomingState.load(out)
    # homing makes the positions absolute itself; the bus watchdog guards it as it guards a stream
    link = open_dynamixel(url, acts, power_up_check=False, bus_watchdog=read_stop(robot).bus_watchdog)
    try:
        homer = Homer(link, acts, specs, default_clock(), confirm_on_stdin)
        homer.check()  # before anything moves
        homed = homer.run()
    finally:
        link.close()
    old.merged(homed).save(out)
    for s in homed:
        print(f"homed {s.name} (id {s.id}, model {s.model}) by {s.method}: homing offset {s.offset} ticks")
    print(f"homing state: {out}")
    return 0
