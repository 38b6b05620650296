"""A real host killed mid-stream (issue 38): `crtraj stream --dynamixel` in its own process, SIGKILLed while it
streams to `crtraj sim-dynamixel` in another; the servos' state is then read over the same bus, as a lab would
read a real robot's after its host died."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import dxl_helpers
import numpy as np
import pytest
from conftest import ROOT, default_sigint, require_module
from dxl_helpers import Z_HOMING, robot_text

from crtraj.hardware.dynamixel import X

sim1_plan = dxl_helpers.sim1_plan  # the fixture, shared
WAIT_S = 120.0  # s the test waits for a subprocess's line at most (a loaded CI machine is slow to import)
# A loaded CI machine can starve the streaming process for more than the default 0.1 s: these tests are about the
# kill and the signals, so the servos' Bus Watchdog and the stream's telemetry watchdog are longer
BUS_WATCHDOG = 0.5  # s
STOP = f"\n[robot.stop]\nbus_watchdog = {BUS_WATCHDOG}\n"


def _spawn(args: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "crtraj.cli", *args],
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=default_sigint,  # its Ctrl-C must reach it when the suite runs in the background
    )


def _streaming(log: Path, proc: subprocess.Popen) -> bool:
    """The stream's run log has its ``streaming`` event (the first set-point went out)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and proc.poll() is None:
        if log.exists() and any(
            json.loads(x).get("event") == "streaming" for x in log.read_text().splitlines() if x.endswith("}")
        ):
            return True
        time.sleep(0.05)
    return False


def _read(ph, port, dxl_id: int, addr: int, size: int) -> int:
    """One register over the bus (signed for 4 bytes)."""
    f = {1: ph.read1ByteTxRx, 4: ph.read4ByteTxRx}[size]
    for _ in range(5):
        value, result, _ = f(port, dxl_id, addr)
        if result == 0:
            return value - (1 << 32) if size == 4 and value >= 1 << 31 else value
    raise AssertionError(f"servo {dxl_id} does not answer")


@pytest.mark.slow
def test_sigkill_of_a_streaming_host_leaves_every_servo_stopped_by_its_watchdog(sim1_plan, tmp_path):
    """`crtraj stream` SIGKILLed about 1 s into a sim-1 stream (no cleanup of it runs: no torque off, no last
    frame): every servo's Bus Watchdog (0.5 s here) fires, register 98 reads -1 (0xFF), the servos stand still (two
    readings of every position 0.3 s apart agree, Moving reads 0) with the torque still on, and the next stream
    refuses the z stage, naming the watchdog stop, until it is homed again."""
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    import dynamixel_sdk as sdk

    with _simulator(sim1_plan, tmp_path) as (robot, pty):
        args, log, _, _ = _signalled(sim1_plan, robot, pty, tmp_path, signal.SIGKILL)
        records = [json.loads(x) for x in log.read_text().splitlines() if x.endswith("}")]
        assert not any(r.get("type") == "report" for r in records)  # killed mid-stream: it never reported
        time.sleep(BUS_WATCHDOG + 0.5)  # the watchdog, then each servo brakes with its profile (about 0.1 s here)
        port, ph = sdk.PortHandler(pty), sdk.PacketHandler(2.0)
        assert port.openPort() and port.setBaudRate(1_000_000)
        try:
            ids = range(1, 8)
            assert [_read(ph, port, i, X.BUS_WATCHDOG, 1) for i in ids] == [X.WATCHDOG_TRIPPED] * 7
            first = np.array([_read(ph, port, i, X.PRESENT_POSITION, 4) for i in ids])
            time.sleep(0.3)
            second = np.array([_read(ph, port, i, X.PRESENT_POSITION, 4) for i in ids])
            assert np.array_equal(first, second), (first, second)
            assert [_read(ph, port, i, X.MOVING, 1) for i in ids] == [0] * 7
            assert [_read(ph, port, i, X.TORQUE_ENABLE, 1) for i in ids] == [1] * 7
        finally:
            port.closePort()
        again = _spawn(args, tmp_path)
        out = again.communicate(timeout=WAIT_S)[0]
        assert again.returncode == 2, out
        assert re.search(r"servo id 7 \(z\): its bus watchdog stopped it", out), out


@pytest.mark.slow
@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_or_sigterm_mid_stream_finishes_the_verified_stop(sim1_plan, tmp_path, signum, code):
    """Ctrl-C (or SIGTERM) about 1 s into a sim-1 stream to the simulated servos: the stream brakes to rest with
    its verified stop (one stop planned, more than one frame, none latched), writes its report (status
    interrupted), exits 130 (143), and leaves the servos standing still with their torque on (torque = "keep")."""
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    import dynamixel_sdk as sdk

    with _simulator(sim1_plan, tmp_path) as (robot, pty):
        _, log, rc, out = _signalled(sim1_plan, robot, pty, tmp_path, signum)
        assert rc == code, out
        assert "Traceback" not in out
        report = [json.loads(x) for x in log.read_text().splitlines()][-1]
        assert report["type"] == "report" and report["status"] == "interrupted", report
        assert report["brakes"] == 1 and report["brake_frames"] > 1 and report["latched"] == 0, report
        time.sleep(0.3)
        port, ph = sdk.PortHandler(pty), sdk.PacketHandler(2.0)
        assert port.openPort() and port.setBaudRate(1_000_000)
        try:
            ids = range(1, 8)
            assert [_read(ph, port, i, X.MOVING, 1) for i in ids] == [0] * 7
            assert [_read(ph, port, i, X.TORQUE_ENABLE, 1) for i in ids] == [1] * 7
        finally:
            port.closePort()


def _signalled(plan: Path, robot: Path, pty: str, tmp_path: Path, signum: int):
    """`crtraj stream plan --dynamixel pty` in its own process, sent `signum` about 1 s after its first set-point
    went out: (its arguments, its run log, its exit code, its output)."""
    log = tmp_path / "stream.jsonl"
    args = ["stream", str(plan), "--dynamixel", pty, "--robot", str(robot), "--log", str(log), "--watchdog", "2.0"]
    host = _spawn(args, tmp_path)
    assert _streaming(log, host), host.communicate(timeout=WAIT_S)[0]
    time.sleep(1.0)
    host.send_signal(signum)
    out = host.communicate(timeout=WAIT_S)[0]
    return args, log, host.returncode, out


@contextlib.contextmanager
def _simulator(plan: Path, tmp_path: Path) -> Iterator[tuple[Path, str]]:
    """`crtraj sim-dynamixel --pty --at plan` in its own process (servos homed at the plan's start, wall clock):
    (the robot file, the pseudo-terminal's path); ended with Ctrl-C after the block."""
    robot = tmp_path / "robot.toml"
    robot.write_text(robot_text(Z_HOMING) + STOP)
    sim = _spawn(["sim-dynamixel", "--pty", "--robot", str(robot), "--at", str(plan)], tmp_path)
    try:
        line = ""
        deadline = time.monotonic() + WAIT_S
        while "sim-dynamixel on" not in line and time.monotonic() < deadline and sim.poll() is None:
            line = sim.stdout.readline()
        pty = re.search(r"on (/dev/\S+) ", line)
        assert pty, line
        yield robot, pty.group(1)
    finally:
        sim.send_signal(signal.SIGINT)
        sim.communicate(timeout=WAIT_S)
