"""The signal cases of issue 36's hostile corpus, reproduced as a user meets them: each long-running command is
started in a folder whose outputs already hold the user's earlier files, then stopped by a signal at a random
wall-clock point after it installed its handler (a probe, not a test: the point moves with the machine's load).

Ctrl-C is delivered as a terminal delivers it, to the command's whole process group (its children get it too);
SIGTERM to the command's process only, as `kill PID` does. Each probe then checks:
- the exit status is 130 (SIGINT) or 143 (SIGTERM), with exactly one stderr line and no traceback;
- no process of the run (every child inherits a marker in its environment, read from /proc) is alive 2 s later;
- every file of the output folder is byte-identical and no temporary or partial file was left there;
- for a stream to the simulated device, the actuator acceleration it reports is within the limits (<= 1.00).

Run: python benchmarks/hostile.py [--trials 3] [--seed 36] [--only record-cosserat,replan-cosserat] [--tree DIR]
(--tree: the checkout whose code and inputs run, e.g. an exported older commit, for a before/after comparison.)
Prints one line per probe and a table of clean / dirty / finished-first per case. Linux only (/proc).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from crtraj.core.tomledit import set_values
from crtraj.hardware.protocol import HOLD, MOVE, PING, Frame, FrameError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Tree:
    """The checkout whose crtraj the commands run, and its inputs (another one: a before/after comparison)."""

    root: Path

    @property
    def paper(self) -> Path:
        return self.root / "problems" / "paper_dynamic.toml"

    @property
    def robot(self) -> Path:
        return self.root / "problems" / "robots" / "cdsr2.toml"

    @property
    def result(self) -> Path:
        return self.root / "tests" / "data" / "plan_cspace_v1.json"

    @property
    def calibration(self) -> Path:
        return self.root / "tests" / "data" / "calibration_small.json"


HANG_S = 600.0  # a hung command: reported dirty
ORPHAN_S = 2.0  # the bound
STARTUP_S = 10.0  # the clock starts at the handler's install, or this long after the start (a crtraj without one)
_ACCEL = re.compile(r"([\d.]+) of their acceleration limit")
_TOL = 1e-6  # the simulated device's own tolerance on a limit


@dataclass(frozen=True)
class Case:
    """One command of the corpus: `args(tree, folder, address)` its arguments after `crtraj`, `outputs` the files
    pre-created in folder/o, `window` (s) the range of the random signal point after the handler is
    installed, `signals` the ones drawn from, `device` True when it streams to a simulated UDP device."""

    name: str
    args: Callable[[Tree, Path, str], list[str]]
    outputs: tuple[str, ...]
    window: tuple[float, float]
    signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)
    device: bool = False


@dataclass
class Probe:
    """The outcome of one signalled run."""

    case: str
    signum: int
    at_s: float
    problems: list[str] = field(default_factory=list)
    finished_first: bool = False
    acceleration: float | None = None  # the largest on the wire, a fraction of the limit
    last_step: float | None = None  # the last frame's speed over what one period of braking stops
    reported: float | None = None  # the command's own report (stdout), a fraction of the limit


def _ros_problem(tree: Tree, folder: Path) -> str:
    """paper_dynamic.toml on a DDS domain of its own (the bridge waits for a robot that never comes)."""
    values = {
        ("robot",): str(tree.robot),
        ("ros", "domain_id"): 100 + os.getpid() % 100,
        ("ros", "start_timeout"): 600.0,
    }
    p = folder / "paper_ros.toml"
    p.write_text(set_values(tree.paper.read_text(), values))
    return str(p)


CASES = (
    Case("verify-cosserat", lambda t, f, a: ["verify", str(t.result), "--model", "cosserat", "--robot", str(t.robot)],
         ("keep.txt",), (0.5, 4.0), (signal.SIGINT,)),
    # the probes: SIGINT at 2 s and at 6 s, the earlier dataset replaced after an exit 0
    Case("record-cosserat", lambda t, f, a: ["record", "--excite", "--plant", "cosserat", "--duration", "300",
                                          "--out", str(f / "o" / "data.json")], ("data.json",), (2.0, 6.0),
         (signal.SIGINT,)),
    Case("replan-cosserat", lambda t, f, a: ["replan", str(t.paper), "--plant", "cosserat",
                                             "--out", str(f / "o" / "run")],
         ("run/run.json", "run/run.png"), (1.0, 10.0), (signal.SIGTERM, signal.SIGINT)),
    Case("replan-pcc", lambda t, f, a: ["replan", str(t.paper), "--out", str(f / "o" / "run")],
         ("run/run.json",), (0.5, 6.0)),
    Case("ros-bridge-record", lambda t, f, a: ["ros-bridge", _ros_problem(t, f), "--out", str(f / "o" / "run"),
                                            "--record", str(f / "o" / "bridge.mcap")],
         ("run/run.json", "bridge.mcap"), (1.0, 6.0), (signal.SIGTERM, signal.SIGINT)),
    Case("replan-stream-udp", lambda t, f, a: ["replan", str(t.paper), "--stream", f"udp://{a}", "--approach",
                                            "--out", str(f / "o" / "live")],
         ("live/run.json",), (8.0, 40.0), (signal.SIGINT,), device=True),
    Case("stream-udp", lambda t, f, a: ["stream", str(t.result), "--udp", a, "--approach", "--log",
                                     str(f / "o" / "stream.jsonl")], ("stream.jsonl",), (1.0, 8.0), device=True),
    Case("calibrate", lambda t, f, a: ["calibrate", str(t.calibration),
                                    "--out", str(f / "o" / "cal.toml")],
         ("cal.toml", "cal.report.json", "cal.residuals.png"), (0.5, 4.0)),
    Case("model-compare", lambda t, f, a: ["model", "compare", str(t.robot), "--samples", "100000",
                                        "--plot", str(f / "o" / "compare.png")], ("compare.png",), (0.5, 4.0)),
    Case("bench", lambda t, f, a: ["bench", "table1", "--workers", "2", "--scenarios", "50", "--counts", "3",
                                "--planners", "cspace", "--time-limit", "1", "--no-progress",
                                "--out", str(f / "o" / "table1")], ("table1/table1.md", "table1/runs.csv"),
         (1.0, 8.0)),
)  # fmt: skip


# ---------------------------------------------------------------------------------------- /proc readers
def marked(mark: str) -> list[int]:
    """Live (not zombie) processes whose environment carries CRTRAJ_HOSTILE_MARK=mark."""
    key = f"CRTRAJ_HOSTILE_MARK={mark}".encode()
    found = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            env = Path(f"/proc/{d}/environ").read_bytes()
            state = Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if key in env.split(b"\0") and state != "Z":
            found.append(int(d))
    return found


def handles_sigterm(pid: int) -> bool:
    """The process installed its own SIGTERM handler (crtraj's interrupt policy: the command runs)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = next(line for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(int(caught.split()[1], 16) >> (signal.SIGTERM - 1) & 1)


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under `folder`, hidden ones too, and its SHA-256."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
        for p in sorted(folder.rglob("*"))
    }


# ------------------------------------------------------------------------------- the wire, measured
def acceleration_limits(robot: Path) -> np.ndarray:
    """The actuators' acceleration limits in wire order (the servos s<k>c<i>, then z), read from the robot file
    itself (rad/s^2, mm/s^2), not through crtraj's actuator model."""
    acts = tomllib.loads(robot.read_text())["robot"]["actuators"]
    servos = [acts["servo"][n].get("acceleration_limit", acts["acceleration_limit"]) for n in acts["servo"]]
    return np.array([*servos, acts["z"]["acceleration_limit"]], dtype=float)


class Wire:
    """A UDP relay between a command and the simulated device that measures every set-point frame the command
    sent: the largest acceleration of the commanded positions (second difference over the frames' sequence gap
    times the session's declared period; a HOLD is a position like any other) as a fraction of `amax`, and the
    speed of the last frame (a stream that ends moving has not stopped)."""

    def __init__(self, device: str, amax: np.ndarray) -> None:
        host, port = device.rsplit(":", 1)
        self._device, self._amax = (host, int(port)), amax
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.settimeout(0.2)
        self.address = f"127.0.0.1:{self._sock.getsockname()[1]}"
        self._client: tuple[str, int] | None = None
        self._stop = threading.Event()
        self.reset()
        self._thread = threading.Thread(target=self._relay, daemon=True)
        self._thread.start()

    def reset(self) -> None:
        """Forget the frames seen (a new probe)."""
        self.peak, self.last_speed = 0.0, 0.0
        self._period, self._prev = 0.0, None  # (seq, values, velocity or None)

    def _measure(self, frame: Frame) -> None:
        if frame.kind == PING:
            self._period, self._prev = float(frame.values[0]), None
            return
        if frame.kind not in (MOVE, HOLD) or not self._period:
            return
        if self._prev is not None and frame.seq > self._prev[0]:
            dt = (frame.seq - self._prev[0]) * self._period
            v = (frame.values - self._prev[1]) / dt
            if self._prev[2] is not None:
                self.peak = max(self.peak, float(np.max(np.abs(v - self._prev[2]) / dt / self._amax)))
            self._prev = (frame.seq, frame.values, v)
            self.last_speed = float(np.max(np.abs(v) / (self._amax * self._period)))
        elif self._prev is None:
            self._prev = (frame.seq, frame.values, None)

    def _relay(self) -> None:
        while not self._stop.is_set():
            try:
                data, sender = self._sock.recvfrom(65536)
            except TimeoutError:
                continue
            if sender == self._device:
                if self._client is not None:
                    self._sock.sendto(data, self._client)
                continue
            self._client = sender
            self._sock.sendto(data, self._device)
            try:
                frame = Frame.decode(data)
            except FrameError:
                continue
            if isinstance(frame, Frame):
                self._measure(frame)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._sock.close()


# ---------------------------------------------------------------------------------------------- a probe
def _device(tree: Tree, folder: Path) -> tuple[subprocess.Popen, str]:
    """The simulated UDP device, in a process group of its own (a Ctrl-C of the command does not reach it)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "crtraj.cli", "sim-device", "--udp", "127.0.0.1:0", "--duration", "900"],
        cwd=folder, env={**os.environ, "PYTHONPATH": str(tree.root)}, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    line = proc.stdout.readline()
    found = re.search(r"udp://(\S+?) ", line)
    if not found:
        raise SystemExit(f"sim-device printed {line!r}")
    return proc, found.group(1)


def _start(case: Case, tree: Tree, folder: Path, address: str, mark: str) -> subprocess.Popen:
    env = {**os.environ, "CRTRAJ_HOSTILE_MARK": mark, "PYTHONPATH": str(tree.root)}

    def preexec() -> None:  # a terminal's job: SIGINT at its default, a process group of its own
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.setsid()

    return subprocess.Popen(
        [sys.executable, "-m", "crtraj.cli", *case.args(tree, folder, address)],
        cwd=folder, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=preexec,
    )  # fmt: skip


def _deliver(proc: subprocess.Popen, signum: int) -> None:
    """Ctrl-C: to the process group, as a terminal sends it; SIGTERM: to the process, as `kill PID`."""
    if signum == signal.SIGINT:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)


def probe(
    case: Case, tree: Tree, rng: random.Random, wire: Wire | None
) -> Probe:  # long: one run, its signal and its checks
    """Run `case` once in a fresh folder, signal it at a random point, and check what it left."""
    signum = rng.choice(case.signals)
    at = rng.uniform(*case.window)
    result = Probe(case.name, signum, at)
    with tempfile.TemporaryDirectory(prefix="hostile-") as tmp:
        folder = Path(tmp)
        out = folder / "o"
        for name in case.outputs:
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            (out / name).write_bytes(f"the user's earlier {name}\n".encode())
        before, mark = snapshot(out), uuid.uuid4().hex
        if wire is not None:
            wire.reset()
        proc = _start(case, tree, folder, wire.address if wire is not None else "", mark)
        end = time.monotonic() + STARTUP_S
        while not handles_sigterm(proc.pid) and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.01)
        deadline = time.monotonic() + at
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        if proc.poll() is not None:
            result.finished_first = True
        else:
            _deliver(proc, signum)
        try:
            stdout, err = proc.communicate(timeout=HANG_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            stdout, err = proc.communicate()
            result.problems.append("hung after the signal")
        want = [f"crtraj: {'interrupted' if signum == signal.SIGINT else 'terminated'}"]
        if result.finished_first:
            if proc.returncode != 0:
                result.problems.append(f"exit {proc.returncode} before the signal: {err.strip()[-400:]!r}")
        else:
            if proc.returncode != 128 + signum:
                result.problems.append(f"exit {proc.returncode}")
            if err.splitlines() != want:
                result.problems.append(f"stderr {err[-400:]!r}")
        if "Traceback" in err:
            result.problems.append("traceback")
        found = _ACCEL.findall(stdout)
        result.reported = max(map(float, found)) if found else None
        if wire is not None:
            time.sleep(0.5)  # the relay's last frames
            result.acceleration, result.last_step = wire.peak, wire.last_speed
            if wire.peak > 1 + _TOL:
                result.problems.append(f"acceleration on the wire {wire.peak:.2f} of its limit")
            if wire.last_speed > 1 + _TOL:
                result.problems.append(f"the last frame moves {wire.last_speed:.2f} periods of braking")
        end = time.monotonic() + ORPHAN_S
        while (alive := marked(mark)) and time.monotonic() < end:
            time.sleep(0.05)
        if alive:
            result.problems.append(f"orphans {alive}")
            for pid in alive:
                os.kill(pid, signal.SIGKILL)
        after = snapshot(out)
        if after != before and not result.finished_first:
            changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
            result.problems.append(f"outputs changed: {changed}")
    return result


# ---------------------------------------------------------------------------------------------- report
def _line(p: Probe) -> str:
    what = f"{p.case:18s} {signal.Signals(p.signum).name:7s} at {p.at_s:5.2f} s"
    accel = ""
    if p.acceleration is not None:
        reported = "none" if p.reported is None else f"{p.reported:.2f}"
        accel = f" (acceleration on the wire {p.acceleration:.2f} of the limit, reported {reported})"
    if p.finished_first:
        return f"{what}: finished before the signal{accel}" + (f": {'; '.join(p.problems)}" if p.problems else "")
    return f"{what}: " + ("clean" if not p.problems else "DIRTY: " + "; ".join(p.problems)) + accel


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--trials", type=int, default=3, help="probes per case")
    parser.add_argument("--seed", type=int, default=36)
    parser.add_argument("--only", default="", help="comma-separated case names (default: all)")
    parser.add_argument("--tree", type=Path, default=ROOT, help="the checkout to run (default: this one)")
    args = parser.parse_args(argv)
    tree = Tree(args.tree.resolve())
    names = [c.name for c in CASES]
    only = [n for n in args.only.split(",") if n]
    unknown = sorted(set(only) - set(names))
    if unknown:
        parser.error(f"--only: no case {', '.join(unknown)} (cases: {', '.join(names)})")
    chosen = [c for c in CASES if not only or c.name in only]
    rng = random.Random(args.seed)
    probes: list[Probe] = []
    with tempfile.TemporaryDirectory(prefix="hostile-dev-") as tmp:
        device, address = _device(tree, Path(tmp)) if any(c.device for c in chosen) else (None, "")
        wire = Wire(address, acceleration_limits(tree.robot)) if device is not None else None
        try:
            for case in chosen:
                for _ in range(args.trials):
                    probes.append(probe(case, tree, rng, wire if case.device else None))
                    print(_line(probes[-1]), flush=True)
        finally:
            if device is not None:
                wire.close()
                device.terminate()
                device.communicate(timeout=60)
    print("\ncase                clean dirty finished-first")
    for case in chosen:
        mine = [p for p in probes if p.case == case.name]
        signalled = [p for p in mine if not p.finished_first]
        dirty = sum(bool(p.problems) for p in mine)
        print(f"{case.name:18s} {len(signalled) - dirty:6d} {dirty:5d} {len(mine) - len(signalled):14d}")
    return 1 if any(p.problems for p in probes) else 0


if __name__ == "__main__":
    sys.exit(main())
