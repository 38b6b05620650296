"""Use case: export a robot's symbolic model as .casadi files, C source and a library (`crtraj export`).

The files are written into a staged folder that replaces ``--out`` as a whole when complete; ``--out`` must be
new, empty or an earlier export (it carries crtraj's export marker), never a folder of other files, nor one
that holds the robot file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from crtraj.core.errors import InputError
from crtraj.core.fileio import StagedDir, check_output_dir, check_outputs_not_inputs
from crtraj.io.problem import load_robot
from crtraj.model.export import export_model
from crtraj.model.kinematics import MAX_BATCH, MAX_POINTS, Model

# The kind of crtraj's marker on an export folder: a later export may replace a folder that carries it.
EXPORT_KIND = "export"


def export_command(args: argparse.Namespace) -> int:
    """`crtraj export ...` (arguments from `crtraj.cli`); returns the exit code."""
    # sizes first: a huge --batch or --points would build (or allocate) for minutes before failing
    if not 1 <= args.batch <= MAX_BATCH:
        raise InputError(f"--batch: must be in [1, {MAX_BATCH}], got {args.batch}")
    if args.points is not None and not 2 <= args.points <= MAX_POINTS:
        raise InputError(f"--points: must be in [2, {MAX_POINTS}], got {args.points}")
    out = Path(args.out)
    check_outputs_not_inputs({"--out": out}, {"--robot": args.robot})
    robot = load_robot(args.robot)
    check_output_dir(out, "--out", frozenset(), EXPORT_KIND)
    model = Model(robot, n_points=args.points)
    # every file goes into a staged folder that replaces --out as a whole only when the export is complete
    with StagedDir(out, frozenset(), EXPORT_KIND) as stage:
        rep = export_model(model, stage.path, batch=args.batch, compile=not args.no_compile)
        stage.commit()
    print(f"exported robot '{robot.name}' ({robot.n_segments} segments, {model.n_points} points) to {out}")
    print(f"  {len(rep.casadi_files)} .casadi files, C source {rep.c_source.name}")
    print(f"  library: {rep.library.name if rep.library else 'none'} ({rep.compiler_message})")
    print(f"  manifest: {out / 'manifest.json'}")
    return 0
