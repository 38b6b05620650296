"""First power-on from the command line, against the Dynamixel simulator (the servos `crtraj sim-dynamixel`
serves, here in process: the SDK's bytes reach them through `SimPort`, so the test can read the shafts): a
power-cycled z stage at -150 mm is refused by `crtraj replan --stream dynamixel://DEV` (live and after the
run) and by `crtraj stream` with one line naming it; `crtraj home --dynamixel DEV` homes it; then replan
streams sim 2, and the issue's "done when" chain power-cycle, home, plan, approach and stream sim 1 ends at
the goal with every frame sent keeping D_sf and the positions the simulated shafts actually reached free of
contact by an independent dense check.

The command line runs on one virtual clock shared with the servos (the library's test seams,
`dxl_helpers.in_process`): the servos' motion, the streamer's pacing and watchdogs, the SDK's reply timeouts
and the homing's waits all take virtual time, so each run is the same under any load."""

from __future__ import annotations

import json
from pathlib import Path

import dxl_helpers
import numpy as np
import pytest
from conftest import PROBLEMS, paper_copy, require_module
from dxl_helpers import Z_HOMING, Clock, in_process, robot_text
from test_planner_helpers import dense_path_check

from crtraj.cli import main
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._homing_state import state_path
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import ServoChain
from crtraj.io.problem import Problem, load_robot
from crtraj.model.kinematics import Model
from crtraj.world.scene import Scene

sim1_plan = dxl_helpers.sim1_plan  # the fixture, shared


@pytest.fixture(autouse=True)
def _sdk():
    require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")


def _robot_file(tmp_path: Path) -> Path:
    p = tmp_path / "robot.toml"
    p.write_text(robot_text(Z_HOMING))
    return p


class Recorder:
    """Wraps a chain's `handle`: the physical shaft positions (ticks) at every sync read, with the time."""

    def __init__(self, chain: ServoChain) -> None:
        self.chain, self.rows = chain, []
        self._handle = chain.handle
        chain.handle = self.handle

    def handle(self, packet: dxl.Packet, now: float) -> list[bytes]:
        out = self._handle(packet, now)
        if packet.instruction == dxl.SYNC_READ:
            self.rows.append((now, self.chain.shaft(now)))
        return out


def _power_cycled_chain(robot, acts, x, clock: Clock) -> ServoChain:
    """Servos at configuration x with the stage's lower stop at its homing reference (-200 mm), power-cycled."""
    from crtraj.hardware.dynamixel._sim_robot import stops

    chain = ServoChain(
        acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(acts.command(robot.cables(x))), stops=stops(robot, acts)
    )
    chain.power_cycle(clock.now())
    return chain


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def _untouched(chain, acts, now, before, goals) -> None:
    """Nothing moved and no goal went out; torque off everywhere."""
    np.testing.assert_array_equal(chain.positions(now), before)
    assert [chain.register(i, X.GOAL_POSITION, 4) for i in acts.bus.ids] == goals
    assert not any(chain.torque(i) for i in acts.bus.ids)


def _home(dev: str, robot_file, capsys) -> dict:
    assert main(["home", "--dynamixel", dev, "--robot", str(robot_file)]) == 0
    out = capsys.readouterr().out
    assert "homed z (id 7, model 1030) by hard_stop" in out
    return json.loads(state_path(robot_file).read_text())


def _homed_stage(tmp_path: Path, monkeypatch, capsys) -> tuple[Path, str, dict]:
    """The robot file, the device of its servos power-cycled with the stage at -150 mm and served in process,
    and the homing state `crtraj home` wrote for them."""
    robot_file = _robot_file(tmp_path)
    robot = load_robot(robot_file)
    clock = Clock()
    chain = _power_cycled_chain(robot, Actuators.from_robot(robot), robot.straight(-150.0), clock)
    dev = in_process(monkeypatch, chain, clock).path
    return robot_file, dev, _home(dev, robot_file, capsys)


def test_replan_stream_dynamixel_refuses_a_power_cycled_stage_then_runs_after_home(tmp_path, capsys, monkeypatch):
    """`crtraj replan --stream dynamixel://DEV` (live with --feed, and after the run) refuses the power-cycled
    z stage with one line naming it and the command that homes it, before any goal reaches a servo; after
    `crtraj home` the same replan streams the run and the servos end at its last set-point."""
    robot_file = _robot_file(tmp_path)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    problem = paper_copy(tmp_path, values={("robot",): str(robot_file)})
    clock = Clock()
    chain = _power_cycled_chain(robot, acts, robot.straight(-150.0), clock)
    sim = in_process(monkeypatch, chain, clock)
    dev = sim.path
    home = f"run crtraj home --dynamixel {dev} --robot {robot_file}"
    base = ["replan", str(problem), "--quiet", "--no-html", "--stream", f"dynamixel://{dev}", "--approach"]
    # live: the link is refused at connect, before the loop runs
    assert main([*base, "--feed", "udp://127.0.0.1:0", "--out", str(tmp_path / "live")]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("crtraj: error: servo id 7 (z): not homed since its last power-up"), line
    assert line.endswith(home), line
    before = chain.positions(clock.now()).copy()
    assert acts.bus.values(before)[-1] == pytest.approx(-150.0 % 20.0, abs=0.01)  # within one turn of 20 mm
    goals = [chain.register(i, X.GOAL_POSITION, 4) for i in acts.bus.ids]
    # after the run: the run is written, the stream refused
    assert main([*base, "--out", str(tmp_path / "r1")]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("crtraj: error: servo id 7 (z): not homed since its last power-up") and home in line
    assert (tmp_path / "r1" / "run.json").is_file()  # the refused stream keeps the run (only a stop does not)
    _untouched(chain, acts, clock.now(), before, goals)
    saved = _home(dev, robot_file, capsys)
    z = saved["servos"][0]
    assert (z["id"], z["model"], z["model_information"], z["firmware"]) == (7, 1030, 0, 46)
    assert acts.bus.values(chain.positions(clock.now()))[-1] == pytest.approx(-200.0, abs=0.01)
    assert main([*base, "--out", str(tmp_path / "r2")]) == 0, capsys.readouterr()
    out = capsys.readouterr().out
    assert "stream done: completed" in out, out
    assert len(sim.ports) == 4 and sim.ports[-1].timeouts == 0  # live, r1, home, r2: every read answered
    run = json.loads((tmp_path / "r2" / "run.json").read_text())
    q_last = np.asarray(run["waypoints"][-1]["q"], dtype=float)
    reached = acts.bus.values(np.rint(chain.positions(clock.now())))
    assert np.max(np.abs(reached - acts.command(q_last))) <= 0.01 + 1e-9  # the settle tolerance (rad, mm)


def test_a_state_file_of_another_servo_is_refused_in_one_line(sim1_plan, tmp_path, capsys, monkeypatch):
    """The homing state file records each servo's identity (id, model number, model information, firmware: the
    X-series has no serial number); a file whose firmware differs from the servo's is refused, naming it."""
    robot_file, dev, saved = _homed_stage(tmp_path, monkeypatch, capsys)
    saved["servos"][0]["firmware"] = 45
    state_path(robot_file).write_text(json.dumps(saved))
    argv = ["stream", str(sim1_plan), "--dynamixel", dev, "--approach", "--robot", str(robot_file)]
    assert main([*argv, "--log", str(tmp_path / "s.jsonl")]) == 2
    line = _one_error_line(capsys)
    assert line.startswith(
        "crtraj: error: servo id 7 (z): model 1030, model information 0, firmware 46 is not the servo the homing "
        "state file recorded (model 1030, model information 0, firmware 45)"
    ), line


def test_a_stream_without_robot_is_told_to_home_and_stream_with_one(sim1_plan, tmp_path, capsys, monkeypatch):
    """Without --robot the stream has no homing state to read (it lies beside the robot file): the refusal of
    a stage homed by `crtraj home --robot R` says to home and stream with the same --robot, exit 2, and
    streaming so completes, so the user does not loop between home and stream."""
    robot_file, dev, _ = _homed_stage(tmp_path, monkeypatch, capsys)
    argv = ["stream", str(sim1_plan), "--dynamixel", dev, "--approach", "--log", str(tmp_path / "s.jsonl")]
    assert main(argv) == 2
    line = _one_error_line(capsys)
    assert line.startswith("crtraj: error: servo id 7 (z): its homing offset"), line
    assert line.endswith(
        f"run crtraj home --dynamixel {dev} --robot ROBOT.toml, then stream with the same --robot ROBOT.toml"
    ), line
    assert main([*argv, "--robot", str(robot_file)]) == 0
    assert "done: completed" in capsys.readouterr().out


def test_power_cycle_home_plan_approach_and_stream_sim1_from_the_cli(tmp_path, capsys, monkeypatch):
    """The issue's "done when", first half: power-cycle (z at -150 mm), `crtraj home`, `crtraj plan` sim 1,
    `crtraj stream --approach`: done at the goal; every frame sent keeps D_sf and every position the simulated
    shafts reached is free of contact, by an independent dense check against the scene."""
    robot_file = _robot_file(tmp_path)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    clock = Clock()
    chain = _power_cycled_chain(robot, acts, np.array([0.9, -0.6, 0.3, 0.5, -150.0]), clock)
    rec = Recorder(chain)
    sim = in_process(monkeypatch, chain, clock)
    dev = sim.path
    plan = tmp_path / "plan.json"
    problem = Problem.load(PROBLEMS / "paper_static.toml")
    _home(dev, robot_file, capsys)
    assert main(["plan", str(PROBLEMS / "paper_static.toml"), "--seed", "1", "--out", str(plan)]) == 0
    capsys.readouterr()
    rec.rows.clear()
    log = tmp_path / "stream.jsonl"
    argv = ["stream", str(plan), "--dynamixel", dev, "--approach", "--robot", str(robot_file)]
    assert main([*argv, "--log", str(log)]) == 0, capsys.readouterr()
    out = capsys.readouterr().out
    assert "done: completed" in out, out
    assert len(sim.ports) == 2 and sim.ports[-1].timeouts == 0  # home, stream; every read of the stream answered
    records = [json.loads(x) for x in log.read_text().splitlines()]
    report = next(r for r in records if r["type"] == "report")
    assert report["status"] == "done" and report["latched"] == 0
    assert not any(e[1] == "refused" for e in report["events"])
    model, scene = Model(problem.robot), Scene.from_table(problem.section("scene"))
    sent = [r for r in records if r["type"] == "tx" and r["kind"] in ("move", "hold")]
    t_sent = np.array([r["stamp"] for r in sent])
    x_sent = robot.config(acts.actuation(np.array([r["values"] for r in sent])))
    clear, limit, _ = dense_path_check(model, scene, t_sent, x_sent, dt=0.01, points=100)
    assert clear >= -1e-6 and limit <= 1e-9  # every frame sent keeps D_sf and the limits
    t_reached = np.array([t for t, _ in rec.rows])
    values = acts.bus.values(np.rint(np.array([s for _, s in rec.rows])))
    x_reached = robot.config(acts.actuation(values))
    clear_r, _, _ = dense_path_check(model, scene, t_reached - t_reached[0], x_reached, dt=0.01, points=100)
    assert clear_r + scene.safety_distance > 0.0  # no contact anywhere the shafts went
    tip = model.tip_position(x_reached[-1])
    assert np.linalg.norm(tip - np.asarray(problem.task.goal)) <= problem.task.goal_tolerance + 0.5


def test_crtraj_home_on_a_servo_that_never_stalls_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    """No mechanical stop within the travel: `crtraj home` ends with one line naming the servo, exit 2, the
    torque off, no Homing Offset written and no state file."""
    robot_file = tmp_path / "robot.toml"
    robot_file.write_text(robot_text(Z_HOMING + "travel = 20.0\n"))
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    chain = ServoChain(
        acts.bus.ids, acts.bus.models, initial=acts.bus.ticks(acts.command(robot.cables(robot.straight(-150.0))))
    )
    clock = Clock()
    chain.power_cycle(clock.now())
    dev = in_process(monkeypatch, chain, clock).path
    assert main(["home", "--dynamixel", dev, "--robot", str(robot_file)]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("crtraj: error: servo id 7 (z): no stall within 20 mm of travel"), line
    assert line.endswith("no mechanical stop found; nothing written"), line
    assert chain.register(7, X.HOMING_OFFSET, 4) == 0 and not chain.torque(7)
    assert not state_path(robot_file).exists()
