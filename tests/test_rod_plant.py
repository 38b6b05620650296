"""The Cosserat rod as the closed loop's plant (`crtraj replan --plant cosserat`): the drive against PCC, the
plant's clearance against an independent recomputation, tip feedback on the rod, the simulated capture for
calibration, and one-line bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.lab import sample_configs
from crtraj.app.plant_sim import attach_plant, make_plant
from crtraj.cli import main
from crtraj.control.loop import ClosedLoop
from crtraj.core.clock import VirtualClock
from crtraj.hardware.actuators import Actuators
from crtraj.io.calibration_data import read_dataset
from crtraj.io.problem import Problem, load_robot
from crtraj.model.calibration import paper_markers
from crtraj.model.cosserat._cables import CableDrivenRod
from crtraj.model.cosserat._drive import RodDrive
from crtraj.model.cosserat._map import pcc_nodes, tensions_for_bending
from crtraj.model.cosserat._statics import CosseratRod, RodLoad
from crtraj.model.kinematics import Model

ROOT = Path(__file__).resolve().parent.parent
CDSR2 = ROOT / "problems" / "robots" / "cdsr2.toml"
# the goal configuration of the short problem: both segments bent the same way, about 100 mm off axis
X_GOAL = np.array([0.45, 0.1, 0.15, 0.05, 0.0])
BALL = ((-70.0, 20.0, 330.0), 25.0)  # mm: a static sphere on the other side, centre and radius


@pytest.fixture(scope="module")
def cdsr2():
    return load_robot(CDSR2)


def _short_problem(tmp: Path) -> Path:
    """A short task from the straight pose to X_GOAL's tip beside one static sphere; no step deadline (the
    loop's decisions do not depend on wall time)."""
    goal = Model(load_robot(CDSR2)).tip_position(X_GOAL)
    text = f"""
name = "rod_short"
robot = "{CDSR2.as_posix()}"
seed = 3
[task]
start = [0.0, 0.0, 400.0]
start_config = [0.0, 0.0, 0.0, 0.0, 0.0]
goal = [{goal[0]:.6f}, {goal[1]:.6f}, {goal[2]:.6f}]
goal_tolerance = 0.5
[scene]
safety_distance = 5.0
[[scene.obstacle]]
name = "ball"
center = [{BALL[0][0]}, {BALL[0][1]}, {BALL[0][2]}]
radius = {BALL[1]}
[replan]
step_deadline = 0.0
[loop]
duration = 25.0
"""
    path = tmp / "short.toml"
    path.write_text(text)
    return path


def test_weightless_plant_follows_pcc_within_the_compare_bound(cdsr2):
    """Without gravity the driven rod stays within 1 mm of the PCC backbone (the bound of
    test_cosserat's weightless comparison: only axial compression and tendon geometry differ), and the
    straight pose holds exactly the pretension in every tendon."""
    drive = RodDrive(cdsr2, pretension=1.0, gravity=False)
    model = Model(cdsr2)
    for x in sample_configs(cdsr2, 4, np.random.default_rng(5)):
        s = drive.shape(cdsr2.cables(x))
        assert s.is_success(), s.status
        pcc = pcc_nodes(model, x, drive.mech.steps)
        pcc[:, 2] += x[-1]
        assert np.max(np.linalg.norm(s.points - pcc, axis=1)) < 1.0
    straight = drive.shape(cdsr2.cables(cdsr2.straight(-10.0)))
    np.testing.assert_allclose(straight.tensions, 1.0, rtol=1e-6)
    np.testing.assert_allclose(straight.tip[:2], 0.0, atol=1e-9)
    # the base stage at -10 mm; segment 1 carries all six tendons' 1 N, segment 2 three: compressed by F L / EA
    ea = drive.mech.youngs_modulus * drive.mech.area
    assert straight.tip[2] == pytest.approx(390.0 - 200.0 * (6.0 + 3.0) / ea, abs=1e-6)


def test_gravity_pulls_the_plant_off_pcc_and_more_with_more_mass(cdsr2):
    """With the robot's weight the bent rod sags away from PCC; heavier discs sag it further."""
    x = X_GOAL
    pcc = Model(cdsr2).tip_position(x)
    errs = []
    for disc_mass in (0.062, 0.3):
        mech = RodDrive(cdsr2).mech.with_(disc_mass=disc_mass)
        s = RodDrive(cdsr2, mech, gravity=True).shape(cdsr2.cables(x))
        errs.append(float(np.linalg.norm(s.tip - pcc)))
    assert 1.0 < errs[0] < errs[1]


@pytest.mark.parametrize("mode", ["cable_length", "tension"])
def test_the_plant_runs_in_the_robot_files_actuation_mode(tmp_path, cdsr2, mode):
    """`--plant cosserat` on a robot file with ``actuation = mode``: the plant's rod at the goal actuation
    equals a cold interpreted solve of that mode's statics (fixed tensions, or the commanded cable lengths),
    and its report and summary line name the mode."""
    robot_file = tmp_path / f"{mode}.toml"
    robot_file.write_text(CDSR2.read_text().replace("[robot.mechanics]", f'[robot.mechanics]\nactuation = "{mode}"'))
    prob = tmp_path / "p.toml"
    prob.write_text(_short_problem(tmp_path).read_text().replace(CDSR2.as_posix(), robot_file.as_posix()))
    plant = make_plant("cosserat", Problem.load(prob), tip_noise=0.0)
    q = cdsr2.cables(X_GOAL)
    got = plant.shape(q)
    assert got.is_success()
    mech = plant.drive.mech
    if mode == "tension":
        tau = tensions_for_bending(cdsr2, mech, cdsr2.bending(X_GOAL), 1.0)
        ref = CosseratRod(cdsr2, mech, compiled=False).solve(tau, RodLoad(), warm=False).points
    else:
        ell = RodDrive(cdsr2, pretension=1.0).lengths(q)
        ref = CableDrivenRod(cdsr2, mech, compiled=False).solve(ell, RodLoad()).rod.points
    np.testing.assert_allclose(got.points, ref, atol=1e-6)
    assert plant.describe()["actuation"] == mode and f"actuation {mode}" in plant.summary_line()


def test_the_two_actuation_modes_sag_differently(cdsr2):
    """Under gravity the fixed tensions let the bent rod sag far more than the commanded cable lengths do
    (the tendons of a position servo take up part of the weight): tips more than 5 mm apart at X_GOAL."""
    tips = {}
    for mode in ("cable_length", "tension"):
        mech = RodDrive(cdsr2).mech.with_(actuation=mode)
        tips[mode] = RodDrive(cdsr2, mech).shape(cdsr2.cables(X_GOAL)).tip
    pcc = Model(cdsr2).tip_position(X_GOAL)
    assert np.linalg.norm(tips["tension"] - pcc) > np.linalg.norm(tips["cable_length"] - pcc) + 5.0


def _sphere_clearance(points: np.ndarray, t: float, body: float, d_sf: float) -> float:
    """Clearance (mm, minus D_sf) of the body around `points` from the static sphere BALL, by numpy."""
    c, r = np.array(BALL[0]), BALL[1]
    return float(np.min(np.linalg.norm(points - c, axis=1)) - r - body - d_sf)


@pytest.mark.slow
def test_closed_loop_on_the_rod_reports_the_clearance_an_independent_check_finds(tmp_path, capsys, cdsr2):
    """`crtraj replan --plant cosserat` on a short problem: run.json's plant clearance at every control
    period equals the rod re-solved from the recorded actuation (commanded lengths through the public
    cable-length API) against the sphere by numpy; its minimum and counts agree, and PCC's own view is
    recorded beside it."""
    out = tmp_path / "run"
    code = main(["replan", str(_short_problem(tmp_path)), "--plant", "cosserat", "--out", str(out), "--no-html"])
    text = capsys.readouterr().out
    assert "plant (Cosserat rod, actuation cable_length, with gravity)" in text and "PCC's own view" in text
    doc = json.loads((out / "run.json").read_text())
    plant = doc["plant"]
    assert plant["kind"] == "plant" and plant["gravity"] is True and plant["failure"] == ""
    assert plant["actuation"] == "cable_length"  # cdsr2.toml names no mode: the position servos' default
    q, t, clear = np.array(plant["q"]), np.array(plant["t"]), np.array(plant["clearance"], dtype=float)
    assert len(q) == len(t) == len(clear) == plant["periods"] + 1 > 20
    np.testing.assert_allclose(np.diff(t), 0.02, atol=1e-9)  # every control period of 0.02 s
    drive = RodDrive(cdsr2, pretension=plant["pretension_n"])
    rod = CableDrivenRod(cdsr2)
    idx = np.unique(np.linspace(0, len(q) - 1, 12).astype(int))
    for k in idx:
        sol = rod.solve(drive.lengths(q[k]), RodLoad())
        assert sol.is_success()
        pts = sol.rod.points + np.array([0.0, 0.0, q[k][-1]])
        mine = _sphere_clearance(pts, t[k], cdsr2.body_radius, 5.0)
        assert mine == pytest.approx(clear[k], abs=1e-6)
        np.testing.assert_allclose(pts[-1], plant["tip"][k], atol=1e-6)
    assert plant["min_clearance_mm"] == pytest.approx(float(np.min(clear[1:])), abs=1e-12)
    assert plant["collisions"] == int(np.sum(clear[1:] + 5.0 < 0.0))
    assert plant["safety_violations"] == int(np.sum(clear[1:] < 0.0))
    err = float(np.linalg.norm(np.array(plant["tip"][-1]) - np.array(doc["task"]["goal"])))
    assert plant["final_tip_error_mm"] == pytest.approx(err, abs=1e-9)
    assert plant["pcc"]["final_tip_error_mm"] == pytest.approx(doc["summary"]["final_tip_error_mm"])
    assert code == (0 if doc["success"] and plant["safety_violations"] == 0 else 1)


@pytest.mark.slow
def test_tip_feedback_brings_the_rods_tip_to_the_goal_under_gravity(tmp_path):
    """Gravity sags the rod off PCC: without tip feedback the loop brings PCC's tip to the goal and the rod's
    tip stays off by the sag; with the rod's tip as its measurement the rod's tip gets within 1 mm, under half
    the error without."""
    problem = Problem.load(_short_problem(tmp_path))
    errs = {}
    for feedback in (False, True):
        plant = make_plant("cosserat", problem, tip_noise=0.0)
        loop = ClosedLoop.from_problem(problem, tip_sensor=plant, tip_feedback=feedback, clock=VirtualClock())
        attach_plant(plant, loop)
        run = loop.run(device=plant)
        assert run.reached, run.message
        errs[feedback] = plant.describe()["final_tip_error_mm"]
    print(f"rod tip error without / with tip feedback: {errs[False]:.2f} / {errs[True]:.2f} mm")
    assert errs[False] > 1.0  # the sag at this goal (1.6 mm)
    assert errs[True] < 0.5 * errs[False] and errs[True] < 1.0


def test_simulated_capture_reads_markers_off_the_rod(tmp_path, cdsr2, capsys):
    """`crtraj record --excite --plant cosserat-weightless`: a dataset whose markers are the rod's base, mid
    and tip nodes (plus 0.3 mm noise) at the recorded actuator values."""
    out = tmp_path / "rod.json"
    assert (
        main(["record", "--excite", "--plant", "cosserat-weightless", "--capture-rate", "0.5", "--out", str(out)]) == 0
    )
    assert "filmed on the cosserat-weightless rod" in capsys.readouterr().out
    data = read_dataset(out, Actuators.from_robot(cdsr2).names, cdsr2.n_segments)
    assert data.n > 10 and [s.name for s in data.sites] == [s.name for s in paper_markers(2)]
    drive = RodDrive(cdsr2, gravity=False)
    q = Actuators.from_robot(cdsr2).actuation(data.values)
    dev = []
    for k in (0, data.n // 2, data.n - 1):
        s = drive.shape(q[k])
        steps = drive.mech.steps
        truth = np.stack([s.points[0], s.points[steps], s.points[-1]])
        dev.append(np.abs(data.positions[k] - truth))
    dev = np.concatenate(dev)
    assert np.max(dev) < 5 * 0.3 and np.std(dev) > 0.01  # noisy, but only by the capture noise


def _one_error(capsys, argv) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, (code, err)
    return err[0]


def test_plant_bad_input_is_one_line(tmp_path, capsys):
    """A robot file without [robot.mechanics], an unknown plant, a plant with a live device: one line each,
    exit 2, nothing written."""
    bare = tmp_path / "bare.toml"
    bare.write_text(CDSR2.read_text().split("[robot.mechanics]")[0])
    prob = tmp_path / "p.toml"
    prob.write_text(
        (ROOT / "problems" / "paper_dynamic.toml").read_text().replace("robots/cdsr2.toml", bare.as_posix())
    )
    out = tmp_path / "run"
    base = ["replan", str(prob), "--out", str(out)]
    assert "has no [robot.mechanics]" in _one_error(capsys, [*base, "--plant", "cosserat"])
    assert "unknown plant 'pcc'" in _one_error(capsys, [*base, "--plant", "pcc"])
    assert "cannot be combined" in _one_error(capsys, [*base, "--plant", "cosserat", "--stream", "127.0.0.1:9"])
    assert "give --excite" in _one_error(
        capsys, ["record", "--plant", "cosserat", "--out", str(tmp_path / "d.json"), "--log", "x"]
    )
    assert not out.exists() and not (tmp_path / "d.json").exists()
