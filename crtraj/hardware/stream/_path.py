"""Checks of a whole admitted motion before the streamer sends any of it: admission, approach, start position.

`check_admitted` refuses anything `crtraj.hardware.admission.admit` did not make for this streamer;
`approach_frames` prepends the verified approach from the device's position; `refusal_text` words a limits
refusal of the path's start. Times in s, values in actuator units (rad for servos, mm for the z stage).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from crtraj.core.errors import AdmissionError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion
from crtraj.hardware.limits import Violation
from crtraj.hardware.setpoints import SetpointPath

# (admitted motion, the device's actuator values) -> the motion's path with an approach ending at its first time;
# raises AdmissionError when no safe approach exists. The app layer injects a planner (crtraj.app.devices._approach).
ApproachPlanner = Callable[[AdmittedMotion, np.ndarray], SetpointPath]


def check_admitted(motion: object, actuators: Actuators, rate: float) -> None:
    """`AdmissionError` unless `motion` was admitted for `actuators` at `rate` (Hz)."""
    if not isinstance(motion, AdmittedMotion):
        raise AdmissionError(
            f"run_path: streams only a motion admitted by crtraj.hardware.admission.admit, got {type(motion).__name__}"
        )
    if not motion.admitted_for(actuators):
        raise AdmissionError("run_path: the motion was admitted for other actuators than this streamer's")
    if motion.rate != rate:
        raise AdmissionError(
            f"run_path: the motion was verified at {motion.rate:g} Hz, this streamer sends at "
            f"{rate:g} Hz; admit it with rate={rate:g}"
        )


def approach_frames(
    motion: AdmittedMotion,
    here: np.ndarray,
    actuators: Actuators,
    rate: float,
    plan_approach: ApproachPlanner | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The approach's frames from `here` (the device's values), verified, followed by the motion's verified
    frames: (stamps (M,) s, values (M, n)). `AdmissionError` if the approach is unsafe."""
    path = plan_approach(motion, here) if plan_approach is not None else motion.path.with_approach(here, actuators)
    stamps, values = path.sample(rate)
    na = path.approach_frames(rate)
    # the motion's own frames are the verified ones, on the same grid: sampling with an approach must give
    # them back bit for bit, or what is sent would not be what was verified
    if len(stamps) - na != len(motion.stamps) or not (
        np.array_equal(stamps[na:], motion.stamps) and np.array_equal(values[na:], motion.values)
    ):
        raise AdmissionError("approach: the approach changed the motion's verified set-points")
    if motion.verifier is None:
        raise AdmissionError("approach: the motion carries no verifier")
    # the approach and its join into the motion: body and limits from the device's position at rest
    why = motion.verifier.failure(stamps[: na + 1], values[: na + 1], start=here)
    if why is not None:
        raise AdmissionError(f"approach: {why}")
    return np.concatenate([stamps[:na], motion.stamps]), np.concatenate([values[:na], motion.values])


def refusal_text(v: Violation, values: np.ndarray, here: np.ndarray, actuators: Actuators, dt: float) -> str:
    """The one-line refusal of a path (values (M, n)) the limits gate refused from `here`; dt: period (s)."""
    msg = f"refused before sending: {v.message()}"
    d = np.abs(values[0] - here)
    if v.quantity in ("velocity", "acceleration") and np.any(d > actuators.amax * dt**2 * (1 + 1e-9)):
        i = int(np.argmax(d / actuators.amax))
        msg += (
            f"; the path starts {d[i]:.4g} {actuators.units[i]} ({actuators.names[i]}) away from "
            "the device's position: move there first (--approach)"
        )
    return msg
