"""The ``crtraj`` command.

Each subcommand is a small function that parses its arguments, calls the
library, prints a short summary and returns an exit code. User errors
(`InputError`) print one line ``crtraj: error: ...`` and exit 2; a failed
plan or solve exits 1 with its status printed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from crtraj import __version__
from crtraj.errors import InputError

DEFAULT_ROBOT = Path(__file__).resolve().parent.parent / "problems" / "robots" / "cdsr2.toml"


def _resolve_robot(arg: str | None) -> Path:
    if arg:
        return Path(arg)
    return DEFAULT_ROBOT


# --------------------------------------------------------------------- export
def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write the symbolic model as .casadi files, C source and a shared library",
        description="Export every model function (FK, backbone, Jacobians, cable maps, limits) "
        "as CasADi .casadi files, generated C, a compiled library and manifest.json.",
    )
    p.add_argument("--robot", help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument("--out", default="out/export", help="output folder (default: out/export)")
    p.add_argument("--points", type=int, default=None, help="backbone points (default: robot.collision_points)")
    p.add_argument("--batch", type=int, default=1024, help="configurations per backbone_map call (default 1024)")
    p.add_argument("--no-compile", action="store_true", help="write C source only, do not compile")
    p.set_defaults(func=_cmd_export)


def _cmd_export(args: argparse.Namespace) -> int:
    from crtraj.model import Model
    from crtraj.problem import load_robot

    if args.batch < 1:
        raise InputError(f"--batch: must be >= 1, got {args.batch}")
    robot = load_robot(_resolve_robot(args.robot))
    model = Model(robot, n_points=args.points)
    rep = model.export(args.out, batch=args.batch, compile=not args.no_compile)
    print(
        f"exported robot '{robot.name}' ({robot.n_segments} segments, {model.n_points} points) to {rep.out_dir}"
    )
    print(f"  {len(rep.casadi_files)} .casadi files, C source {rep.c_source.name}")
    print(f"  library: {rep.library.name if rep.library else 'none'} ({rep.compiler_message})")
    print(f"  manifest: {rep.out_dir / 'manifest.json'}")
    return 0


# Subcommands register themselves here in display order.
_COMMANDS: tuple[Callable[[argparse._SubParsersAction], None], ...] = (_add_export,)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crtraj",
        description="Safety-constrained motion planning for cable-driven continuum robots.",
    )
    parser.add_argument("--version", action="version", version=f"crtraj {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"crtraj: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crtraj: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
