"""Use case: run the simulated servo controller on 127.0.0.1 until Ctrl-C or --duration (`crtraj sim-device`)."""

from __future__ import annotations

import argparse

from crtraj.core import interrupt
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.sim import Faults, SimDevice
from crtraj.hardware.transport import parse_hostport
from crtraj.io.problem import load_robot


def sim_device_command(args: argparse.Namespace) -> int:
    """`crtraj sim-device ...` (arguments from `crtraj.cli`); returns the exit code."""
    host, port = parse_hostport(args.udp, "--udp")
    robot = load_robot(args.robot)
    if robot.actuators is None:
        raise InputError(f"{args.robot}: robot.actuators: missing; add a [robot.actuators] table")
    faults = Faults(args.drop, args.corrupt, args.delay, args.disconnect_after, args.disconnect_for)
    actuators = Actuators.from_robot(robot)
    dev = SimDevice(
        actuators, port, host=host, tau=args.tau, telemetry_rate=args.telemetry_rate, faults=faults, seed=args.seed
    )
    print(
        f"sim-device listening on {dev.url} ({actuators.n} actuators: {', '.join(actuators.names)}; "
        f"tau {args.tau:g} s)",
        flush=True,
    )
    try:
        dev.serve(args.duration)
    except KeyboardInterrupt:
        interrupt.acknowledge()  # Ctrl-C is a server's normal end: exit 0
    finally:
        st = dev.state()
        dev.stop()
    counts = ", ".join(f"{k} {st[k]}" for k in ("received", "applied", "crc_errors", "missed", "stale", "refused"))
    print(f"sim-device stopped: {counts}", flush=True)
    return 0
