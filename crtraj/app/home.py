"""Use case: home a Dynamixel robot after its power-up (`crtraj home --dynamixel DEV`).

Reads the robot file's ``[robot.actuators]`` and ``[robot.homing]``
(`crtraj.hardware.homing_spec`), connects without the absolute-position check,
runs `crtraj.hardware.homing.Homer` (hard-stop moves or operator-confirmed
marks, then the spools' unwrap), verifies every reading against its limits and
writes the homing state (`crtraj.hardware.homing_state`) atomically next to the
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
from crtraj.hardware.dynamixel import DEFAULT_BAUD, open_dynamixel
from crtraj.hardware.homing import Homer
from crtraj.hardware.homing_spec import read_homing
from crtraj.hardware.homing_state import HomingState, state_path
from crtraj.io.problem import load_robot


def confirm_on_stdin(text: str) -> bool:
    """Show `text` and wait for Enter; False when standard input is closed (nobody to confirm)."""
    print(f"{text} [Enter]", flush=True)
    line = sys.stdin.readline()
    return line != ""


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
    check_outputs_not_inputs({"--state": out}, {"--robot": args.robot})
    check_output_file(out, "--state")
    old = HomingState.load(out)
    url = f"dynamixel://{args.dynamixel}?baud={args.baud or DEFAULT_BAUD}"
    link = open_dynamixel(url, acts, power_up_check=False)  # homing makes the positions absolute itself
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
