#!/usr/bin/env bash
# Calibrate PCC against the Cosserat rod and close the loop on the rod with the calibrated robot file.
#
# 1. film the built-in excitation motion on the simulated rod (gravity from the robot file; markers: base,
#    end of segment 1, tip; 0.3 mm capture noise) -> a calibration dataset;
# 2. fit PCC to it (crtraj calibrate: lengths, coupling, cable radius, zero offsets, capture frame);
# 3. run simulation 2 planning with the calibrated file, on the nominal rod (--true-robot: the servo values
#    the loop sends are read back through the nominal robot's actuators), without and with tip feedback.
# Usage: bash examples/rod_calibration.sh [OUT]   (default OUT = out/rod_calibration). Units: mm, s.
set -euo pipefail
out=${1:-out/rod_calibration}
mkdir -p "$out"
crtraj=(python -m crtraj.cli)
"${crtraj[@]}" record --excite --plant cosserat --capture-rate 5 --out "$out/rod_data.json"
"${crtraj[@]}" calibrate "$out/rod_data.json" --noise 0.3 --out "$out/cdsr2_rodcal.toml"
# the problem of simulation 2, planning with the calibrated robot file
sed 's|^robot = "robots/cdsr2.toml"|robot = "cdsr2_rodcal.toml"|' problems/paper_dynamic.toml > "$out/paper_dynamic_rodcal.toml"
"${crtraj[@]}" replan "$out/paper_dynamic_rodcal.toml" --plant cosserat --true-robot problems/robots/cdsr2.toml \
  --no-html --out "$out/replan" || true
"${crtraj[@]}" replan "$out/paper_dynamic_rodcal.toml" --plant cosserat --true-robot problems/robots/cdsr2.toml \
  --tip-feedback --no-html --out "$out/replan-tip-feedback" || true
