"""`crtraj record --excite --plant cosserat`: a calibration dataset filmed on the simulated Cosserat rod.

The excitation motion (`crtraj.app.lab._record.excitation_motion`: timed within half the actuator limits and
admitted like any motion) is taken at the capture rate; the servos are taken to be at their set-points
(the motion is slow: quasi-static), the rod's shape at each frame is solved in cable-length mode
(`crtraj.model.cosserat.RodDrive`, the robot file's ``[robot.mechanics]``) and every marker site is read
off the backbone, plus Gaussian capture noise per axis (seeded). The capture frame is the robot frame.
The dataset is the one `crtraj calibrate` reads (`crtraj.io.calibration_data`), so PCC can be fitted to
the rod. Units: mm, rad, s.
"""

from __future__ import annotations

import logging

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import check_float
from crtraj.hardware.admission import AdmittedMotion
from crtraj.io.calibration_data import Dataset
from crtraj.model.calibration import MarkerSite
from crtraj.model.cosserat import RodDrive

log = logging.getLogger(__name__)

# Most frames a simulated capture solves (each is one rod solve of a few to tens of ms).
MAX_FRAMES = 20_000


def plant_dataset(
    motion: AdmittedMotion,
    drive: RodDrive,
    sites: tuple[MarkerSite, ...],
    *,
    rate: float = 10.0,
    noise: float = 0.3,
    seed: int = 0,
) -> Dataset:
    """The dataset of `motion` filmed on the rod of `drive` at `rate` Hz (noise: mm per axis).
    `InputError` for a bad rate or noise, or when a rod solve fails (no marker is guessed)."""
    rate = check_float(rate, "--capture-rate", gt=0.0, le=1000.0)
    noise = check_float(noise, "--capture-noise", ge=0.0, le=100.0)
    stamps, values = motion.path.sample(rate)
    if len(stamps) > MAX_FRAMES:
        raise InputError(f"--capture-rate: {len(stamps)} frames, at most {MAX_FRAMES}; lower the rate")
    act = motion.actuators
    q = act.actuation(values)
    rng = np.random.default_rng(seed)
    positions = np.empty((len(stamps), len(sites), 3))
    for i, qi in enumerate(q):
        s = drive.shape(qi)
        if not s.is_success():
            raise InputError(f"--plant: the rod's solve failed at t={stamps[i]:.2f} s ({s.status})")
        positions[i] = [drive.point_at(s.points, m.segment, m.arc) for m in sites]
    positions += rng.normal(0.0, noise, positions.shape)
    source = {
        "plant": "cosserat" if drive.gravity else "cosserat-weightless",
        "robot": drive.robot.name,
        "capture_rate_hz": rate,
        "noise_mm": noise,
        "seed": seed,
        "values": "commanded",
    }
    log.info("simulated capture: %d frames of %d markers on the rod", len(stamps), len(sites))
    return Dataset(act.names, sites, stamps - stamps[0], values, positions, source)
