"""Calibration (`crtraj record`, `crtraj calibrate`): recovery of a synthetic truth, identifiability, bad data,
the comment-preserving robot file rewrite, the round trip into planning, and the exact Jacobian.

Synthetic truth (`synthetic_truth`): cdsr2 with segment lengths +-5 %, coupling -0.8 instead of -1, servo
zero offsets uniform in +-0.05 rad, the capture frame rotated 10 degrees about a random axis and shifted
50 mm; markers (base, proximal tip, distal tip) with 0.3 mm noise per axis and 2 % outliers of ~20 mm.
"""

from __future__ import annotations

import json
import math
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.lab._calibrate import calibrate
from crtraj.app.lab._calibration_report import toml_changes
from crtraj.app.lab._record import excitation_motion
from crtraj.cli import main
from crtraj.control.loop import ClosedLoop
from crtraj.core.errors import AdmissionError, InputError
from crtraj.core.tomledit import set_values
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.mocap import MocapTip, SimulatedMocap
from crtraj.io.calibration_data import Dataset, read_calibration
from crtraj.io.mocap import LogSeries, MarkerFrames, join, read_markers, read_stream_log
from crtraj.io.problem import Problem, load_robot
from crtraj.io.results import read_result
from crtraj.model.calibration import (
    GROUPS,
    CalibrateOptions,
    CalibrationModel,
    Hardware,
    Layout,
    MarkerSite,
    Observations,
    fit,
    paper_markers,
    rotation_matrix,
    simulate_markers,
    split,
    synthetic_truth,
    synthetic_values,
)
from crtraj.model.kinematics import Model
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "problems" / "robots" / "cdsr2.toml"
NOISE = 0.3  # mm per axis
N = 400


@pytest.fixture(scope="module")
def setup():
    robot = load_robot(ROBOT)
    act = Actuators.from_robot(robot)
    hw = Hardware(act.spool_radius, act.sign)
    return robot, act, hw, paper_markers(robot.n_segments)


@pytest.fixture(scope="module")
def synthetic(setup):
    robot, act, hw, sites = setup
    truth = synthetic_truth(robot, act.zero_offset, seed=3)
    values = synthetic_values(robot, hw, N, seed=11)
    m, bad = simulate_markers(
        truth.robot, hw, truth.zero_offsets, truth.capture, values, sites, noise=NOISE, outliers=0.02, seed=5
    )
    clean, _ = simulate_markers(truth.robot, hw, truth.zero_offsets, truth.capture, values, sites)
    obs = Observations(values, m, sites, split(N, 0.2, 0))
    res = fit(robot, hw, act.zero_offset, obs, GROUPS)
    return truth, values, m, bad, clean, obs, res


def _equivalent_truth(truth, res, act) -> np.ndarray:
    """The true parameters as this data can express them with the held ones at their prior (closed form):
    a common zero offset of a segment's three cables is invisible (the pseudo-inverse of eq. 2-3 removes it,
    equal spools and signs), and the stage's zero offset moves the markers like the capture translation
    along the robot's z axis (p_robot = R m + t)."""
    names = res.layout.names
    eq = truth.theta.copy()
    for k in range(act.n_segments):
        i3 = names.index(f"s{k + 1}c3.zero_offset")
        shift = eq[i3] - res.prior[i3]
        for i in range(3):
            eq[names.index(f"s{k + 1}c{i + 1}.zero_offset")] -= shift
    iz = names.index("z.zero_offset")
    eq[-1] += act.sign[-1] * (eq[iz] - res.prior[iz])
    eq[iz] = res.prior[iz]
    return eq


def test_fit_recovers_every_identifiable_parameter(synthetic, setup):
    _, act, _, _ = setup
    truth, *_, res = synthetic
    assert res.success, res.status
    held = {h.name for h in res.held}
    assert held == {"s1c3.zero_offset", "s2c3.zero_offset", "z.zero_offset"}
    for i, name in enumerate(res.layout.names):
        if name in held:
            assert res.theta[i] == res.prior[i], f"{name} moved although held"
    eq = _equivalent_truth(truth, res, act)
    free = res.free
    z = np.abs(res.theta[free] - eq[free]) / res.std_error[free]
    worst = int(np.argmax(z))
    assert z.max() <= 3.0, f"{np.array(res.layout.names)[free][worst]}: {z.max():.2f} standard errors from the truth"
    # and the errors are small in absolute terms: the data determine the parameters well
    i_l = res.layout.index("lengths")
    assert np.all(res.std_error[i_l] < 0.1)
    assert abs(res.value("coupling") + 0.8) < 5e-3


def test_heldout_tip_error_is_at_the_noise_level(synthetic, setup):
    robot, _act, hw, sites = setup
    _, values, m, bad, clean, obs, res = synthetic
    cm = CalibrationModel(robot, hw, sites, res.layout)
    held = obs.heldout & ~bad[:, -1]  # the test's own outlier mask, independent of the fit's
    tip = -1

    def tip_rms(theta):
        # compare in the robot frame: the prediction against the measured marker mapped through the frame
        e = cm.residuals(theta, values[held], m[held])[:, tip]
        return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))

    after = tip_rms(res.theta)
    before = tip_rms(res.prior)
    noise_rms = NOISE * math.sqrt(3)
    print(f"held-out tip RMS: uncalibrated {before:.2f} mm, calibrated {after:.3f} mm (noise {noise_rms:.3f} mm)")
    assert after <= 1.5 * noise_rms
    assert before > 10 * noise_rms  # the uncalibrated model is far off on the same data
    # the report's own figures agree with this independent computation (up to its outlier rule)
    rep = res.after["heldout"]["tip"]
    assert rep.rms_inliers == pytest.approx(after, rel=0.15)
    assert res.before["heldout"]["tip"].rms > 10 * rep.rms_inliers
    # prediction against the noise-free truth: far below the noise
    P = cm.predict(res.theta, values[held])[:, tip]
    w = res.capture()
    from_capture = clean[held, tip] @ rotation_matrix(w[:3]).T + w[3:]
    assert float(np.sqrt(np.mean(np.sum((P - from_capture) ** 2, axis=1)))) < 0.5 * NOISE


def test_a_distal_segment_that_never_bends_leaves_the_coupling_undetermined(setup):
    """In this model, motion in one plane still determines every parameter (a zero offset pushes the body out
    of the plane); what the data cannot determine is the coupling when the distal segment never bends: c
    only scales the distal bending that enters the proximal segment."""
    robot, act, hw, sites = setup
    truth = synthetic_truth(robot, act.zero_offset, seed=4)
    zo = truth.zero_offsets.copy()
    zo[3:6] = 0.0  # the distal segment's cables at their true zero: it stays straight
    values = synthetic_values(robot, hw, 200, seed=2, planar_distal=True)
    m, _ = simulate_markers(truth.robot, hw, zo, truth.capture, values, sites, noise=NOISE, seed=1)
    obs = Observations(values, m, sites, split(200, 0.2, 0))
    res = fit(robot, hw, act.zero_offset, obs, ("lengths", "coupling", "capture_frame"))
    assert [h.name for h in res.held] == ["coupling"]
    assert res.value("coupling") == robot.coupling  # not moved
    assert not res.free[res.layout.names.index("coupling")]
    assert res.success
    assert abs(res.value("segment[1].length") - truth.robot.segments[1].length) < 3 * res.std_error[1] + 1e-9
    # commanded bending in one plane only (both segments along x, the base moving): nothing more is lost than
    # the two common cable offsets and the stage offset, which no data determines
    rng = np.random.default_rng(0)
    x = np.zeros((200, robot.nx))
    x[:, 0], x[:, 2], x[:, -1] = rng.uniform(-0.8, 0.8, 200), rng.uniform(-0.8, 0.8, 200), rng.uniform(-50, 50, 200)
    planar = act.command(robot.cables(x))
    m, _ = simulate_markers(truth.robot, hw, truth.zero_offsets, truth.capture, planar, sites, noise=NOISE, seed=1)
    res = fit(robot, hw, act.zero_offset, Observations(planar, m, sites, split(200, 0.2, 0)), GROUPS)
    assert {h.name for h in res.held} == {"s1c3.zero_offset", "s2c3.zero_offset", "z.zero_offset"}


def test_jacobian_matches_finite_differences(setup):
    robot, act, hw, sites = setup
    truth = synthetic_truth(robot, act.zero_offset, seed=1)
    layout = Layout.build(truth.robot, truth.zero_offsets, truth.capture, CalibrateOptions())
    cm = CalibrationModel(robot, hw, sites, layout)
    values = synthetic_values(robot, hw, 5, seed=3)
    values[0, :6] = 0.0  # the straight pose: the series branch of the kinematics
    m = np.random.default_rng(0).normal(0, 100, (5, len(sites), 3))
    th = layout.prior
    J = cm.jacobians(th, values, m)
    h = 1e-6 * np.maximum(1.0, np.abs(th))
    for i in range(layout.n):
        d = np.zeros_like(th)
        d[i] = h[i]
        fd = (cm.residuals(th + d, values, m) - cm.residuals(th - d, values, m)) / (2 * h[i])
        np.testing.assert_allclose(J[..., i], fd, rtol=1e-5, atol=1e-5, err_msg=layout.names[i])


# ------------------------------------------------------------------ files and commands
def _log(path: Path, names, t, values) -> Path:
    lines = [json.dumps({"type": "header", "names": list(names)})]
    lines += [json.dumps({"type": "tx", "wall": float(ti), "kind": "move", "values": v.tolist()}) for ti, v in
              zip(t, values, strict=True)]  # fmt: skip
    path.write_text("\n".join(lines) + "\n")
    return path


def _markers_csv(path: Path, t, m, sites, scale: float = 1.0) -> Path:
    rows = ["timestamp,marker,x,y,z"]
    for i, ti in enumerate(t):
        for j, s in enumerate(sites):
            rows.append(f"{ti:.6f},{s.name}," + ",".join(f"{v * scale:.6f}" for v in m[i, j]))
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def recorded(setup, tmp_path_factory):
    """A stream log (set-points at 10 Hz) and a marker file (the true robot filmed at 7 Hz, own clock +100 s)."""
    robot, act, hw, sites = setup
    d = tmp_path_factory.mktemp("rec")
    truth = synthetic_truth(robot, act.zero_offset, seed=3)
    t_log = np.arange(0, 60.0, 0.1)
    base = synthetic_values(robot, hw, 61, seed=9)
    v_log = np.stack([np.interp(t_log, np.arange(61.0), base[:, i]) for i in range(act.n)], axis=1)
    t_cap = np.arange(0.05, 59.9, 1 / 7)
    v_cap = np.stack([np.interp(t_cap, t_log, v_log[:, i]) for i in range(act.n)], axis=1)
    m, _ = simulate_markers(
        truth.robot, hw, truth.zero_offsets, truth.capture, v_cap, sites, noise=NOISE, outliers=0.02, seed=2
    )
    log = _log(d / "log.jsonl", act.names, t_log, v_log)
    mk = _markers_csv(d / "markers.csv", t_cap + 100.0, m, sites)
    return d, truth, log, mk, t_cap, (t_log, v_log), m


def test_join_interpolates_the_log_at_marker_times():
    t = np.array([0.0, 0.1, 0.2, 0.3])
    vals = np.stack([1 + 2 * t, -3 * t], axis=1)  # linear: interpolation is exact
    frames = MarkerFrames(np.array([100.05, 100.25, 100.5]), np.zeros((3, 1, 3)))
    tl, v, _, dropped = join(LogSeries(("a", "b"), t, vals, "commanded"), frames, time_offset=100.0)
    np.testing.assert_allclose(tl, [0.05, 0.25])
    np.testing.assert_allclose(v, np.stack([1 + 2 * tl, -3 * tl], axis=1))
    assert dropped == 1
    with pytest.raises(InputError, match="do not overlap"):
        join(LogSeries(("a", "b"), t, vals, "commanded"), frames, time_offset=0.0)


def test_record_then_calibrate_round_trip_into_planning(recorded, setup, tmp_path, capsys):
    robot, act, hw, sites = setup
    _d, truth, log, mk, t_cap, (t_log, v_log), _ = recorded
    data = tmp_path / "data.json"
    assert main(["record", "--log", str(log), "--markers", str(mk), "--time-offset", "100", "--out", str(data)]) == 0
    doc = json.loads(data.read_text())
    np.testing.assert_allclose(doc["t"], t_cap, atol=1e-6)  # the capture times on the log's clock
    expect = np.stack([np.interp(doc["t"], t_log, v_log[:, i]) for i in range(act.n)], axis=1)
    np.testing.assert_allclose(doc["values"], expect, rtol=1e-12, atol=1e-12)  # interpolated there
    out = tmp_path / "cal.toml"
    assert main(["calibrate", str(data), "--robot", str(ROBOT), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "z.zero_offset is not identifiable" in text and "held at its prior" in text
    assert (tmp_path / "cal.residuals.png").read_bytes()[:4] == b"\x89PNG"
    report = json.loads((tmp_path / "cal.report.json").read_text())
    assert report["success"] and report["residuals_after"]["heldout"]["tip"]["count"] > 0
    # the file keeps every comment and key; only the fitted values changed, plus the [calibration] table
    orig, new = ROBOT.read_text(), out.read_text()
    for line in orig.splitlines():
        if line.strip().startswith("#"):
            assert line in new
    a, b = tomllib.loads(orig), tomllib.loads(new)
    assert set(b) == {"robot", "calibration"}
    for k in a["robot"]:
        if k not in ("segment", "coupling", "cable_radius", "actuators"):
            assert a["robot"][k] == b["robot"][k]
    for key in ("theta_max", "cable_phase"):
        assert [s[key] for s in a["robot"]["segment"]] == [s[key] for s in b["robot"]["segment"]]
    rec = read_calibration(out)
    assert rec is not None and rec.dataset == str(data) and rec.date and "coupling" in rec.fitted
    # load it like any robot file, plan with it; the true robot running the plan's set-points puts its tip
    # where the plan says
    cal = load_robot(out)
    assert abs(cal.coupling + 0.8) < 0.01
    prob = tmp_path / "static.toml"
    static = (ROOT / "problems" / "paper_static.toml").read_text()
    prob.write_text(static.replace('robot = "robots/cdsr2.toml"', f'robot = "{out}"'))
    assert main(["plan", str(prob), "--out", str(tmp_path / "plan.json")]) == 0
    res = read_result(tmp_path / "plan.json")
    commanded = Actuators.from_robot(cal).command(res.q)
    true_layout = Layout.build(truth.robot, truth.zero_offsets, truth.capture, CalibrateOptions())
    true_tip = CalibrationModel(truth.robot, hw, sites, true_layout).predict(true_layout.prior, commanded)[:, -1]
    err = np.linalg.norm(true_tip - res.tip, axis=1)
    nominal = Actuators.from_robot(robot).command(res.q)  # the same plan sent with the uncalibrated file
    nominal_tip = CalibrationModel(truth.robot, hw, sites, true_layout).predict(true_layout.prior, nominal)[:, -1]
    err_nominal = np.linalg.norm(nominal_tip - res.tip, axis=1)
    print(
        f"plan tip vs truth: calibrated max {err.max():.3f} mm; set-points of the nominal file {err_nominal.max():.1f}"
    )
    assert err.max() < 0.5
    assert err_nominal.max() > 10.0


def _one_error(capsys, argv) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, (code, err)
    return err[0]


def test_bad_data_one_line_each(recorded, setup, tmp_path, capsys):
    _robot, _act, _hw, sites = setup
    _d, _truth, log, mk, t_cap, _, m = recorded
    good = tmp_path / "good.json"
    assert main(["record", "--log", str(log), "--markers", str(mk), "--time-offset", "100", "--out", str(good)]) == 0
    doc = json.loads(good.read_text())
    cal = ["calibrate", "--robot", str(ROBOT), "--out", str(tmp_path / "c.toml")]

    nan = tmp_path / "nan.json"
    bad = json.loads(good.read_text())
    bad["values"][3][2] = float("nan")
    nan.write_text(json.dumps(bad))
    assert "values[3][2]: must be finite" in _one_error(capsys, [*cal, str(nan)])

    few = tmp_path / "few.json"
    bad = dict(doc, t=doc["t"][:10], values=doc["values"][:10])
    bad["positions"] = {k: v[:10] for k, v in doc["positions"].items()}
    few.write_text(json.dumps(bad))
    assert "10 samples, need at least 20" in _one_error(capsys, [*cal, str(few)])

    unknown = tmp_path / "unknown.csv"
    unknown.write_text(mk.read_text() + "100.5,elbow,1,2,3\n")
    rec = ["record", "--log", str(log), "--time-offset", "100", "--out", str(tmp_path / "x.json")]
    assert "marker 'elbow' unknown" in _one_error(capsys, [*rec, "--markers", str(unknown)])

    assert "do not overlap" in _one_error(
        capsys, ["record", "--log", str(log), "--markers", str(mk), "--out", str(tmp_path / "y.json")]
    )

    metres = _markers_csv(tmp_path / "m.csv", t_cap + 100.0, m, sites, scale=1e-3)
    data_m = tmp_path / "metres.json"
    assert "not in mm" in _one_error(capsys, [*rec[:-2], "--markers", str(metres), "--out", str(data_m)])
    assert not data_m.exists()  # record checks the units as calibrate does
    bad = json.loads(good.read_text())
    bad["positions"] = {
        k: [None if p is None else [x * 1e-3 for x in p] for p in v] for k, v in doc["positions"].items()
    }
    data_m.write_text(json.dumps(bad))
    assert "not in mm" in _one_error(capsys, [*cal, str(data_m)])
    assert not (tmp_path / "c.toml").exists()  # nothing written on any of them


def test_toml_rewriter_changes_only_the_asked_values():
    text = '# head\n[a]\nx = 1.0   # keep me\ny = "s # not a comment"\n\n[[a.b]]\nz = 2\n[[a.b]]\nz = 3 # third\n'
    out = set_values(text, {("a", "x"): 2.5, ("a", "b", 1, "z"): 4, ("a", "w"): 1.0, ("c", "d"): [1.0, 2.0]})
    assert "x = 2.5   # keep me" in out and "z = 4 # third" in out and "# head" in out
    t = tomllib.loads(out)
    assert t["a"]["x"] == 2.5 and t["a"]["b"] == [{"z": 2}, {"z": 4}] and t["a"]["w"] == 1.0 and t["c"]["d"] == [1, 2]
    assert t["a"]["y"] == "s # not a comment"
    # a table defined through a dotted key gets the new key as a dotted key (tomlkit), not a second header
    assert tomllib.loads(set_values("a.b = 1\n", {("a", "c"): 2.0})) == {"a": {"b": 1, "c": 2.0}}


def test_toml_changes_exclude_held_and_unfitted_parameters(synthetic):
    *_, res = synthetic
    ch = toml_changes(res)
    assert ("robot", "actuators", "servo", "s1c3", "zero_offset") not in ch
    assert ("robot", "actuators", "z", "zero_offset") not in ch
    assert ch[("robot", "coupling")] == res.value("coupling")
    assert len(ch) == int(res.free.sum()) - 6  # every fitted robot parameter; the capture frame is not a robot key


def test_excitation_is_admitted_and_refused_when_it_would_hit_an_obstacle(setup):
    robot, act, _, _ = setup
    motion = excitation_motion(robot, act, Scene(), rate=50.0)
    assert motion.values.shape[1] == act.n
    assert np.all(act.position_violation(motion.values) <= 0)
    ball = Obstacle(center=(0.0, 0.0, 250.0), radius=20.0)  # on the straight body it starts from
    with pytest.raises(AdmissionError, match=r"refused|obstacle|D_sf"):
        excitation_motion(robot, act, Scene(obstacles=(ball,)), rate=50.0)


def test_calibrate_use_case_holds_a_capture_frame_it_is_not_asked_to_fit(synthetic, setup):
    robot, act, _hw, sites = setup
    truth, values, m, *_ = synthetic
    ds = Dataset(act.names, sites, np.arange(N, dtype=float), values, m)
    res = calibrate(ds, robot, ("lengths", "coupling", "zero_offsets"), CalibrateOptions(), capture=truth.capture)
    np.testing.assert_array_equal(res.capture(), truth.capture)
    assert res.success and abs(res.value("coupling") + 0.8) < 0.01


def test_calibration_kinematics_agree_with_the_model_at_nominal_parameters(setup):
    """The calibration's own forward kinematics (symbolic in the parameters) against `Model` (independent)."""
    robot, act, hw, _ = setup
    sites = (*paper_markers(2), MarkerSite("mid2", 1, 100.0))
    layout = Layout.build(robot, act.zero_offset, np.zeros(6), CalibrateOptions())
    cm = CalibrationModel(robot, hw, sites, layout)
    values = synthetic_values(robot, hw, 20, seed=4)
    x = robot.config(act.actuation(values))
    model = Model(robot)
    pts = model.points(x, 5)  # arc lengths 0, 100, 200, 300, 400 mm
    P = cm.predict(layout.prior, values)
    np.testing.assert_allclose(P[:, 0], pts[:, 0], atol=1e-9)
    np.testing.assert_allclose(P[:, 1], pts[:, 2], atol=1e-9)
    np.testing.assert_allclose(P[:, 2], pts[:, 4], atol=1e-9)
    np.testing.assert_allclose(P[:, 3], pts[:, 3], atol=1e-9)
    sensor = SimulatedMocap(robot, act, noise=0.0)
    np.testing.assert_allclose(sensor.true_tip(robot.cables(x[3])), model.tip_position(x[3]), atol=1e-9)


@pytest.mark.slow
def test_tip_feedback_corrects_the_model_error_in_closed_loop(tmp_path):
    """The true robot differs from the model (lengths +-2 %, coupling -0.95, zero offsets ~0.01 rad): the loop
    brings the model's tip to the goal, which leaves the true tip off by the model error; with the motion
    capture tip as its measurement it brings the measured tip there instead."""
    text = ROBOT.read_text()
    changes = {
        ("robot", "segment", 0, "length"): 204.0,
        ("robot", "segment", 1, "length"): 196.0,
        ("robot", "coupling"): -0.95,
        ("robot", "actuators", "servo", "s1c1", "zero_offset"): 0.01,
        ("robot", "actuators", "servo", "s2c3", "zero_offset"): -0.01,
    }
    true_file = tmp_path / "true.toml"
    true_file.write_text(set_values(text, changes))
    problem = Problem.load(ROOT / "problems" / "paper_dynamic.toml")
    act = Actuators.from_robot(problem.robot)
    sensor = SimulatedMocap(load_robot(true_file), act, noise=0.1, seed=0)
    loop = ClosedLoop.from_problem(problem, tip_sensor=sensor, tip_feedback=True)
    run = loop.run()
    assert run.reached, run.message
    true_final = sensor.true_tip(run.q[-1])
    err_true = float(np.linalg.norm(true_final - run.goal))
    err_model = float(run.goal_error[-1])  # where the model's tip is: the error a loop without feedback keeps
    print(f"true tip error with feedback {err_true:.2f} mm; model error at the goal {err_model:.2f} mm")
    assert err_true < 1.0
    assert err_model > 5.0
    assert run.measured_tip is not None and run.measured_tip.shape == (len(run.t), 3)


def test_one_command_from_a_log_and_a_marker_file(recorded, tmp_path, capsys):
    _, _, log, mk, *_ = recorded
    out = tmp_path / "cal.toml"
    argv = ["calibrate", "--log", str(log), "--markers", str(mk), "--time-offset", "100", "--robot", str(ROBOT)]
    assert main([*argv, "--out", str(out), "--fit", "lengths,coupling,zero_offsets,capture_frame"]) == 0
    rec = read_calibration(out)
    assert rec is not None and str(log) in rec.dataset and "coupling" in rec.fitted
    assert abs(load_robot(out).coupling + 0.8) < 0.01
    assert (tmp_path / "cal.report.json").exists()
    capsys.readouterr()
    assert "not both" in _one_error(capsys, [*argv, str(tmp_path / "data.json"), "--out", str(tmp_path / "x.toml")])
    assert "arc 500 mm is beyond segment 1" in _one_error(
        capsys, [*argv, "--marker", "base=1:0", "--marker", "far=1:500", "--out", str(tmp_path / "y.toml")]
    )


def test_live_mocap_tip_maps_through_the_capture_frame_and_drops_hostile_datagrams():
    now = [100.0]
    cap = np.array([0.1, -0.2, 0.3, 10.0, -20.0, 30.0])
    R = rotation_matrix(cap[:3])
    with MocapTip(cap, max_age=0.1, clock=lambda: now[0]) as sensor:
        assert sensor.address[0] == "127.0.0.1"
        bad = [
            b"x" * 20000,  # oversized
            b"\xff\xfe",  # not UTF-8
            b"[[[[[[[[1]]]]]]]]",  # nested too deeply
            b"{not json",
            b'{"marker": "tip", "position": [1, 2]}',
            b'{"marker": "tip", "position": [1, NaN, 2]}',
            b'{"marker": "tip", "position": [1, true, 2]}',
            b'{"marker": "tip", "x": 1e9, "y": 0, "z": 0}',
        ]
        for d in bad:
            assert not sensor.ingest(d, now[0])
        assert sensor.rejected == len(bad) and sensor.tip(0.0, np.zeros(7)) is None
        assert not sensor.ingest(b'{"marker": "base", "position": [0, 0, 0]}', now[0])  # another marker
        assert sensor.rejected == len(bad)
        m = np.array([5.0, 6.0, 7.0])
        msg = [{"marker": "base", "position": [0, 0, 0]}, {"marker": "tip", "x": 5.0, "y": 6.0, "z": 7.0}]
        # over the socket, as a capture bridge sends it (bounded wait: a local datagram arrives at once)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(json.dumps(msg).encode(), sensor.address)
            for _ in range(500):
                got = sensor.tip(0.0, np.zeros(7))
                if got is not None:
                    break
                time.sleep(0.01)
        np.testing.assert_allclose(got, R @ m + cap[3:], atol=1e-12)
        now[0] += 0.2  # older than max_age: stale
        assert sensor.tip(0.0, np.zeros(7)) is None


def test_replan_tip_options_refuse_in_one_line(capsys, tmp_path):
    base = ["replan", str(ROOT / "problems" / "paper_dynamic.toml"), "--out", str(tmp_path / "r")]
    assert "needs a tip measurement" in _one_error(capsys, [*base, "--tip-feedback"])
    assert "a live run only" in _one_error(capsys, [*base, "--mocap-port", "0"])
    assert "a simulation" in _one_error(capsys, [*base, "--true-robot", str(ROBOT), "--mocap-port", "0"])


def test_marker_formats_agree_and_the_log_prefers_telemetry(tmp_path, setup):
    _, act, _, sites = setup
    rows = [(0.5, "base", (1.0, 2.0, 3.0)), (0.5, "tip", (4.0, 5.0, 6.0)), (0.6, "tip1", (7.0, 8.0, 9.0))]
    csv_file = tmp_path / "m.csv"
    csv_file.write_text("# exported\ntime,name,x,y,z\n" + "".join(f"{t},{n},{x},{y},{z}\n" for t, n, (x, y, z) in rows))
    jl = tmp_path / "m.jsonl"
    jl.write_text("".join(json.dumps({"t": t, "marker": n, "position": list(p)}) + "\n" for t, n, p in rows))
    a, b = read_markers(csv_file, sites), read_markers(jl, sites)
    np.testing.assert_array_equal(a.t, [0.5, 0.6])
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(np.isnan(a.positions), np.isnan(b.positions))
    np.testing.assert_array_equal(np.nan_to_num(a.positions), np.nan_to_num(b.positions))
    assert np.isnan(a.positions[0, 1]).all() and a.positions[0, 2].tolist() == [4.0, 5.0, 6.0]
    log = tmp_path / "log.jsonl"
    lines = [{"type": "header", "names": list(act.names)}, {"type": "tx", "wall": 0.0, "kind": "ping", "seq": 0}]
    for k in range(3):
        lines.append({"type": "tx", "wall": 0.1 * k, "values": [1.0 * k] * act.n})
        lines.append({"type": "rx", "wall": 0.1 * k + 0.01, "positions": [2.0 * k] * act.n})
    log.write_text("".join(json.dumps(x) + "\n" for x in lines))
    measured, commanded = read_stream_log(log), read_stream_log(log, "commanded")
    assert measured.kind == "measured" and measured.values[:, 0].tolist() == [0.0, 2.0, 4.0]
    assert commanded.kind == "commanded" and commanded.values[:, 0].tolist() == [0.0, 1.0, 2.0]


def test_record_excite_streams_the_admitted_excitation_and_logs_it(tmp_path, setup, capsys):
    _, act, _, _ = setup
    log, frames = tmp_path / "ex.jsonl", tmp_path / "frames.bin"
    argv = ["record", "--excite", "--dry-run", str(frames), "--log", str(log), "--out", str(tmp_path / "d.json")]
    assert main(argv) == 0
    assert "join it with the capture" in capsys.readouterr().out
    assert frames.stat().st_size > 0
    series = read_stream_log(log)
    assert series.kind == "commanded" and series.t[-1] > 30.0
    assert np.all(act.position_violation(series.values) <= 1e-12)
    rest = act.command(load_robot(ROBOT).cables(load_robot(ROBOT).straight()))
    np.testing.assert_allclose(series.values[0], rest, atol=1e-9)  # starts and ends straight, at rest
    np.testing.assert_allclose(series.values[-1], rest, atol=1e-9)
    # the workspace: each segment bends over a third of its limit, in every direction, and the base sweeps
    robot = load_robot(ROBOT)
    ub = robot.bending(robot.config(act.actuation(series.values)))  # (T, 2, 2) effective bending vectors
    theta = np.linalg.norm(ub, axis=-1)
    assert np.all(theta.max(axis=0) > np.pi / 3)
    for k in range(2):
        big = theta[:, k] > 0.2
        octant = np.floor((np.arctan2(ub[big, k, 1], ub[big, k, 0]) + np.pi) / (np.pi / 4)).astype(int) % 8
        assert set(octant.tolist()) == set(range(8))
    assert np.ptp(series.values[:, -1]) > 100.0
