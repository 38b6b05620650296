"""`crtraj verify --model cosserat` (crtraj.app.lab._verify) against an independent per-frame computation, and a
gravity sag that PCC cannot see."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.lab._verify import frames, verify_cosserat
from crtraj.core.fields import Table
from crtraj.io.problem import load_robot
from crtraj.io.results import read_result
from crtraj.model.cosserat import CableDrivenRod, CosseratRod, RodDrive, RodLoad, pcc_nodes, tensions_for_bending
from crtraj.model.kinematics import Model
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
CDSR2 = ROOT / "problems" / "robots" / "cdsr2.toml"
D_SF = 5.0
# one obstacle moving on a line (linear profile) and breathing: c(t) = C0 + (t / DUR) (TO - C0), R = A + B sin(W t)
C0, TO, DUR = np.array([60.0, 40.0, 300.0]), np.array([20.0, -30.0, 250.0]), 4.0
A, B, W = 25.0, 8.0, 1.3


@pytest.fixture(scope="module")
def robot() -> Robot:
    return load_robot(CDSR2)


def _scene(obstacles: list[dict]) -> Scene:
    return Scene.from_table(Table({"safety_distance": D_SF, "obstacle": obstacles}, "scene"))


def _document(robot: Robot, scene: Scene, t: np.ndarray, x: np.ndarray) -> dict:
    """A minimal plan document: header, verdict, waypoints (t, x)."""
    return {
        "kind": "plan",
        "schema": 1,
        "robot": robot.to_dict(),
        "scene": scene.to_dict(),
        "status": "exact",
        "success": True,
        "message": "",
        "timing": {"setup_s": 0.5, "total_s": 0.5},
        "summary": {},
        "waypoints": [{"t": float(tk), "x": xk.tolist()} for tk, xk in zip(t, x, strict=True)],
    }


def _path(robot: Robot, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n configurations on a line from a bend toward +x to one toward +y, with the base moving up."""
    x0, x1 = np.zeros(robot.nx), np.zeros(robot.nx)
    x0[:4], x1[:4] = [0.5, 0.0, 0.3, 0.1], [0.0, 0.6, -0.2, 0.4]
    x0[-1], x1[-1] = robot.z_range[0], 0.5 * (robot.z_range[0] + robot.z_range[1])
    s = np.linspace(0.0, 1.0, n)[:, None]
    return np.linspace(0.0, DUR, n), (1 - s) * x0 + s * x1


def _with_actuation(robot: Robot, mode: str) -> Robot:
    """`robot` with ``[robot.mechanics] actuation = mode``."""
    return dataclasses.replace(robot, mechanics={**dict(robot.mechanics or {}), "actuation": mode})


def _cold_rod(robot: Robot, mech: Mechanics, x: np.ndarray, mode: str) -> np.ndarray:
    """The rod's backbone (mm, base at the origin) at x with gravity in `mode`, by a cold interpreted solve:
    under the tensions that hold x's PCC bending (1 N pretension), or under `RodDrive`'s commanded lengths."""
    if mode == "tension":
        tau = tensions_for_bending(robot, mech, robot.bending(x), 1.0)
        sol = CosseratRod(robot, mech, compiled=False).solve(tau, RodLoad(), warm=False)
        assert sol.is_success()
        return sol.points
    cab = CableDrivenRod(robot, mech, compiled=False).solve(RodDrive(robot, mech).lengths(robot.cables(x)), RodLoad())
    assert cab.is_success()
    return cab.rod.points


@pytest.mark.parametrize("mode", ["cable_length", "tension"])
def test_verify_matches_a_direct_per_frame_solve_and_distance(robot: Robot, mode: str) -> None:
    """Every frame's clearance under both models equals a cold interpreted rod solve in the robot file's
    actuation mode + numpy distances, and the verification reports that mode."""
    robot = _with_actuation(robot, mode)
    obstacle = {
        "center": C0.tolist(),
        "radius": {"mean": A, "amplitude": B, "omega": W},
        "motion": {"to": TO.tolist(), "duration": DUR},
    }
    scene = _scene([obstacle])
    # the cold cable-length solves are the costly part (about 7 s a frame under load): 5 frames of them, 11 of
    # the tension mode (whose warm-started solves are checked over shorter steps)
    n = 3 if mode == "cable_length" else 6
    t, x = _path(robot, n)
    result = read_result(_document(robot, scene, t, x))
    v = verify_cosserat(result, robot, substeps=2)
    assert v.actuation == mode
    tt, xx = frames(t, x, 2)
    assert len(v.t) == 2 * n - 1 and np.allclose(tt[1::2], 0.5 * (t[:-1] + t[1:]))
    mech, model = Mechanics.from_robot(robot), Model(robot)
    rod_c, pcc_c = [], []
    for tk, xk in zip(tt, xx, strict=True):
        c = C0 + min(tk / DUR, 1.0) * (TO - C0)
        r = A + B * np.sin(W * tk)
        for pts, out in ((_cold_rod(robot, mech, xk, mode), rod_c), (pcc_nodes(model, xk, mech.steps), pcc_c)):
            world = pts + np.array([0.0, 0.0, xk[-1]])
            out.append(np.min(np.linalg.norm(world - c, axis=1)) - r - robot.body_radius - D_SF)
    np.testing.assert_allclose(v.rod_clearance, rod_c, atol=1e-3)  # verify solves to 1e-6 N: ~1e-4 mm
    np.testing.assert_allclose(v.pcc_clearance, pcc_c, atol=1e-9)
    assert v.failed == 0
    assert v.rod.clearance == pytest.approx(min(rod_c), abs=1e-3)
    assert v.rod.t == pytest.approx(tt[int(np.argmin(rod_c))])
    assert v.clearance_loss == pytest.approx(max(np.array(pcc_c) - np.array(rod_c)), abs=1e-3)


def _sideways(robot: Robot) -> Robot:
    """cdsr2 lying on its side, tension-controlled: gravity along -x of the base frame."""
    mech = dict(robot.mechanics or {})
    mech["gravity"] = [-9.80665, 0.0, 0.0]
    mech["actuation"] = "tension"
    return dataclasses.replace(robot, mechanics=mech)


def test_gravity_sag_into_an_obstacle_is_caught(robot: Robot, tmp_path: Path) -> None:
    """A straight robot lying sideways sags onto a sphere placed under its tip: PCC keeps D_sf, the rod
    touches; the command says CONTACT and exits 1, names the mode, and without gravity it passes."""
    side = _sideways(robot)
    x = robot.straight(robot.z_range[0])
    sagged = CosseratRod(side).solve(np.ones(6), RodLoad())  # the straight pose's 1 N pretension
    assert sagged.is_success()
    tip = sagged.tip + np.array([0.0, 0.0, x[-1]])
    pcc_tip = Model(robot).tip_position(x)
    assert np.linalg.norm(tip - pcc_tip) > 30.0  # the sag is large against D_sf + body + radius
    scene = _scene([{"center": (tip - np.array([4.0, 0.0, 0.0])).tolist(), "radius": 3.0}])
    t = np.array([0.0, 1.0])
    doc = _document(side, scene, t, np.stack([x, x]))
    v = verify_cosserat(read_result(doc), side)
    assert v.pcc.clearance > 5.0 and v.contact and not v.holds
    assert v.rod.clearance == pytest.approx(4.0 - 3.0 - robot.body_radius - D_SF, abs=1e-3)
    res = tmp_path / "side.json"
    res.write_text(json.dumps(doc), encoding="utf-8")
    robot_file = tmp_path / "side.toml"
    text = CDSR2.read_text(encoding="utf-8").replace("gravity = [0.0, 0.0, -9.80665]", "gravity = [-9.80665, 0, 0]")
    text = text.replace("[robot.mechanics]", '[robot.mechanics]\nactuation = "tension"')
    robot_file.write_text(text, encoding="utf-8")
    cmd = [sys.executable, "-m", "crtraj.cli", "verify", str(res), "--model", "cosserat", "--robot", str(robot_file)]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 1, out.stderr
    assert "CONTACT" in out.stdout and "extra D_sf this result needs" in out.stdout
    assert "Cosserat rod (actuation tension) with gravity" in out.stdout
    free = subprocess.run([*cmd, "--no-gravity"], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert free.returncode == 0, free.stdout + free.stderr
    assert "Cosserat: min clearance" in free.stdout and "holds" in free.stdout


def test_bad_verify_inputs_are_one_line(robot: Robot, tmp_path: Path) -> None:
    """A missing --model, a bad --substeps, or a result without mechanics to find: one line, exit 2."""
    t, x = _path(robot, 3)
    res = tmp_path / "r.json"
    res.write_text(json.dumps(_document(robot, _scene([]), t, x)), encoding="utf-8")
    base = [sys.executable, "-m", "crtraj.cli", "verify", str(res)]
    for extra, needle in (
        ([], "--model"),
        (["--model", "cosserat", "--robot", str(CDSR2), "--substeps", "0"], "--substeps"),
        (["--model", "cosserat"], "--robot"),
    ):
        out = subprocess.run(base + extra, capture_output=True, text=True, cwd=ROOT, timeout=600)
        assert out.returncode == 2 and needle in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr


def _box_distance(p: np.ndarray, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Closed-form signed distance (N,) mm of points p (N, 3) to an axis-aligned box."""
    q = np.abs(p - centre) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def _cylinder_distance(p: np.ndarray, centre: np.ndarray, radius: float, length: float) -> np.ndarray:
    """Closed-form signed distance (N,) mm of points p (N, 3) to a solid cylinder about z through `centre`."""
    y = p - centre
    q = np.stack([np.hypot(y[:, 0], y[:, 1]) - radius, np.abs(y[:, 2]) - 0.5 * length], axis=1)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def test_shapes_are_checked_against_the_rods_body_and_pccs(robot: Robot) -> None:
    """A box under the sagged rod's tip touches the rod but not PCC's straight body; a cylinder at PCC's tip
    touches PCC but not the sagged rod: each model's clearance equals a closed-form distance to its own body."""
    side = _sideways(robot)
    x = robot.straight(robot.z_range[0])
    sag = CosseratRod(side).solve(np.ones(6), RodLoad())
    assert sag.is_success()
    lift = np.array([0.0, 0.0, x[-1]])
    rod_pts, pcc_pts = sag.points + lift, pcc_nodes(Model(robot), x, Mechanics.from_robot(side).steps) + lift
    half = np.array([3.0, 3.0, 3.0])
    box_c = rod_pts[-1] - np.array([5.0, 0.0, 0.0])  # 2 mm below the sagged tip
    cyl_c, cyl_r, cyl_len = pcc_pts[-1] + np.array([6.0, 0.0, 0.0]), 4.0, 8.0  # 2 mm beside PCC's tip
    shapes = [
        {"kind": "box", "half_extents": half.tolist(), "position": box_c.tolist()},
        {"kind": "cylinder", "radius": cyl_r, "length": cyl_len, "position": cyl_c.tolist()},
    ]
    scene = Scene.from_table(Table({"safety_distance": D_SF, "shape": shapes}, "scene"))
    v = verify_cosserat(read_result(_document(side, scene, np.array([0.0, 1.0]), np.stack([x, x]))), side)

    def clearance(pts: np.ndarray) -> tuple[float, float]:
        body = robot.body_radius + D_SF
        box = _box_distance(pts, box_c, half).min() - body
        return float(box), float(_cylinder_distance(pts, cyl_c, cyl_r, cyl_len).min() - body)

    rod_box, rod_cyl = clearance(rod_pts)
    pcc_box, pcc_cyl = clearance(pcc_pts)
    assert rod_box < -D_SF and rod_cyl > 10.0 and pcc_cyl < -D_SF and pcc_box > 10.0  # each touches one body
    np.testing.assert_allclose(v.rod_clearance, min(rod_box, rod_cyl), atol=1e-3)
    np.testing.assert_allclose(v.pcc_clearance, min(pcc_box, pcc_cyl), atol=1e-9)
    assert v.contact and not v.holds
    assert v.rod.name == "shape 0 (box)" and v.pcc.name == "shape 1 (cylinder)"
    assert v.rod.node == int(np.argmin(_box_distance(rod_pts, box_c, half)))
    assert v.pcc.node == int(np.argmin(_cylinder_distance(pcc_pts, cyl_c, cyl_r, cyl_len)))
