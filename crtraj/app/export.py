"""Use case: export a robot's symbolic model as .casadi files, C source and a library (`crtraj export`)."""

from __future__ import annotations

import argparse

from crtraj.core.errors import InputError
from crtraj.io.problem import load_robot
from crtraj.model.export import export_model
from crtraj.model.kinematics import MAX_BATCH, MAX_POINTS, Model


def export_command(args: argparse.Namespace) -> int:
    """`crtraj export ...` (arguments from `crtraj.cli`); returns the exit code."""
    # sizes first: a huge --batch or --points would build (or allocate) for minutes before failing
    if not 1 <= args.batch <= MAX_BATCH:
        raise InputError(f"--batch: must be in [1, {MAX_BATCH}], got {args.batch}")
    if args.points is not None and not 2 <= args.points <= MAX_POINTS:
        raise InputError(f"--points: must be in [2, {MAX_POINTS}], got {args.points}")
    robot = load_robot(args.robot)
    model = Model(robot, n_points=args.points)
    rep = export_model(model, args.out, batch=args.batch, compile=not args.no_compile)
    print(f"exported robot '{robot.name}' ({robot.n_segments} segments, {model.n_points} points) to {rep.out_dir}")
    print(f"  {len(rep.casadi_files)} .casadi files, C source {rep.c_source.name}")
    print(f"  library: {rep.library.name if rep.library else 'none'} ({rep.compiler_message})")
    print(f"  manifest: {rep.out_dir / 'manifest.json'}")
    return 0
