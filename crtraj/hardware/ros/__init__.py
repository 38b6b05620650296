"""The ROS 2 bridge (optional extra ``[ros]``): options, message checks, the node and the loop's device port.

Public names load on first use (`crtraj.core.lazy.lazy_exports`), so importing the package needs no ROS; the
modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.hardware.ros._controller": ("check_parameters", "detect_distro", "parameter_names"),
        "crtraj.hardware.ros._device": ("RosDevice", "VERIFY_SUBSTEPS"),
        "crtraj.hardware.ros._jtc": ("JtcParameters",),
        "crtraj.hardware.ros._node": ("RosNode", "domain_id"),
        "crtraj.hardware.ros._options": ("RosOptions",),
        "crtraj.hardware.ros._record": ("McapRecorder",),
    },
)
