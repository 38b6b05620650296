"""End to end on loopback: plan (sim 1, 10 seeds: `crtraj plan`) or replan (sim 2, 5 seeds: `crtraj replan`),
then `crtraj stream RESULT --approach` to a freshly started simulated device. Every run streams with zero
refusals, and the device ends within tolerance of the final set-point, which is the result's own final
actuation.

Most seeds run the commands in process and stream to an in-process device on the streamer's virtual clock
(`devlink.CoreLink`: no wall clock, so a loaded machine cannot fail them); one seed runs the real command
line, three processes over UDP (`crtraj plan`, `crtraj sim-device`, `crtraj stream`).
"""

from __future__ import annotations

import contextlib
import io
import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import default_sigint, paper_copy
from devlink import CoreLink

from crtraj.app.devices import admit_result, plan_approach
from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import ESTOP, MOVE, Frame
from crtraj.hardware.sim import DeviceCore
from crtraj.hardware.stream import Streamer, StreamOptions, StreamReport
from crtraj.io.results import read_result

pytestmark = pytest.mark.timeout(600)
ROOT = Path(__file__).resolve().parent.parent
STATIC = ROOT / "problems" / "paper_static.toml"


def _cli(argv: list[str]) -> tuple[int, str]:
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = main(argv)
    return code, buf.getvalue()


def _stream_fresh(result: Path) -> tuple[StreamReport, DeviceCore, list[Frame], np.ndarray]:
    """`crtraj stream RESULT --approach` (its admission, default options and approach planner) to a freshly
    started device on a virtual clock: (report, device, frames sent, the result's final actuator values)."""
    opts = StreamOptions()
    motion = admit_result(result, rate=opts.rate)  # refuses (raises) a failed, unsafe or too fast result
    clock = VirtualClock()
    core = DeviceCore(motion.actuators)  # a fresh device: every actuator at its zero offset
    assert np.max(np.abs(core.state()["positions"] - motion.values[0])) > opts.settle_tolerance  # an approach is due
    link = CoreLink(core, clock)
    rep = Streamer(link, motion.actuators, opts, realtime=True, clock=clock).run_path(
        motion, approach=True, plan_approach=plan_approach
    )
    res = read_result(result)
    q_end = res.executed[2][-1] if res.executed is not None else res.q[-1]
    return rep, core, [Frame.decode(f) for f in link.sent], motion.actuators.command(q_end)


def _check(rep: StreamReport, core: DeviceCore, sent: list[Frame], goal: np.ndarray) -> None:
    assert rep.ok and rep.status == "done", f"{rep.status}: {rep.message}"
    dev = core.state()
    assert dev["refused"] == 0 and dev["limited"] == 0, dev  # the device refused or clipped nothing
    moves = [f for f in sent if f.kind == MOVE]
    assert moves and not any(f.kind == ESTOP for f in sent)
    np.testing.assert_allclose(moves[-1].values, goal, rtol=0, atol=1e-9)  # the last set-point: the result's end
    assert np.max(np.abs(dev["positions"] - goal)) <= StreamOptions().settle_tolerance


@pytest.mark.parametrize("seed", range(1, 11))
def test_sim1_plan_then_stream_with_approach(seed, tmp_path):
    out = tmp_path / f"plan-{seed}.json"
    code, text = _cli(["plan", str(STATIC), "--seed", str(seed), "--out", str(out)])
    assert code == 0, text
    _check(*_stream_fresh(out))


@pytest.fixture(scope="module")
def replans(tmp_path_factory):
    """`crtraj replan problems/paper_dynamic.toml --seed S --out DIR` for seeds 1..5, once, without the 4 ms step
    deadline (`paper_copy`): which steps fall back then depends on the seed only, not on the machine's load."""
    runs = {}
    problem = paper_copy(tmp_path_factory.mktemp("problem"))
    for seed in range(1, 6):
        out = tmp_path_factory.mktemp("replan") / f"seed{seed}"
        code, text = _cli(["replan", str(problem), "--seed", str(seed), "--out", str(out), "--no-html", "--quiet"])
        runs[seed] = (code, text, out / "run.json")
    return runs


@pytest.mark.parametrize("seed", range(1, 6))
def test_sim2_replan_then_stream_with_approach(replans, seed, tmp_path):
    code, text, run = replans[seed]
    assert code == 0, text
    _check(*_stream_fresh(run))


def test_command_line_chain_plan_sim_device_stream(tmp_path):
    """The README's chain as three real processes: plan, a fresh `crtraj sim-device`, `crtraj stream --approach`."""
    exe = [sys.executable, "-m", "crtraj.cli"]
    plan = tmp_path / "p.json"
    done = subprocess.run(
        [*exe, "plan", str(STATIC), "--seed", "10", "--out", str(plan)], cwd=ROOT, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stdout + done.stderr
    dev = subprocess.Popen(
        [*exe, "sim-device", "--udp", "127.0.0.1:0", "--duration", "600"],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        preexec_fn=default_sigint,
    )
    try:
        line = dev.stdout.readline()
        assert line.startswith("sim-device listening on udp://127.0.0.1:"), line
        addr = line.split("udp://")[1].split()[0]
        log = tmp_path / "stream.jsonl"
        # a 1 s watchdog: this test is about the chain, not about a loaded machine starving the device process
        argv = [*exe, "stream", str(plan), "--approach", "--udp", addr, "--log", str(log), "--watchdog", "1.0"]
        streamed = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)  # a hang bound
    finally:
        dev.send_signal(signal.SIGINT)
        dev_out, _ = dev.communicate(timeout=60)  # a hang bound only
    assert streamed.returncode == 0, streamed.stdout + streamed.stderr
    assert streamed.stdout.splitlines()[1] == "done: completed", streamed.stdout
    assert "refused 0" in streamed.stdout and "limited 0" in streamed.stdout, streamed.stdout
    records = [json.loads(x) for x in log.read_text().splitlines()]
    report = records[-1]
    assert report["type"] == "report" and report["status"] == "done"
    sent = [r for r in records if r["type"] == "tx" and r["kind"] == "move"]
    res = read_result(plan)
    goal = Actuators.from_robot(res.robot).command(res.q[-1])
    np.testing.assert_allclose(sent[-1]["values"], goal, rtol=0, atol=1e-9)
    # the device's last telemetry: within the settle tolerance of the final set-point
    tel = [r for r in records if r["type"] == "rx" and "positions" in r]
    assert tel and np.max(np.abs(np.asarray(tel[-1]["positions"]) - goal)) <= StreamOptions().settle_tolerance
    assert "sim-device stopped: received" in dev_out
