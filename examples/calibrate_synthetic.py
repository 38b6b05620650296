"""Calibration, the whole loop, on synthetic motion capture: excite -> record -> calibrate -> plan.

1. `crtraj.excitation_motion`: the built-in excitation motion, admitted, and streamed by `crtraj.Streamer`
   (to a frame file here, as `crtraj record --excite --dry-run` does; to a device with a udp:// or serial://
   address), with its stream log;
2. a synthetic motion-capture system films a "true" robot perturbed from cdsr2 (lengths +-5 %, coupling
   -0.8 instead of -1, zero offsets +-0.05 rad, capture frame rotated 10 degrees and shifted 50 mm; 0.3 mm
   marker noise, 2 % outliers) at 30 Hz on its own clock (1000 s ahead of the log's);
3. `crtraj.record_dataset`: the dataset (actuator values interpolated at the capture times); with a clock
   offset 7 s off it refuses, naming the likely offset (the markers' motion lags the actuators');
4. `crtraj.calibrate_robot`: the calibrated robot file, written only when the fit passes its sanity gate
   (held-out residual within 2 x the noise estimated from the data, few outliers, no parameter at its
   bound, converged);
5. `crtraj.plan_problem` with the nominal and with the calibrated robot file; the true robot runs each
   plan's set-points and its tip is compared with the planned tip.

Run: python examples/calibrate_synthetic.py   (writes out/calibrate_synthetic/)
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

import crtraj
from crtraj.io import read_stream_log
from crtraj.model.calibration import (
    CalibrateOptions,
    CalibrationModel,
    Hardware,
    Layout,
    paper_markers,
    simulate_markers,
    synthetic_truth,
)

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "out" / "calibrate_synthetic"
OUT.mkdir(parents=True, exist_ok=True)
ROBOT = ROOT / "problems" / "robots" / "cdsr2.toml"
CLOCK = 1000.0  # s: the capture system's clock runs this far ahead of the log's

robot = crtraj.load_robot(ROBOT)
act = crtraj.Actuators.from_robot(robot)
hw = Hardware(act.spool_radius, act.sign)
truth = synthetic_truth(robot, act.zero_offset, seed=7)
sites = paper_markers(robot.n_segments)

# 1. excitation, admitted against an empty scene and streamed to a frame file with its log
motion = crtraj.excitation_motion(robot, act, crtraj.Scene())
frames = f"file://{OUT / 'frames.bin'}"
report = crtraj.Streamer.open(frames, motion.actuators, log=OUT / "excite.jsonl").run_path(motion)
print(f"excitation: {report.status}, {report.moves} set-points over {report.duration:.1f} s")
assert report.ok

# 2. the synthetic capture: 30 Hz, the true robot's markers at the log's (interpolated) actuator values
log = read_stream_log(OUT / "excite.jsonl")
t_cap = np.arange(log.t[0], log.t[-1], 1 / 30)
values = np.stack([np.interp(t_cap, log.t, log.values[:, i]) for i in range(log.values.shape[1])], axis=1)
m, _ = simulate_markers(
    truth.robot, hw, truth.zero_offsets, truth.capture, values, sites, noise=0.3, outliers=0.02, seed=1
)
with (OUT / "markers.csv").open("w", newline="") as fh:
    w = csv.writer(fh)
    w.writerow(["timestamp", "marker", "x", "y", "z"])
    for i, t in enumerate(t_cap):
        for j, s in enumerate(sites):
            w.writerow([f"{t + CLOCK:.6f}", s.name, *(f"{v:.4f}" for v in m[i, j])])

# 3. the dataset; a wrong clock offset is refused (one line naming the likely offset)
try:
    crtraj.record_dataset(OUT / "excite.jsonl", OUT / "markers.csv", robot, sites, time_offset=CLOCK + 7)
except crtraj.InputError as exc:
    print(f"refused: {exc}")
else:
    raise AssertionError("a clock offset 7 s off was not refused")
data, dropped = crtraj.record_dataset(OUT / "excite.jsonl", OUT / "markers.csv", robot, sites, time_offset=CLOCK)
data.write(OUT / "data.json")
print(f"dataset: {data.n} samples ({dropped} capture frames outside the log)")

# 4. calibrate every parameter group; the file is written only when the fit passes the gate
cal = crtraj.calibrate_robot(data, ROBOT, OUT / "calibrated.toml")
print("\n".join(cal.report()))
assert cal.ok, cal.verdict.line()

# 5. plan the paper's simulation 1 with each robot file; the true robot executes the plan's set-points
static = (ROOT / "problems" / "paper_static.toml").read_text()
true_layout = Layout.build(truth.robot, truth.zero_offsets, truth.capture, CalibrateOptions())
true_model = CalibrationModel(truth.robot, hw, sites, true_layout)
true_theta = true_layout.prior
for label, robot_file in (("nominal", ROBOT), ("calibrated", cal.path)):
    prob = OUT / f"static_{label}.toml"
    prob.write_text(static.replace('robot = "robots/cdsr2.toml"', f'robot = "{robot_file}"'))
    plan = crtraj.plan_problem(crtraj.Problem.load(prob))
    assert plan.result.is_success(), plan.result.message
    plan.write(OUT / f"plan_{label}.json")
    q, planned_tip = plan.result.cables, plan.result.tips
    commanded = crtraj.Actuators.from_robot(crtraj.load_robot(robot_file)).command(q)  # what the servos are told
    true_tip = true_model.predict(true_theta, commanded)[:, -1]
    err = np.linalg.norm(true_tip - planned_tip, axis=1)
    print(f"{label:10s} plan: true tip vs planned tip: mean {err.mean():.3f} mm, max {err.max():.3f} mm")
