"""The parsers of the lab commands: a calibration dataset (`record`), the fit (`calibrate`), the mechanics
model against PCC (`model compare`) and a result re-checked with it (`verify`). Each sets ``use_case`` to its
entry in `crtraj.cli._USE_CASES`."""

from __future__ import annotations

import argparse

from crtraj.cli.paths import DEFAULT_ROBOT

_PLANT_HELP = (
    "excitation, simulated: film the Cosserat rod (cosserat, or cosserat-weightless) instead of a device; the "
    "markers are read off its shape (0.3 mm capture noise), no device or marker file is needed"
)


def add_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="write a calibration dataset: a stream log joined with a motion-capture marker file",
        description="Join a stream log (crtraj stream --log, crtraj replan --stream) with a marker file (CSV or "
        "JSON lines: timestamp, marker, x, y, z in mm, capture frame) by timestamp, interpolating the actuator "
        "values at the marker times; or, with --excite, stream a built-in excitation motion that covers the "
        "workspace (verified like any motion) to a device, log it, and join it with --markers when given.",
    )
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument("--out", required=True, help="dataset JSON to write")
    p.add_argument("--log", help="stream log (JSON lines) to read, or with --excite to write")
    p.add_argument("--markers", help="marker file (CSV or JSON lines), positions in mm")
    p.add_argument(
        "--marker",
        action="append",
        default=None,
        metavar="NAME=SEGMENT:ARC",
        help="where a marker sits: segment (1-based) and arc length from its start (mm) or 'tip'; repeat per "
        "marker (default: base=1:0, tip1=1:tip, tip=2:tip, the paper's markers)",
    )
    p.add_argument(
        "--time-offset", type=float, default=0.0, help="marker time minus log time, s (default 0: same clock)"
    )
    p.add_argument(
        "--values",
        choices=["measured", "commanded"],
        default="measured",
        help="actuator values from the device's telemetry (default, when the log has any) or the set-points sent",
    )
    p.add_argument("--excite", action="store_true", help="stream the built-in excitation motion first")
    p.add_argument("--duration", type=float, default=None, help="excitation: at least this long, s (default: limits)")
    p.add_argument("--udp", metavar="HOST:PORT", help="excitation: device over UDP")
    p.add_argument("--serial", metavar="DEVICE", help="excitation: device on a serial port")
    p.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    p.add_argument("--dry-run", metavar="FILE", help="excitation: write the frames to FILE instead of a device")
    p.add_argument("--problem", help="excitation: problem file whose [scene] the motion must keep clear of")
    p.add_argument("--plant", metavar="MODEL", help=_PLANT_HELP)
    p.add_argument("--capture-rate", type=float, default=10.0, help="with --plant: frames per second (default 10)")
    p.set_defaults(use_case="record")


def add_calibrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the robot file's lengths, coupling, cable radius, zero offsets and capture frame to a dataset",
        description="One CasADi least-squares NLP (pseudo-Huber loss, exact Jacobians, parameter bounds, held-out "
        "split) fits the chosen parameters to a dataset written by crtraj record. Prints residuals per marker "
        "before and after, the fitted values with standard errors and the parameters the data cannot determine "
        "(held at their prior); writes the calibrated robot file (the original with only the fitted values "
        "changed, plus a [calibration] table), a JSON report and a residual plot.",
    )
    p.add_argument(
        "data", nargs="?", help="calibration dataset (JSON, from crtraj record); or give --log and --markers"
    )
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot TOML file (default: problems/robots/cdsr2.toml)")
    p.add_argument("--out", required=True, help="calibrated robot TOML file to write")
    p.add_argument(
        "--fit",
        default="all",
        help="comma-separated groups: lengths, coupling, cable_radius, zero_offsets, base_z, capture_frame "
        "(default: all)",
    )
    p.add_argument("--report", help="JSON report (default: OUT with .report.json)")
    p.add_argument("--plot", help="residual plot PNG (default: OUT with .residuals.png)")
    p.add_argument("--loss-scale", type=float, default=None, help="pseudo-Huber scale, mm (default 1)")
    p.add_argument("--holdout", type=float, default=None, help="held-out fraction of samples (default 0.2)")
    p.add_argument(
        "--noise",
        type=float,
        default=None,
        metavar="MM",
        help="marker noise per axis, mm, that the held-out residual is judged against (default: estimated from "
        "the data)",
    )
    p.add_argument(
        "--allow-at-bound",
        action="append",
        default=None,
        metavar="NAME",
        help="a parameter that may end at its bound without failing the fit (repeatable)",
    )
    p.add_argument("--log", help="instead of DATA: a stream log, joined with --markers as crtraj record does")
    p.add_argument("--markers", help="with --log: the marker file (CSV or JSON lines, mm)")
    p.add_argument(
        "--marker", action="append", default=None, metavar="NAME=SEGMENT:ARC", help="with --log: as crtraj record"
    )
    p.add_argument("--time-offset", type=float, default=0.0, help="with --log: marker time minus log time, s")
    p.add_argument(
        "--values", choices=["measured", "commanded"], default="measured", help="with --log: as crtraj record"
    )
    p.set_defaults(use_case="calibrate")


def add_model(sub: argparse._SubParsersAction) -> None:  # crtraj model compare ROBOT: PCC against the Cosserat rod
    p = sub.add_parser("model", help="mechanics: compare the PCC model with Cosserat-rod statics")
    c = p.add_subparsers(dest="model_command", metavar="MODEL_COMMAND", required=True).add_parser(
        "compare", help="PCC against Cosserat-rod statics over random configurations (tip and body error, mm)"
    )
    c.add_argument("robot", metavar="ROBOT", help="robot TOML file with a [robot.mechanics] table")
    c.add_argument("--samples", type=int, default=100, help="configurations, 1..100000 (default 100)")
    c.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    c.add_argument("--plot", default=None, help="PNG plot of the discrepancies (default: none)")
    c.set_defaults(use_case="model-compare")


def add_verify(sub: argparse._SubParsersAction) -> None:  # crtraj verify RESULT --model cosserat
    p = sub.add_parser(
        "verify",
        help="re-check a plan or run against its obstacles with the Cosserat-rod shape of every frame",
        description="Re-check a result (crtraj plan or crtraj replan output) against its scene's obstacles, at "
        "each frame's time, with the shape of the Cosserat-rod statics model (driven in the robot file's "
        "[robot.mechanics] actuation mode: commanded cable lengths or fixed tensions; with the robot's weight) as "
        "well as PCC. Prints each model's minimum "
        "clearance (mm, beyond D_sf), where and when, whether D_sf holds, and the extra D_sf the result needs. "
        "Exit 1 when the rod's body touches an obstacle or a rod solve fails (with --strict also when D_sf "
        "does not hold), 2 on bad input.",
    )
    p.add_argument("result", metavar="RESULT", help="result JSON of crtraj plan or crtraj replan")
    p.add_argument("--model", choices=["cosserat"], required=True, help="the mechanics model to verify with")
    p.add_argument("--robot", default=None, help="robot TOML with [robot.mechanics] (default: the result's problem's)")
    p.add_argument("--no-gravity", action="store_true", help="the rod without its weight")
    p.add_argument(
        "--substeps", type=int, default=1, help="frames per waypoint interval, 1..100 (default 1: the waypoints)"
    )
    p.add_argument("--safety-distance", type=float, default=None, help="D_sf to check in mm (default: the scene's)")
    p.add_argument("--strict", action="store_true", help="exit 1 also when D_sf does not hold under the rod")
    p.set_defaults(use_case="verify")
