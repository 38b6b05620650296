"""Robots of 1 to 4 segments end to end (problems/robots/cdsr{1,2,3,4}.toml and problems/cdsrN_*.toml).

Everything is judged against computations written here from the paper's equations, not the library's:
the piecewise-constant-curvature forward kinematics (one arc per segment, coupled bending vectors of
eq. 9-11, base translation z), the cable lengths of eq. 4, and a dense body-to-sphere clearance check
that reads the obstacles straight from the problem file. Streaming runs on a virtual clock.
"""

from __future__ import annotations

import json
import math
from functools import cache
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import PROBLEMS
from devlink import CoreLink

from crtraj.app.devices import plan_approach
from crtraj.cli import main
from crtraj.core.clock import VirtualClock
from crtraj.core.fileio import read_toml
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import admit
from crtraj.hardware.protocol import MOVE, Frame
from crtraj.hardware.sim import DeviceCore
from crtraj.hardware.stream import Streamer, StreamOptions
from crtraj.io.problem import load_robot
from crtraj.io.results import read_result
from crtraj.model.kinematics import Model

SEGMENTS = (1, 3, 4)
# Points along the body of the independent clearance check: with at most 400 mm of backbone they are
# < 2.1 mm apart, and a chord that short deviates from an arc of bend radius >= 28 mm by < 0.02 mm.
_DENSE_POINTS = 200
_SAGITTA = 0.02  # mm


# ------------------------------------------------------------- independent closed forms
@cache
def _robot_data(n: int) -> dict:
    return read_toml(PROBLEMS / "robots" / f"cdsr{n}.toml")["robot"]


def _coupled(u: np.ndarray, c: float) -> np.ndarray:
    """Paper eq. 9-11, segment by segment from the tip: u_bar_n = u_n, u_bar_k = u_k + c u_bar_(k+1)."""
    ub = u.copy()
    for k in range(len(u) - 2, -1, -1):
        ub[k] = u[k] + c * ub[k + 1]
    return ub


def _rz(phi: float) -> np.ndarray:
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _arc(theta: float, phi: float, s: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
    """(rotations (k, 3, 3), positions (k, 3)) at arc lengths s (k,) of a constant-curvature arc bending
    theta over `length` in the plane at angle phi: R = Rz(phi) Ry(a) Rz(-phi) and
    p = rho (cos phi (1 - cos a), sin phi (1 - cos a), sin a) with a = theta s / length, rho = length / theta
    (the straight line when theta = 0)."""
    s = np.atleast_1d(np.asarray(s, dtype=float))
    if theta < 1e-12:
        return np.broadcast_to(np.eye(3), (len(s), 3, 3)), np.stack([0 * s, 0 * s, s], axis=1)
    a = theta * s / length
    rho = length / theta
    vers = 2.0 * np.sin(0.5 * a) ** 2  # 1 - cos a, without its cancellation at small a
    ry = np.zeros((len(s), 3, 3))
    ry[:, 0, 0] = ry[:, 2, 2] = np.cos(a)
    ry[:, 0, 2], ry[:, 2, 0], ry[:, 1, 1] = np.sin(a), -np.sin(a), 1.0
    rz = _rz(phi)
    p = np.stack([rho * math.cos(phi) * vers, rho * math.sin(phi) * vers, rho * np.sin(a)], axis=1)
    return rz @ ry @ rz.T, p


def closed_form_points(n: int, x: np.ndarray, arcs: np.ndarray) -> np.ndarray:
    """Backbone points (len(arcs), 3) in mm at arc lengths `arcs` from the base, configuration x =
    (u_1x, u_1y, ..., u_nx, u_ny, z)."""
    data = _robot_data(n)
    lengths = [float(s["length"]) for s in data["segment"]]
    ub = _coupled(np.asarray(x[:-1], dtype=float).reshape(n, 2), float(data["coupling"]))
    starts = np.concatenate([[0.0], np.cumsum(lengths)])
    arcs = np.asarray(arcs, dtype=float)
    out = np.empty((len(arcs), 3))
    R, o = np.eye(3), np.array([0.0, 0.0, float(x[-1])])
    for k, length in enumerate(lengths):
        theta, phi = float(np.hypot(*ub[k])), float(math.atan2(ub[k][1], ub[k][0]))
        mine = (arcs >= starts[k]) & ((arcs < starts[k + 1]) | (k == n - 1))
        _, p = _arc(theta, phi, arcs[mine] - starts[k], length)
        out[mine] = o + p @ R.T
        Rk, p = _arc(theta, phi, np.array([length]), length)
        o, R = o + R @ p[0], R @ Rk[0]
    return out


def closed_form_tip(n: int, x: np.ndarray) -> np.ndarray:
    """Tip position (3,) in mm: the backbone point at the robot's full length."""
    total = sum(float(s["length"]) for s in _robot_data(n)["segment"])
    return closed_form_points(n, x, np.array([total]))[0]


def closed_form_cables(n: int, x: np.ndarray) -> np.ndarray:
    """Paper eq. 4: cable i of segment k is L_k - r theta_k cos(phi_k + alpha_ki), alpha_ki = phase_k + 2 pi i / 3,
    (theta_k, phi_k) the segment's own (uncoupled) bending; then z."""
    data = _robot_data(n)
    r = float(data["cable_radius"])
    q = []
    for k, seg in enumerate(data["segment"]):
        ux, uy = x[2 * k], x[2 * k + 1]
        theta, phi = math.hypot(ux, uy), math.atan2(uy, ux)
        for i in range(3):
            alpha = float(seg.get("cable_phase", 0.0)) + 2.0 * math.pi * i / 3.0
            q.append(float(seg["length"]) - r * theta * math.cos(phi + alpha))
    return np.array([*q, x[-1]])


def _obstacles(problem: Path) -> list[dict]:
    return read_toml(problem)["scene"]["obstacle"]


def _sphere_states(obstacles: list[dict], t: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (m, 3) and radii (m,) of the problem file's fixed-centre spheres at time t (s):
    radius = mean + amplitude sin(omega t + phase), or a constant."""
    centres, radii = [], []
    for ob in obstacles:
        r = ob["radius"]
        if isinstance(r, dict):
            r = r["mean"] + r.get("amplitude", 0.0) * math.sin(r.get("omega", 0.0) * t + r.get("phase", 0.0))
        centres.append(ob["center"])
        radii.append(float(r))
    return np.array(centres, dtype=float), np.array(radii)


def body_clearance(n: int, problem: Path, times: np.ndarray, configs: np.ndarray) -> float:
    """Smallest distance (mm) from the body surface (backbone chords plus the disc radius) to any sphere surface,
    minus D_sf, over the given samples."""
    data = _robot_data(n)
    table = read_toml(problem)["scene"]
    d_sf, body = float(table["safety_distance"]), float(data["body_radius"])
    obstacles = _obstacles(problem)
    arcs = np.linspace(0.0, sum(float(s["length"]) for s in data["segment"]), _DENSE_POINTS)
    worst = math.inf
    for t, x in zip(times, configs, strict=True):
        pts = closed_form_points(n, x, arcs)
        a, ab = pts[:-1], np.diff(pts, axis=0)
        centres, radii = _sphere_states(obstacles, float(t))
        for c, r in zip(centres, radii, strict=True):
            u = np.clip(np.einsum("ij,ij->i", c - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0, 1)
            dist = np.linalg.norm(a + u[:, None] * ab - c, axis=1).min()
            worst = min(worst, dist - r - body - d_sf)
    return worst


def densify(times: np.ndarray, configs: np.ndarray, n: int, step: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints linearly interpolated in configuration (as the streamer moves between them) so that no
    backbone point moves more than `step` mm between samples (by the closed-form FK)."""
    data = _robot_data(n)
    arcs = np.linspace(0.0, sum(float(s["length"]) for s in data["segment"]), 20)
    T, X = [times[0]], [configs[0]]
    for i in range(len(times) - 1):
        move = np.abs(closed_form_points(n, configs[i + 1], arcs) - closed_form_points(n, configs[i], arcs)).max()
        k = max(1, math.ceil(2.0 * move / step))  # a point moves at most about twice its endpoint displacement
        for j in range(1, k + 1):
            f = j / k
            T.append(times[i] + f * (times[i + 1] - times[i]))
            X.append(configs[i] + f * (configs[i + 1] - configs[i]))
    return np.array(T), np.array(X)


# ----------------------------------------------------------------------------- kinematics
@pytest.mark.parametrize("n", (1, 2, 3, 4))
def test_fk_and_cables_match_the_closed_form(n):
    """Tip, backbone and cable lengths at random configurations within the limits (and at the straight
    pose) agree with the closed forms to 1e-9 mm."""
    robot = load_robot(PROBLEMS / "robots" / f"cdsr{n}.toml")
    assert robot.n_segments == n and robot.nx == 2 * n + 1 and robot.nq == 3 * n + 1
    model = Model(robot)
    lo, hi = robot.config_box()
    X = np.random.default_rng(n).uniform(lo, hi, size=(40000, robot.nx))
    X = X[robot.limit_violation(X) <= 0.0][:25]
    X = np.vstack([robot.straight(0.0), robot.straight(-50.0) + 1e-7, X])
    assert len(X) >= 20
    arcs = model.arc_positions(13)
    for x in X:
        ref = closed_form_points(n, x, arcs)
        np.testing.assert_allclose(model.points(x, 13), ref, atol=1e-9)
        np.testing.assert_allclose(model.tip_position(x), ref[-1], atol=1e-9)
        np.testing.assert_allclose(model.cables(x), closed_form_cables(n, x), atol=1e-9)
    # the straight pose: the tip is on the axis, the robot's length above the base
    np.testing.assert_allclose(model.tip_position(robot.straight(10.0)), [0.0, 0.0, robot.total_length + 10.0])


# ----------------------------------------------------------------------- plan and replan
@cache
def _plan_file(n: int, folder: str) -> Path:
    out = Path(folder) / f"plan{n}.json"
    assert main(["plan", str(PROBLEMS / f"cdsr{n}_static.toml"), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def plans(tmp_path_factory):
    folder = str(tmp_path_factory.mktemp("segments"))
    return lambda n: _plan_file(n, folder)


@pytest.mark.parametrize("n", SEGMENTS)
def test_static_plan_keeps_dsf_by_the_independent_check(n, plans):
    problem = PROBLEMS / f"cdsr{n}_static.toml"
    task = read_toml(problem)["task"]
    res = read_result(plans(n))
    assert res.success and res.x.shape[1] == 2 * n + 1
    tips = np.array([closed_form_tip(n, x) for x in (res.x[0], res.x[-1])])
    assert np.linalg.norm(tips[0] - task["start"]) <= 1e-3
    assert np.linalg.norm(tips[1] - task["goal"]) <= task["goal_tolerance"] + 1e-9
    T, X = densify(res.t, res.x, n)
    assert body_clearance(n, problem, T, X) >= -_SAGITTA


@pytest.mark.parametrize("n", SEGMENTS)
def test_replan_run_arrives_and_keeps_dsf_by_the_independent_check(n, tmp_path):
    """The closed loop among breathing spheres: every dense sample of the executed motion keeps D_sf at
    its own time, by the closed-form FK and the spheres read from the problem file."""
    problem = PROBLEMS / f"cdsr{n}_dynamic.toml"
    out = tmp_path / "run"
    assert main(["replan", str(problem), "--out", str(out), "--quiet", "--no-html"]) == 0
    doc = json.loads((out / "run.json").read_text())
    assert doc["success"] and doc["summary"]["safety_violations"] == 0
    arrays = np.load(out / "run.npz")
    T, X = arrays["dense_t"], arrays["dense_x"]
    assert X.shape[1] == 2 * n + 1 and len(T) > 100
    assert body_clearance(n, problem, T, X) >= -_SAGITTA
    goal = read_toml(problem)["task"]
    tip = closed_form_tip(n, arrays["x"][-1])
    assert np.linalg.norm(tip - goal["goal"]) <= goal["goal_tolerance"] + 1e-9


# -------------------------------------------------------------------------------- stream
@pytest.mark.parametrize("n", SEGMENTS)
def test_plan_streams_to_the_sim_device_with_a_planned_approach(n, plans):
    """The device starts straight at z = 0, away from the plan's start: the planned approach and the plan
    stream on a virtual clock, every move frame carries 3 n + 1 values, every frame's pose keeps D_sf by
    the independent check, and the device ends at the plan's last set-point."""
    robot = load_robot(PROBLEMS / "robots" / f"cdsr{n}.toml")
    acts = Actuators.from_robot(robot)
    motion = admit(read_result(plans(n)).motion_record(), acts)
    clock = VirtualClock()
    core = DeviceCore(acts)
    link = CoreLink(core, clock)
    streamer = Streamer(link, acts, StreamOptions(), None, realtime=True, clock=clock)
    rep = streamer.run_path(motion, approach=True, plan_approach=plan_approach)
    assert rep.ok, rep.message
    moves = np.array([f.values for f in map(Frame.decode, link.sent) if f.kind == MOVE])
    assert moves.shape[1] == 3 * n + 1 and len(moves) > len(motion.values)
    np.testing.assert_array_equal(moves[-len(motion.values) :], motion.values)
    configs = np.array([robot.config(acts.actuation(v)) for v in moves[:: max(1, len(moves) // 400)]])
    assert body_clearance(n, PROBLEMS / f"cdsr{n}_static.toml", np.zeros(len(configs)), configs) >= -_SAGITTA
    np.testing.assert_allclose(core.state()["positions"], motion.values[-1], atol=0.02)


# ------------------------------------------------------------------- export, view, bench
@pytest.mark.parametrize("n", SEGMENTS)
def test_export_view_and_bench_work(n, plans, tmp_path):
    """The exported tip function (a .casadi file) agrees with the closed form; the view writes its page;
    a one-scenario bench of the default planner runs and records it."""
    robot_file = PROBLEMS / "robots" / f"cdsr{n}.toml"
    assert main(["export", "--robot", str(robot_file), "--out", str(tmp_path / "e"), "--no-compile"]) == 0
    tip = ca.Function.load(str(tmp_path / "e" / "tip.casadi"))
    x = read_result(plans(n)).x[-1]
    np.testing.assert_allclose(np.array(tip(x)).ravel(), closed_form_tip(n, x), atol=1e-9)
    assert main(["view", str(plans(n)), "--html", str(tmp_path / "v.html")]) == 0
    assert (tmp_path / "v.html").stat().st_size > 100_000
    args = ["bench", "table1", "--robot", str(robot_file), "--scenarios", "1", "--counts", "1"]
    args += ["--planners", "cspace", "--workers", "0", "--time-limit", "5", "--no-progress"]
    args += ["--out", str(tmp_path / "b")]
    assert main(args) == 0
    rows = (tmp_path / "b" / "runs.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith("cspace,1,0,")
    scenario = json.loads((tmp_path / "b" / "scenarios.json").read_text())["scenarios"][0]
    assert len(scenario["start_config"]) == 2 * n + 1
