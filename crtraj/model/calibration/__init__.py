"""Calibration of the robot's parameters from motion-capture markers: one CasADi least-squares NLP.

A sample is the actuator values v (rad for servos, mm for the z stage) and the capture-frame positions
m_j (mm) of markers j sitting on the backbone. The model maps v to the markers' robot-frame positions
through the parameters theta (all in one vector, `Layout`):

    d_i   = sign_i spool_i (v_i - a0_i)        cable i's length change (mm), a0_i its zero offset (rad)
    z     = sign_z (v_z - z0)                   base translation (mm), z0 the stage's zero offset
    u_k   = B1_k d_k / r                        commanded bending vector (paper eq. 2-3), r the cable radius
    u_bar = C(c) u                              coupling (paper eq. 8-11), c the coupling gain
    p_j   = PCC forward kinematics with segment lengths L_k, at the marker's backbone point

and the capture frame by p = R(w) m + t (w a rotation vector, rad; t in mm; capture -> robot frame). The
residual of one marker is e_j = R(w) m_j + t - p_j (mm, robot frame). The fit minimises the
pseudo-Huber loss ``sum_j 2 delta^2 (sqrt(1 + |e_j|^2 / delta^2) - 1)``, quadratic for |e| << delta and
linear beyond, so a swapped or lost marker pulls with a bounded force. IPOPT solves it with CasADi's
exact gradient and Hessian, within the parameter bounds.

Identifiability (`identifiable`): the columns of the robust-weighted Jacobian, each scaled to unit norm,
are taken in a fixed priority order (capture frame, lengths, cable radius, coupling, zero offsets, base
z); a parameter whose column lies (to `tol`) in the span of the ones before it cannot be told apart from
them by this data and is held at its prior. Two such directions always exist: a common zero offset of a
segment's three cables does not change its bending (the pseudo-inverse of eq. 2-3 removes it), and the
stage's zero offset moves every marker like the capture frame's translation along the robot's z axis.

Identifiability is judged again at the fitted parameters (`_identify.at_fit`): a Jacobian column can be zero
at the prior only (a segment commanded straight makes the coupling look inert, while at the truth its zero
offsets bend it and the coupling is confounded with the proximal zero offsets). Parameters confounded at the
fit are named with their partners and their standard errors withheld; the singular values of the scaled
Jacobian are reported at both points.

Every fit then passes a sanity gate (`judge`: time offset from `detect_time_offset`, held-out residual against
the noise, outliers, bounds, convergence), and a failed one is given its likely cause (`likely_cause`).

Standard errors come from the Gauss-Newton covariance at the solution, ``s^2 (J_w^T J_w)^-1`` with the
robust weights w_j = 1 / sqrt(1 + |e_j|^2 / delta^2) and ``s^2 = sum w_j |e_j|^2 / (m - p)``.

The model has no per-segment stiffness: eq. 8 uses one bending stiffness K_B for both segments (one
NiTi backbone), so no stiffness ratio is fitted. Units: mm, rad.
"""

from __future__ import annotations

from crtraj.model.calibration._diagnose import likely_cause
from crtraj.model.calibration._fit import fit, initial_capture
from crtraj.model.calibration._frames import align, rotation_matrix, rotation_vector
from crtraj.model.calibration._gate import GateInput, GateOptions, GateVerdict, estimate_noise, judge, usual_cause
from crtraj.model.calibration._identify import identifiable, scaled_singular_values, weighted_jacobian
from crtraj.model.calibration._layout import CalibrateOptions, Hardware, Layout
from crtraj.model.calibration._model import CalibrationModel
from crtraj.model.calibration._sites import (
    GROUPS,
    MAX_MARKERS,
    MAX_SAMPLES,
    MIN_SAMPLES,
    PLAUSIBLE_SCALE,
    PRIORITY,
    MarkerSite,
    check_sites,
    paper_markers,
    parse_groups,
)
from crtraj.model.calibration._stats import (
    OUTLIER_FACTOR,
    CalibrationResult,
    Held,
    MarkerStats,
    Observations,
    marker_stats,
    split,
)
from crtraj.model.calibration._synthetic import (
    SyntheticTruth,
    simulate_markers,
    synthetic_motion,
    synthetic_truth,
    synthetic_values,
)
from crtraj.model.calibration._timing import detect_time_offset

__all__ = [
    "GROUPS",
    "MAX_MARKERS",
    "MAX_SAMPLES",
    "MIN_SAMPLES",
    "OUTLIER_FACTOR",
    "PLAUSIBLE_SCALE",
    "PRIORITY",
    "CalibrateOptions",
    "CalibrationModel",
    "CalibrationResult",
    "GateInput",
    "GateOptions",
    "GateVerdict",
    "Hardware",
    "Held",
    "Layout",
    "MarkerSite",
    "MarkerStats",
    "Observations",
    "SyntheticTruth",
    "align",
    "check_sites",
    "detect_time_offset",
    "estimate_noise",
    "fit",
    "identifiable",
    "initial_capture",
    "judge",
    "likely_cause",
    "marker_stats",
    "paper_markers",
    "parse_groups",
    "rotation_matrix",
    "rotation_vector",
    "scaled_singular_values",
    "simulate_markers",
    "split",
    "synthetic_motion",
    "synthetic_truth",
    "synthetic_values",
    "usual_cause",
    "weighted_jacobian",
]
