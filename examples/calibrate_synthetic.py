"""Calibration, the whole loop, on synthetic motion capture: excite -> record -> calibrate -> plan.

1. `crtraj record --excite --dry-run`: the built-in excitation motion, admitted and streamed (to a frame
   file here; to a device with --udp/--serial), with its stream log;
2. a synthetic motion-capture system films a "true" robot perturbed from cdsr2 (lengths +-5 %, coupling
   -0.8 instead of -1, zero offsets +-0.05 rad, capture frame rotated 10 degrees and shifted 50 mm; 0.3 mm
   marker noise, 2 % outliers) at 30 Hz on its own clock (1000 s ahead of the log's);
3. `crtraj record --log --markers`: the dataset (actuator values interpolated at the capture times); with a
   clock offset 7 s off it refuses, naming the likely offset (the markers' motion lags the actuators');
4. `crtraj calibrate`: the calibrated robot file, report and residual plot, written only when the fit passes
   its sanity gate (held-out residual within 2 x the noise estimated from the data, few outliers, no
   parameter at its bound, converged);
5. `crtraj plan` with the nominal and with the calibrated robot file; the true robot runs each plan's
   set-points and its tip is compared with the planned tip.

Run: python examples/calibrate_synthetic.py   (writes out/calibrate_synthetic/)
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from crtraj.cli import main
from crtraj.hardware.actuators import Actuators
from crtraj.io.mocap import read_stream_log
from crtraj.io.problem import load_robot
from crtraj.io.results import read_result
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

robot = load_robot(ROBOT)
act = Actuators.from_robot(robot)
hw = Hardware(act.spool_radius, act.sign)
truth = synthetic_truth(robot, act.zero_offset, seed=7)
sites = paper_markers(robot.n_segments)

# 1. excitation, streamed to a frame file with its log
assert main(["record", "--excite", "--dry-run", str(OUT / "frames.bin"), "--log", str(OUT / "excite.jsonl"),
             "--out", str(OUT / "data.json")]) == 0  # fmt: skip

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

# 3. the dataset; a wrong clock offset is refused (exit 2, one line naming the likely offset)
record = ["record", "--log", str(OUT / "excite.jsonl"), "--markers", str(OUT / "markers.csv"), "--time-offset"]
assert main([*record, str(CLOCK + 7), "--out", str(OUT / "wrong.json")]) == 2
assert main([*record, str(CLOCK), "--out", str(OUT / "data.json")]) == 0

# 4. calibrate every parameter group
assert main(["calibrate", str(OUT / "data.json"), "--robot", str(ROBOT), "--out", str(OUT / "calibrated.toml")]) == 0

# 5. plan the paper's simulation 1 with each robot file; the true robot executes the plan's set-points
static = (ROOT / "problems" / "paper_static.toml").read_text()
true_layout = Layout.build(truth.robot, truth.zero_offsets, truth.capture, CalibrateOptions())
true_model = CalibrationModel(truth.robot, hw, sites, true_layout)
true_theta = true_layout.prior
for label, robot_file in (("nominal", ROBOT), ("calibrated", OUT / "calibrated.toml")):
    prob = OUT / f"static_{label}.toml"
    prob.write_text(static.replace('robot = "robots/cdsr2.toml"', f'robot = "{robot_file}"'))
    assert main(["plan", str(prob), "--out", str(OUT / f"plan_{label}.json")]) == 0
    res = read_result(OUT / f"plan_{label}.json")
    q, planned_tip = res.q, res.tip
    commanded = Actuators.from_robot(load_robot(robot_file)).command(q)  # what the servos are told
    true_tip = true_model.predict(true_theta, commanded)[:, -1]
    err = np.linalg.norm(true_tip - planned_tip, axis=1)
    print(f"{label:10s} plan: true tip vs planned tip: mean {err.mean():.3f} mm, max {err.max():.3f} mm")
