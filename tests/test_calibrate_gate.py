"""The calibration's sanity gate and hostile input (issue 27): a fit that cannot explain its data never reports
success, names the failed check and the likely cause, and replaces no file; outputs are never inputs; every
hostile number, CSV or file name gives one line, no traceback.

Synthetic truth: cdsr2 with segment lengths +-5 %, coupling -0.8, zero offsets +-0.05 rad, the capture frame
rotated and shifted (`synthetic_truth`); a smooth 40 s motion logged at 20 Hz, filmed at 10 Hz on a clock
100 s ahead, markers with 0.5 mm noise per axis and 1 % outliers.
"""

from __future__ import annotations

import json
import math
import re
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from crtraj.app.lab._calibrate import calibrate, gate
from crtraj.app.lab._calibration_report import calibrated_text, report_lines
from crtraj.cli import main
from crtraj.hardware.actuators import Actuators
from crtraj.io.calibration_data import Dataset, read_calibration
from crtraj.io.problem import load_robot
from crtraj.model.calibration import (
    GROUPS,
    CalibrateOptions,
    CalibrationModel,
    GateOptions,
    Hardware,
    Layout,
    Observations,
    detect_time_offset,
    estimate_noise,
    fit,
    paper_markers,
    simulate_markers,
    split,
    synthetic_motion,
    synthetic_truth,
    synthetic_values,
    weighted_jacobian,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "problems" / "robots" / "cdsr2.toml"
NOISE = 0.5  # mm per axis
CLOCK = 100.0  # s: the capture's clock ahead of the log's


@pytest.fixture(scope="module")
def setup():
    robot = load_robot(ROBOT)
    act = Actuators.from_robot(robot)
    hw = Hardware(act.spool_radius, act.sign)
    truth = synthetic_truth(robot, act.zero_offset, seed=3)
    return robot, act, hw, paper_markers(robot.n_segments), truth


def _markers(setup, values, *, hw=None, seed=2, outliers=0.01):
    _robot, _act, hw0, sites, truth = setup
    m, _ = simulate_markers(
        truth.robot, hw or hw0, truth.zero_offsets, truth.capture, values, sites, noise=NOISE, outliers=outliers,
        seed=seed,
    )  # fmt: skip
    return m


def _write_log(path: Path, names, t, values) -> Path:
    lines = [json.dumps({"type": "header", "names": list(names)})]
    lines += [
        json.dumps({"type": "tx", "wall": float(a), "values": v.tolist()}) for a, v in zip(t, values, strict=True)
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def _write_csv(path: Path, t, m, names, scale: float = 1.0) -> Path:
    rows = ["timestamp,marker,x,y,z"]
    for i, ti in enumerate(t):
        for j, name in enumerate(names):
            rows.append(f"{ti:.6f},{name}," + ",".join(f"{v * scale:.6f}" for v in m[i, j]))
    path.write_text("\n".join(rows) + "\n")
    return path


@pytest.fixture(scope="module")
def files(setup, tmp_path_factory):
    """A log, a matching marker file and the dataset `crtraj record` makes of them."""
    robot, act, hw, sites, _ = setup
    d = tmp_path_factory.mktemp("gate")
    t_log = np.arange(0.0, 40.0, 0.05)
    log = _write_log(d / "log.jsonl", act.names, t_log, synthetic_motion(robot, hw, t_log, seed=1))
    t_cap = np.arange(0.5, 39.5, 0.1)
    m = _markers(setup, synthetic_motion(robot, hw, t_cap, seed=1))
    mk = _write_csv(d / "markers.csv", t_cap + CLOCK, m, [s.name for s in sites])
    data = d / "data.json"
    assert (
        main(["record", "--log", str(log), "--markers", str(mk), "--time-offset", str(CLOCK), "--out", str(data)]) == 0
    )
    return d, log, mk, data, t_cap


def _snapshot(*dirs: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for d in dirs for p in d.rglob("*") if p.is_file()}


def _refused(capsys, argv, *dirs: Path, codes=(1, 2)) -> str:
    """Run argv; it must exit with one of `codes`, one stderr line and no traceback, and change no file in
    dirs (nor the robot file)."""
    before = _snapshot(*dirs)
    robot_before = ROBOT.read_bytes()
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code in codes and len(err) == 1, (code, err)
    assert "Traceback" not in err[0]
    after = _snapshot(*dirs)
    for p, b in before.items():
        assert after.get(p) == b, f"{p} changed"
    assert ROBOT.read_bytes() == robot_before
    return err[0]


def _dataset_file(setup, path: Path, t, values, m) -> Path:
    _, act, _, sites, _ = setup
    Dataset(act.names, sites, t, values, m).write(path)
    return path


def test_correct_data_passes_with_honest_figures(files, tmp_path, capsys):
    _d, _log, _mk, data, _ = files
    out = tmp_path / "cal.toml"
    assert main(["calibrate", str(data), "--robot", str(ROBOT), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "gate: residual: ok" in text and "gate: time_offset: ok" in text
    rec = read_calibration(out)
    assert rec.noise_mm == pytest.approx(NOISE, rel=0.15)  # the estimate from the data against the true noise
    assert rec.heldout_rms_inliers_mm <= 1.5 * math.sqrt(3) * NOISE
    assert rec.heldout_outliers > 0 and rec.heldout_rms_mm > rec.heldout_rms_inliers_mm  # 1 % outliers
    assert rec.confounded == ()  # nothing confounded at the fit beyond what the prior showed
    report = json.loads((tmp_path / "cal.report.json").read_text())
    assert report["success"] and report["gate"]["passed"]
    assert report["gate"]["heldout_rms_inliers_mm"] == pytest.approx(rec.heldout_rms_inliers_mm)
    assert abs(report["gate"]["time_offset_s"]) < 0.1
    held = report["residuals_after"]["heldout"].values()
    assert rec.heldout_outliers == sum(v["outliers"] for v in held)  # the held-out samples' count, not all
    n = sum(v["count"] for v in held)
    assert rec.heldout_rms_mm == pytest.approx(math.sqrt(sum(v["rms_mm"] ** 2 * v["count"] for v in held) / n))


def test_a_stated_noise_below_the_residuals_fails_and_a_bad_one_is_refused(files, tmp_path, capsys):
    """--noise replaces the estimate: 0.05 mm per axis is ten times below the data's, so the residual check
    fails and names it; a non-finite or negative --noise is refused in one line."""
    d, _log, _mk, data, _ = files
    cal = ["calibrate", str(data), "--robot", str(ROBOT), "--out", str(tmp_path / "c.toml")]
    line = _refused(capsys, [*cal, "--noise", "0.05"], d, tmp_path, codes=(1,))
    assert "residual check failed" in line and "from --noise" in line and "give --noise MM" in line
    for bad in ("nan", "-1", "1e400"):
        assert "--noise" in _refused(capsys, [*cal, "--noise", bad], d, tmp_path, codes=(2,))
    assert "--allow-at-bound" in _refused(capsys, [*cal, "--allow-at-bound", "elbow"], d, tmp_path, codes=(2,))


def test_gate_checks_outliers_bounds_and_convergence(files, setup, tmp_path):
    """Each check on its own: too many outliers; a parameter at its bound (passes when declared); IPOPT's
    "acceptable level" counts only while the residuals qualify, any other stop fails."""
    robot, act, hw, sites, _ = setup
    t_cap = files[4]
    values = synthetic_motion(robot, hw, t_cap, seed=1)
    data = Dataset(act.names, sites, t_cap, values, _markers(setup, values, outliers=0.25))
    res = calibrate(data, robot, GROUPS)
    verdict = gate(data, robot, res)
    assert verdict.failed().name == "outliers" and "misidentified" in verdict.cause
    assert verdict.outlier_fraction > 0.2
    good = Dataset(act.names, sites, t_cap, values, _markers(setup, values))
    res = calibrate(good, robot, GROUPS)
    assert gate(good, robot, res).ok
    pinned = replace(res, at_bound=("coupling",))
    assert gate(good, robot, pinned).failed().name == "bounds"
    assert gate(good, robot, pinned, GateOptions(allow_at_bound=("coupling",))).ok
    assert gate(good, robot, replace(res, status="Solved_To_Acceptable_Level")).ok
    assert gate(good, robot, replace(res, status="Maximum_Iterations_Exceeded")).failed().name == "solver"
    strict = gate(good, robot, replace(res, status="Solved_To_Acceptable_Level"), GateOptions(noise=0.05))
    assert not next(c for c in strict.checks if c.name == "solver").ok  # not acceptable: residuals above noise


def test_a_failed_fit_replaces_no_good_file(files, setup, tmp_path, capsys):
    """A 7 s time offset: the gate fails on the time check, names the offset, keeps the report as
    *.failed.json and leaves the earlier calibrated file, report and plot byte-identical."""
    robot, _act, hw, _sites, _ = setup
    _d, _log, _mk, data, t_cap = files
    out = tmp_path / "cal.toml"
    assert main(["calibrate", str(data), "--robot", str(ROBOT), "--out", str(out)]) == 0
    capsys.readouterr()
    values = synthetic_motion(robot, hw, t_cap, seed=1)
    shifted = _markers(setup, synthetic_motion(robot, hw, t_cap + 7.0, seed=1))  # the markers 7 s early
    bad = _dataset_file(setup, tmp_path / "offset.json", t_cap, values, shifted)
    line = _refused(
        capsys, ["calibrate", str(bad), "--robot", str(ROBOT), "--out", str(out)], files[0], tmp_path, codes=(1,)
    )
    assert "time_offset check failed" in line and "time offset" in line.split("likely cause")[1]
    assert re.search(r"markers move -(6\.9|7|7\.1) s after the actuators", line)
    failed = json.loads((tmp_path / "cal.report.failed.json").read_text())
    assert failed["success"] is False and failed["gate"]["time_offset_s"] == pytest.approx(-7.0, abs=0.11)
    assert (tmp_path / "cal.residuals.failed.png").read_bytes()[:4] == b"\x89PNG"


def test_record_refuses_a_gross_time_offset_and_names_the_likely_one(files, tmp_path, capsys):
    d, log, mk, _data, _ = files
    argv = ["record", "--log", str(log), "--markers", str(mk), "--time-offset", str(CLOCK + 7), "--out"]
    line = _refused(capsys, [*argv, str(tmp_path / "x.json")], d, tmp_path, codes=(2,))
    assert line.startswith("crtraj: error: --time-offset:") and "likely 100 s" in line
    assert not (tmp_path / "x.json").exists()


def test_swapped_marker_names_fail_the_gate_named(files, setup, tmp_path, capsys):
    robot, _act, hw, sites, _ = setup
    _, log, _mk, _data, t_cap = files
    m = _markers(setup, synthetic_motion(robot, hw, t_cap, seed=1))
    names = [s.name for s in sites]
    names[1], names[2] = names[2], names[1]  # the capture labels tip1 and tip the other way round
    mk = _write_csv(tmp_path / "swapped.csv", t_cap + CLOCK, m, names)
    argv = ["calibrate", "--log", str(log), "--markers", str(mk), "--time-offset", str(CLOCK), "--robot", str(ROBOT)]
    line = _refused(capsys, [*argv, "--out", str(tmp_path / "c.toml")], files[0], tmp_path, codes=(1,))
    assert "residual check failed" in line and "marker names: tip1 and tip look swapped" in line
    assert not (tmp_path / "c.toml").exists()


def test_a_reversed_servo_fails_the_gate_named(files, setup, tmp_path, capsys):
    robot, _act, hw, _, _ = setup
    t_cap = files[4]
    values = synthetic_motion(robot, hw, t_cap, seed=1)
    sign = hw.sign.copy()
    sign[4] = -sign[4]  # s2c2 turns the other way than the robot file says
    m = _markers(setup, values, hw=Hardware(hw.spool_radius, sign))
    bad = _dataset_file(setup, tmp_path / "flip.json", t_cap, values, m)
    line = _refused(
        capsys, ["calibrate", str(bad), "--robot", str(ROBOT), "--out", str(tmp_path / "c.toml")], files[0], tmp_path
    )
    assert "check failed" in line and "sign: actuator s2c2 looks reversed" in line


def test_markers_in_metres_are_refused_by_record_and_calibrate(files, setup, tmp_path, capsys):
    robot, _, hw, sites, _ = setup
    _d, log, _mk, _data, t_cap = files
    values = synthetic_motion(robot, hw, t_cap, seed=1)
    m = _markers(setup, values)
    mk = _write_csv(tmp_path / "metres.csv", t_cap + CLOCK, m, [s.name for s in sites], scale=1e-3)
    rec = ["record", "--log", str(log), "--markers", str(mk), "--time-offset", str(CLOCK), "--out"]
    assert "not in mm" in _refused(capsys, [*rec, str(tmp_path / "x.json")], files[0], tmp_path, codes=(2,))
    bad = _dataset_file(setup, tmp_path / "metres.json", t_cap, values, m * 1e-3)
    cal = ["calibrate", str(bad), "--robot", str(ROBOT), "--out", str(tmp_path / "c.toml")]
    assert "not in mm" in _refused(capsys, cal, files[0], tmp_path, codes=(2,))


def test_an_output_that_is_an_input_is_refused_before_any_work(files, tmp_path, capsys):
    """Every pre-existing file (the dataset, the log, the robot copy) stays byte-identical."""
    d, log, mk, data, _ = files
    robot = tmp_path / "robot.toml"
    robot.write_bytes(ROBOT.read_bytes())
    base = ["calibrate", str(data), "--robot", str(robot), "--out", str(tmp_path / "c.toml")]
    for flag, target in (("--report", robot), ("--plot", data), ("--report", data)):
        line = _refused(capsys, [*base, flag, str(target)], d, tmp_path, codes=(2,))
        assert flag in line and "is also" in line
    assert "--out" in _refused(
        capsys, ["calibrate", str(data), "--robot", str(robot), "--out", str(robot)], d, tmp_path, codes=(2,)
    )
    rec = ["record", "--log", str(log), "--markers", str(mk), "--time-offset", str(CLOCK), "--out", str(log)]
    assert "--out" in _refused(capsys, rec, d, tmp_path, codes=(2,))


def test_hostile_numbers_and_csv_give_one_line(files, tmp_path, capsys):
    d, log, mk, data, _ = files
    rec = ["record", "--log", str(log), "--time-offset", str(CLOCK), "--out", str(tmp_path / "x.json")]
    lines = mk.read_text().splitlines()
    cases = {
        "huge_int.csv": [*lines, f"139.45,tip,{'9' * 400},0,0"],
        "quote.csv": [*lines[:3], '139.5,"tip,1,2,' + "3" * 200_000, *lines[3:]],
        "e300.csv": [*lines[:5], lines[5].rsplit(",", 1)[0] + ",1e300", *lines[6:]],
        "dup.csv": [*lines[:4], lines[3], *lines[4:]],
    }
    expect = {
        "huge_int.csv": "expected a number",
        "quote.csv": "stray quote",
        "e300.csv": "must be within",
        "dup.csv": "again at timestamp",
    }
    for name, body in cases.items():
        f = tmp_path / name
        f.write_text("\n".join(body) + "\n")
        assert expect[name] in _refused(capsys, [*rec, "--markers", str(f)], d, tmp_path, codes=(2,)), name
    jl = tmp_path / "huge.jsonl"
    jl.write_text('{"t": 1, "marker": "tip", "x": ' + "9" * 400 + ', "y": 0, "z": 0}\n')
    assert "an integer of 400 digits" in _refused(capsys, [*rec, "--markers", str(jl)], d, tmp_path, codes=(2,))
    log_lines = log.read_text().splitlines()
    for value, msg in (("1e300", "must be within"), ("9" * 400, "400 digits")):
        bad_log = tmp_path / "bad_log.jsonl"
        row = json.loads(log_lines[5])
        text = json.dumps(row).replace(json.dumps(row["values"][2]), value, 1)
        bad_log.write_text("\n".join([*log_lines[:5], text, *log_lines[6:]]) + "\n")
        argv = ["record", "--log", str(bad_log), "--markers", str(mk), "--time-offset", str(CLOCK)]
        line = _refused(capsys, [*argv, "--out", str(tmp_path / "x.json")], d, tmp_path, codes=(2,))
        assert "line 6: values[" in line and msg in line, line
    doc = json.loads(data.read_text())
    cal = ["calibrate", "--robot", str(ROBOT), "--out", str(tmp_path / "c.toml")]
    for field, value, msg in (("values", 1e300, "must be within"), ("values", 10**400, "digits"), ("t", 10**400, "")):
        bad = json.loads(json.dumps(doc))
        bad[field][3] = [value] * len(bad[field][3]) if field == "values" else value
        f = tmp_path / "bad.json"
        f.write_text(json.dumps(bad))
        line = _refused(capsys, [*cal, str(f)], files[0], tmp_path, codes=(2,))
        assert f"{field}[3]" in line and msg in line, line


def test_hostile_file_names_give_valid_toml(files, tmp_path, capsys):
    """A dataset whose name is not UTF-8 or holds control characters: the calibrated file is valid TOML and
    names it with escapes."""
    _, _, _, data, _ = files
    for raw, shown in ((b"data\xff.json", "data\\xff.json"), (b"d\x1b\x7f.json", "d\\u001b\\u007f.json")):
        name = tmp_path / raw.decode("utf-8", "surrogateescape")
        name.write_bytes(data.read_bytes())
        out = tmp_path / "cal.toml"
        assert main(["calibrate", str(name), "--robot", str(ROBOT), "--out", str(out)]) == 0
        doc = tomllib.loads(out.read_text())
        assert doc["calibration"]["dataset"].endswith(shown)
    capsys.readouterr()


def test_a_straight_segment_reports_the_parameters_confounded_at_the_fit(setup):
    """The distal segment is commanded straight; its true zero offsets bend it. At the prior the coupling has no
    effect; at the fit it is confounded with the proximal zero offsets (checked here independently: its Jacobian
    column lies in their span), and the report says so instead of "no effect"."""
    robot, act, hw, sites, _ = setup
    truth = synthetic_truth(robot, act.zero_offset, seed=4)
    values = synthetic_values(robot, hw, 150, seed=2, planar_distal=True)
    m, _ = simulate_markers(truth.robot, hw, truth.zero_offsets, truth.capture, values, sites, noise=NOISE, seed=1)
    obs = Observations(values, m, sites, split(150, 0.2, 0))
    res = fit(robot, hw, act.zero_offset, obs, GROUPS)
    ident = res.identifiability
    names = res.layout.names
    assert "coupling" in [h.name for h in res.held]  # no effect at the prior
    partners = set(ident.effect_at_fit("coupling"))
    assert partners and partners <= {f"s1c{i}.zero_offset" for i in (1, 2, 3)}
    for p in partners:
        assert math.isnan(res.std_error[names.index(p)])  # withheld, not a confident figure
    text = "\n".join(report_lines(res))
    assert "coupling is not identifiable" in text and "no effect at the prior values, but at the fit" in text
    data = Dataset(act.names, sites, np.arange(150.0), values, m)
    toml = calibrated_text(ROBOT.read_text(), res, gate(data, robot, res), "straight.json", "today")
    assert partners <= set(tomllib.loads(toml)["calibration"]["confounded"])  # the calibrated file says so too
    cm = CalibrationModel(robot, hw, sites, res.layout)
    fr = ~obs.heldout
    e = cm.residuals(res.theta, values[fr], m[fr])
    J, _, _ = weighted_jacobian(cm.jacobians(res.theta, values[fr], m[fr]), e, 1.0)
    c = J[:, names.index("coupling")]
    A = J[:, [names.index(p) for p in sorted(partners)]]
    rest = c - A @ np.linalg.lstsq(A, c, rcond=None)[0]
    assert np.linalg.norm(c) > 1.0 and np.linalg.norm(rest) < 1e-6 * np.linalg.norm(c)
    J0 = cm.jacobians(res.prior, values[fr], m[fr])[..., names.index("coupling")]
    assert np.all(J0 == 0.0)  # and at the prior the column is exactly zero


def test_noise_estimate_against_a_known_noise():
    """Third differences recover a known noise under a smooth error of 30 mm."""
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 60.0, 0.05)
    smooth = np.stack([np.sin(0.3 * t), np.cos(0.2 * t), 0.1 * t], axis=1)[:, None, :] * 30.0
    e = smooth + rng.normal(0.0, 0.4, (t.size, 1, 3))
    assert estimate_noise(t, e) == pytest.approx(0.4, rel=0.1)
    assert estimate_noise(t[:3], e[:3]) is None


def test_time_offset_estimate_against_a_known_lag(setup):
    """Markers filmed 2 s late (and 2 s early) are found within one step; in time, no lag."""
    robot, act, hw, sites, _ = setup
    layout = Layout.build(robot, act.zero_offset, np.zeros(6), CalibrateOptions())
    cm = CalibrationModel(robot, hw, sites, layout)
    t = np.arange(0.0, 40.0, 0.1)
    values = synthetic_motion(robot, hw, t, seed=1)
    for lag in (2.0, -2.0, 0.0):
        m = _markers(setup, synthetic_motion(robot, hw, t - lag, seed=1))
        off = detect_time_offset(cm, layout.prior, t, values, m)
        assert off.lag == pytest.approx(lag, abs=0.11)
        assert off.is_gross(0.25) == (lag != 0.0)
