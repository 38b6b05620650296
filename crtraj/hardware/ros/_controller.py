"""What the bridge needs from the robot's joint_trajectory_controller, checked from its parameters at start.

The bridge's messages are shaped so the controller executes exactly the verified curve
(`crtraj.hardware.ros._shaping`) with the controller's defaults. That needs:

- ``interpolation_method: splines`` (the default; "none" jumps to each point),
- ``joints`` naming every joint the bridge commands (``ros.joints`` maps actuators to them),
- the point before each trajectory carrying velocities: ``open_loop_control: true`` (the last
  command, exactly the committed curve) or a ``velocity`` state interface (the measured state; it
  then differs from the committed curve by the tracking error),
- nothing about ``allow_nonzero_velocity_at_trajectory_end``: every message ends at rest, so the
  default (false) is fine; its value is read into the controller model anyway.

`check_parameters` turns the values read through ``/<controller>/get_parameters`` into the
model's `JtcParameters` and the first unmet need (one line naming the parameter).
"""

from __future__ import annotations

from typing import Any

from crtraj.hardware.ros._jtc import JtcParameters

PARAMETERS = (
    "joints",
    "interpolation_method",
    "allow_nonzero_velocity_at_trajectory_end",
    "allow_partial_joints_goal",
    "open_loop_control",
    "state_interfaces",
)


def check_parameters(controller: str, values: dict[str, Any], joints: tuple[str, ...]) -> tuple[JtcParameters, str]:
    """(the controller model's parameters, '' or why the controller cannot execute the bridge's messages as
    verified) from the parameter `values` read from `controller` (None: not set, the default applies)."""
    params = JtcParameters(
        allow_nonzero_velocity_at_trajectory_end=bool(values.get("allow_nonzero_velocity_at_trajectory_end") or False),
        allow_partial_joints_goal=bool(values.get("allow_partial_joints_goal") or False),
        interpolation_method=str(values.get("interpolation_method") or "splines"),
    )
    where = f"{controller}."
    if params.interpolation_method != "splines":
        return params, (
            f"{where}interpolation_method: {params.interpolation_method!r}; the bridge needs 'splines' (the default)"
        )
    have = values.get("joints")
    if have is not None:
        missing = [j for j in joints if j not in have]
        if missing:
            return params, (
                f"{where}joints: no {', '.join(missing)} among the controller's joints ({', '.join(have)}); "
                "map crtraj's actuators to them with [ros.joints]"
            )
    states = values.get("state_interfaces")
    if not values.get("open_loop_control") and states is not None and "velocity" not in states:
        return params, (
            f"{where}open_loop_control: false without a velocity state interface splines each new trajectory from "
            "a state without velocity; set open_loop_control: true or add the velocity state interface"
        )
    return params, ""
