"""The parsers of the commands that talk to a device or stand in for one: `stream` (verified set-points to a
robot), `home`, `ros-bridge`, and the simulators and replays a user runs instead of hardware (`sim-device`,
`sim-dynamixel`, `feed-replay`). Each sets ``use_case`` to its entry in `crtraj.cli._USE_CASES`."""

from __future__ import annotations

import argparse

from crtraj.cli.paths import DEFAULT_ROBOT


def add_stream(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stream",
        help="stream a planned trajectory to the robot's servos (UDP, serial or a dry-run file)",
        description="Convert the result's waypoint actuation q(t) to servo angles and stage positions "
        "([robot.actuators]), interpolate it at a fixed rate and send time-stamped set-points. Every frame is "
        "checked against the position, velocity and acceleration limits before it leaves; a violation is "
        "refused, never clamped. A watchdog holds when telemetry stops. Every run is recorded as JSON lines.",
    )
    p.add_argument("result", help="result JSON written by crtraj plan or crtraj replan")
    dest = p.add_mutually_exclusive_group(required=True)
    dest.add_argument("--udp", metavar="HOST:PORT", help="device address (e.g. 127.0.0.1:9870 for crtraj sim-device)")
    dest.add_argument("--serial", metavar="DEV", help="serial port (e.g. /dev/ttyUSB0), COBS-framed frames")
    dest.add_argument("--dry-run", metavar="FILE", help="write the frames to FILE instead of a device (no waiting)")
    dest.add_argument(
        "--dynamixel",
        metavar="DEV",
        help="Dynamixel servos (Protocol 2.0) on this port, e.g. /dev/ttyUSB0 (ids in [robot.actuators]; needs "
        "pip install 'crtraj[dynamixel]')",
    )
    p.add_argument(
        "--baud", type=int, default=None, help="baud rate (default 115200 with --serial, 1000000 with --dynamixel)"
    )
    p.add_argument("--rate", type=float, default=None, help="set-points per second (default 100)")
    p.add_argument("--watchdog", type=float, default=None, help="hold after this long without telemetry, s (0.1)")
    p.add_argument("--robot", help="robot TOML whose [robot.actuators] to use (default: the result's robot)")
    p.add_argument("--problem", help="problem TOML whose [stream] section sets the defaults")
    p.add_argument(
        "--time-scale", type=float, default=1.0, help="play the trajectory this many times slower (0.001..1000)"
    )
    p.add_argument(
        "--approach",
        action="store_true",
        help="first move from the device's position to the trajectory start (straight if that is safe, else "
        "planned in the result's scene; verified like the rest, nothing is sent without a safe one)",
    )
    p.add_argument("--log", help="run record (JSON lines; default out/stream/<result>-<time>.jsonl)")
    p.set_defaults(use_case="stream")


def add_sim_device(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim-device",
        help="run a simulated servo controller on 127.0.0.1 that speaks the stream protocol",
        description="A device for testing crtraj stream without hardware: checks CRC and sequence numbers, "
        "models each servo as a first-order lag, enforces the actuator limits itself, sends telemetry, and "
        "injects faults on request. Runs until Ctrl-C or --duration.",
    )
    p.add_argument("--udp", metavar="127.0.0.1:PORT", required=True, help="address to listen on (port 0: any)")
    p.add_argument(
        "--robot",
        default=str(DEFAULT_ROBOT),
        help="robot TOML with [robot.actuators] (default: problems/robots/cdsr2.toml)",
    )
    p.add_argument("--tau", type=float, default=0.03, help="servo time constant, s (default 0.03)")
    p.add_argument("--telemetry-rate", type=float, default=100.0, help="telemetry frames per second (100)")
    p.add_argument("--drop", type=float, default=0.0, help="probability of dropping each datagram (both ways)")
    p.add_argument("--corrupt", type=float, default=0.0, help="probability of flipping bits in each datagram")
    p.add_argument("--delay", type=float, default=0.0, help="extra latency of incoming frames, s")
    p.add_argument("--disconnect-after", type=float, default=0.0, help="go silent and deaf after this many s")
    p.add_argument("--disconnect-for", type=float, default=0.0, help="... for this many s (0: never disconnect)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fault generator")
    p.add_argument("--duration", type=float, default=None, help="stop after this many s (default: until Ctrl-C)")
    p.set_defaults(use_case="sim-device")


def add_feed_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "feed-replay",
        help="send a problem's obstacle states over UDP, as a motion-capture bridge would",
        description="Samples the problem's obstacles from their own time functions (timestamps are scene time "
        "from the moment the replay starts) and sends them to a `crtraj replan --feed` listener on 127.0.0.1, "
        "with measurement noise, latency, jitter and dropped messages. Runs for --duration or until Ctrl-C.",
    )
    p.add_argument("problem", help="problem TOML whose [scene] obstacles are replayed (their names are the ids)")
    p.add_argument("--udp", metavar="127.0.0.1:PORT", required=True, help="the feed's address (crtraj replan --feed)")
    p.add_argument("--rate", type=float, default=100.0, help="measurements per second and obstacle (100)")
    p.add_argument("--noise", type=float, default=0.3, help="Gaussian noise per coordinate and radius, mm (0.3)")
    p.add_argument("--latency", type=float, default=0.0, help="delay from measuring to sending, s (0)")
    p.add_argument("--jitter", type=float, default=0.0, help="uniform extra delay per message, s (0)")
    p.add_argument("--dropout", type=float, default=0.0, help="probability that a message is never sent (0)")
    p.add_argument("--duration", type=float, default=120.0, help="s of scene time to replay (120)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and dropout generator (0)")
    p.set_defaults(use_case="feed-replay")


def add_sim_dynamixel(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim-dynamixel",
        help="run simulated Dynamixel servos (Protocol 2.0) on a pseudo-terminal and print its path",
        description="Servos for testing crtraj stream --dynamixel without hardware: answers PING, READ, WRITE, "
        "SYNC READ, SYNC WRITE and REBOOT on the X-series control table, moves each servo within its profile "
        "with a first-order lag, and injects faults on request. Runs until Ctrl-C or --duration.",
    )
    p.add_argument("--pty", action="store_true", required=True, help="serve on a new pseudo-terminal (prints it)")
    p.add_argument(
        "--robot",
        default=str(DEFAULT_ROBOT),
        help="robot TOML whose [robot.actuators] ids and models are the servos (default: problems/robots/cdsr2.toml)",
    )
    p.add_argument("--baud", type=int, default=1_000_000, help="the servos' baud rate (default 1000000)")
    p.add_argument("--tau", type=float, default=0.03, help="servo time constant, s (default 0.03)")
    p.add_argument(
        "--at", metavar="RESULT", help="start the servos homed (crtraj home run against them) at this result's start"
    )
    p.add_argument(
        "--state", default=None, help="homing state file --at writes (default: <robot>.homing.json beside it)"
    )
    p.add_argument("--no-wire-time", action="store_true", help="answer at once (default: as slow as a real wire)")
    p.add_argument("--missing", type=int, action="append", metavar="ID", help="fault: this id never answers")
    p.add_argument(
        "--hardware-error", action="append", metavar="ID:NAME", help="fault: set a hardware error bit, e.g. 3:overload"
    )
    p.add_argument("--silent-after", type=int, metavar="N", help="fault: answer nothing after N packets (timeouts)")
    p.add_argument("--corrupt-after", type=int, metavar="N", help="fault: wrong CRC on every reply after N packets")
    p.add_argument(
        "--power-cycle-at", type=float, default=None, metavar="T", help="fault: power-cycle every servo after T s"
    )
    p.add_argument("--duration", type=float, default=None, help="stop after this many s (default: until Ctrl-C)")
    p.set_defaults(use_case="sim-dynamixel")


def add_home(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "home",
        help="home a Dynamixel robot after power-up ([robot.homing]) and write its homing state",
        description="Runs each actuator's homing ([robot.homing]: a current-limited move to a mechanical stop, "
        "or a mark confirmed by hand), unwraps the spools into their limits, verifies every reading and writes "
        "the homing state next to the robot file. crtraj stream --dynamixel and crtraj replan --stream "
        "dynamixel:// refuse servos not homed since their last power-up.",
    )
    p.add_argument("--dynamixel", metavar="DEV", required=True, help="the servos' port, e.g. /dev/ttyUSB0")
    p.add_argument("--baud", type=int, default=None, help="baud rate (default 1000000)")
    p.add_argument("--robot", default=str(DEFAULT_ROBOT), help="robot TOML with [robot.actuators] and [robot.homing]")
    p.add_argument("--state", default=None, help="homing state file (default: <robot>.homing.json beside it)")
    p.add_argument("--check", action="store_true", help="only report whether each position is proven; move nothing")
    p.set_defaults(use_case="home")


def add_ros_bridge(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ros-bridge",
        help="run the replanner on a robot in a ROS 2 graph (the [ros] extra)",
        description="Join a ROS 2 graph ([ros] section: domain, topics, QoS, frame; localhost-only discovery by "
        "default): read the robot's actuator positions (sensor_msgs/JointState) and the live obstacles (SPHERE "
        "markers, visualization_msgs/MarkerArray, and the UDP JSON feed on 127.0.0.1), run the replanner in real "
        "time, and publish each step's verified motion (trajectory_msgs/JointTrajectory) and the body and "
        "obstacles for RViz. A stale obstacle feed holds the robot; a step that fails verification is not sent. "
        "Writes the run as crtraj replan does.",
    )
    p.add_argument("problem", help="problem TOML with a [ros] section (e.g. problems/paper_dynamic.toml)")
    p.add_argument("--out", help="output folder (default out/ros-bridge)")
    p.add_argument("--seed", type=int, default=None, help="random seed of the planner (default: the problem's)")
    p.add_argument("--no-html", action="store_true", help="do not write run.html")
    p.add_argument(
        "--overwrite-failed",
        action="store_true",
        help="let a failed run replace a successful one in --out (default: it is written beside it, as OUT.failed)",
    )
    p.add_argument(
        "--record",
        metavar="FILE",
        help="log every message the bridge sent and received to an MCAP file (CDR, ros2msg schemas; Foxglove)",
    )
    p.add_argument("--quiet", action="store_true", help="print only the summary lines")
    p.set_defaults(use_case="ros-bridge")
