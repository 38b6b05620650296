"""Use cases of the lab commands: record a calibration dataset, calibrate a robot file, compare PCC with the rod,
verify with the rod (`crtraj record`, `calibrate`, `model compare`, `verify`).

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.app.lab._calibrate": ("calibrate_command",),
        "crtraj.app.lab._calibrate_file": (
            "Calibration",
            "calibrate_robot",
        ),
        "crtraj.app.lab._model_compare": (
            "compare_models",
            "model_compare_command",
            "sample_configs",
        ),
        "crtraj.app.lab._record": (
            "excitation_motion",
            "record_dataset",
            "record_command",
        ),
        "crtraj.app.lab._verify": (
            "Verification",
            "verify_cosserat",
            "verify_command",
        ),
    },
)
