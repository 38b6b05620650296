"""`crtraj verify --model cosserat` and the simulated plant (`--plant cosserat`) solve the same rod: one function
(`crtraj.model.cosserat.robot_rod`) decides the actuation physics (cable lengths or tensions) for both.

The check compares what each reports, not how it is built: verify's per-frame largest distance between the rod's
nodes and PCC's, against the plant's own rod shape at the same actuation; in both actuation modes of one robot
file. The two modes differ by several mm on this robot, so a plant and a verifier that disagreed on the mode (or
on the pretension, or on gravity) would fail it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from crtraj.app.lab import verify_cosserat
from crtraj.app.lab._verify import pcc_nodes_batch
from crtraj.app.plant_sim import make_plant
from crtraj.io.problem import Problem
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
ROBOT_FILE = ROOT / "problems" / "robots" / "cdsr1_side.toml"
PROBLEM_FILE = ROOT / "problems" / "side_shelf.toml"
X = np.array([[0.0, 0.0, -50.0], [0.6, 0.3, -20.0], [-0.4, 0.9, 10.0], [1.2, -0.5, 40.0]])


def _problem(tmp_path: Path, mode: str) -> Problem:
    """side_shelf.toml with its robot file's actuation set to `mode`."""
    robot = ROBOT_FILE.read_text().replace('actuation = "cable_length"', f'actuation = "{mode}"')
    assert f'actuation = "{mode}"' in robot
    (tmp_path / "robots").mkdir(exist_ok=True)
    (tmp_path / "robots" / "cdsr1_side.toml").write_text(robot)
    (tmp_path / f"{mode}.toml").write_text(PROBLEM_FILE.read_text())
    return Problem.load(tmp_path / f"{mode}.toml")


def _document(problem: Problem) -> dict:
    """A plan document of four waypoints X (header, verdict, waypoints t and x)."""
    return {
        "kind": "plan",
        "schema": 1,
        "robot": problem.robot.to_dict(),
        "scene": problem.options(Scene, "scene").to_dict(),
        "status": "exact",
        "success": True,
        "message": "",
        "timing": {"setup_s": 0.1, "total_s": 0.1},
        "summary": {},
        "waypoints": [{"t": float(k), "x": x.tolist()} for k, x in enumerate(X)],
    }


def _plant_discrepancy(problem: Problem) -> tuple[np.ndarray, str]:
    """The plant's rod against PCC at X: largest node distance per configuration (mm), and its mode."""
    plant = make_plant("cosserat", problem)
    robot = problem.robot
    nodes = np.array([plant.shape(robot.cables(x)).points for x in X])
    pcc = pcc_nodes_batch(Model(robot), X, plant.drive.mech.steps)
    return np.linalg.norm(nodes - pcc, axis=-1).max(axis=1), plant.drive.actuation


def test_verify_and_the_plant_see_the_same_rod_in_each_actuation_mode(tmp_path: Path) -> None:
    """Per frame, verify's rod-to-PCC distance equals the plant's (to the verifier's looser solve tolerance), in
    cable-length mode and in tension mode; and the modes differ, so the check can tell them apart."""
    seen = {}
    for mode in ("cable_length", "tension"):
        problem = _problem(tmp_path, mode)
        v = verify_cosserat(read_result(_document(problem)), problem.robot)
        plant, plant_mode = _plant_discrepancy(problem)
        assert v.failed == 0 and v.gravity
        assert v.actuation == plant_mode == mode
        assert np.allclose(v.discrepancy, plant, atol=1e-3), (mode, v.discrepancy, plant)
        seen[mode] = plant
    assert np.max(np.abs(seen["tension"] - seen["cable_length"])) > 2.0, seen


@pytest.mark.parametrize("plant", ["cosserat", "cosserat-weightless"])
def test_the_plant_takes_the_robot_files_mode_and_gravity(tmp_path: Path, plant: str) -> None:
    """make_plant's rod is the robot file's mode, with gravity only for --plant cosserat."""
    drive = make_plant(plant, _problem(tmp_path, "tension")).drive
    assert drive.actuation == "tension" and drive.gravity == (plant == "cosserat")
