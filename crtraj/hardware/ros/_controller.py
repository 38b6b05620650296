"""What the bridge needs from the robot's joint_trajectory_controller, checked from its parameters at start.

The bridge's messages are shaped so the controller executes exactly the verified curve
(`crtraj.hardware.ros._shaping`). Which parameters matter, and their names, differ per ros2_controllers
release (`detect_distro` tells them apart by the parameters the controller declares):

- ``interpolation_method: splines`` (the default; "none" jumps to each point),
- ``joints`` naming every joint the bridge commands (``ros.joints`` maps actuators to them),
- the point before a trajectory carrying velocities: the last command (Humble ``open_loop_control``, Jazzy
  ``interpolate_from_desired_state`` or ``open_loop_control``, Rolling ``interpolate_from_desired_state``) or a
  ``velocity`` state interface,
- no tolerance that snaps the command to the measured state: ``constraints.<joint>.trajectory`` 0,
  ``constraints.goal_time`` 0 or every ``constraints.<joint>.goal`` 0, ``cmd_timeout`` 0 (all the defaults),
- Jazzy and Rolling: ``speed_scaling.initial_scaling_factor`` 1 and no ``speed_scaling.state_interface`` (time
  runs at the scaling factor), and the update period, as the command is sampled one period ahead,
- Rolling: ``allow_trajectory_replacement: false``. Its default (true) blends each message into the running
  trajectory re-anchored at the previous cycle, so the old curve runs one period late until the new stamp, and a
  stamp not in the future starts at the arrival cycle, which the bridge cannot know: no stamping makes the
  executed curve the verified one.
- ``allow_nonzero_velocity_at_trajectory_end``: either value (every message ends at rest; Humble's default is
  true, later ones false).

`check_parameters` turns the values read through ``/<controller>/get_parameters`` into the model's
`JtcParameters` and the first unmet need (one line naming the parameter and the fix).
"""

from __future__ import annotations

from typing import Any

from crtraj.hardware.ros._jtc import DISTROS, JtcParameters

# read from every controller (None: the controller does not declare it)
COMMON = (
    "joints",
    "interpolation_method",
    "allow_nonzero_velocity_at_trajectory_end",
    "allow_partial_joints_goal",
    "state_interfaces",
    "cmd_timeout",
    "constraints.goal_time",
    "update_rate",
    "open_loop_control",
    "interpolate_from_desired_state",
    "allow_trajectory_replacement",
    "speed_scaling.initial_scaling_factor",
    "speed_scaling.state_interface",
)
# the parameter that marks each distro's JTC, newest first
MARKERS = (("allow_trajectory_replacement", "rolling"), ("interpolate_from_desired_state", "jazzy"),
           ("open_loop_control", "humble"))  # fmt: skip


def parameter_names(joints: tuple[str, ...]) -> list[str]:
    """Every parameter `check_parameters` reads for a controller of `joints`."""
    per_joint = [f"constraints.{j}.{k}" for j in joints for k in ("trajectory", "goal")]
    return [*COMMON, *per_joint]


def detect_distro(values: dict[str, Any]) -> str | None:
    """The ros2_controllers release whose JTC semantics the controller has, from the parameters it declares:
    ``allow_trajectory_replacement`` Rolling (master since 2026-08), ``interpolate_from_desired_state`` Jazzy (and
    Rolling before), ``open_loop_control`` alone Humble; None when none is declared."""
    for name, distro in MARKERS:
        if values.get(name) is not None:
            return distro
    return None


def _point_before(controller: str, distro: str, values: dict[str, Any]) -> str:
    """'' or why the point before a trajectory would lack velocities."""
    names = {"humble": ("open_loop_control",), "jazzy": ("interpolate_from_desired_state", "open_loop_control")}
    own = names.get(distro, ("interpolate_from_desired_state",))
    states = values.get("state_interfaces")
    if any(values.get(n) for n in own) or states is None or "velocity" in states:
        return ""
    return (
        f"{controller}.{own[0]}: false without a velocity state interface splines each new trajectory from a state "
        f"without velocity; set {own[0]}: true or add the velocity state interface"
    )


def _tolerances(controller: str, values: dict[str, Any], joints: tuple[str, ...]) -> str:
    """'' or the tolerance that would snap the command to the measured state."""
    where = f"{controller}."
    for j in joints:
        if (values.get(f"constraints.{j}.trajectory") or 0.0) > 0.0:
            return (
                f"{where}constraints.{j}.trajectory: {values[f'constraints.{j}.trajectory']:g}; a path tolerance "
                "violation makes the controller hold the measured position, off the verified curve; set it to 0.0"
            )
    goal_time = values.get("constraints.goal_time") or 0.0
    goals = [j for j in joints if (values.get(f"constraints.{j}.goal") or 0.0) > 0.0]
    if goal_time > 0.0 and goals:
        return (
            f"{where}constraints.goal_time: {goal_time:g} s with constraints.{goals[0]}.goal set; a goal missed in "
            "time makes the controller hold the measured position; set constraints.goal_time to 0.0"
        )
    if (values.get("cmd_timeout") or 0.0) > 0.0:
        return (
            f"{where}cmd_timeout: {values['cmd_timeout']:g} s; after it the controller holds the measured position "
            "(every message of the bridge ends at rest on its verified tail anyway); set cmd_timeout: 0.0"
        )
    return ""


def _timing(controller: str, distro: str, values: dict[str, Any], update_rate: float) -> tuple[float, str]:
    """(lookahead s, '' or why the controller's time would not run as verified)."""
    if distro == "humble":
        return 0.0, ""
    where = f"{controller}."
    if values.get("allow_trajectory_replacement"):
        return 0.0, (
            f"{where}allow_trajectory_replacement: true blends each message into the running trajectory, "
            "re-anchored at the cycle it arrives in, which the bridge cannot know (the executed curve would lag the "
            "verified one); set allow_trajectory_replacement: false"
        )
    factor = values.get("speed_scaling.initial_scaling_factor")
    if factor is not None and factor != 1.0:
        return 0.0, (
            f"{where}speed_scaling.initial_scaling_factor: {factor:g}; the trajectory would run at that speed, not "
            "as verified; set it to 1.0"
        )
    if values.get("speed_scaling.state_interface"):
        return 0.0, (
            f"{where}speed_scaling.state_interface: {values['speed_scaling.state_interface']!r}; the hardware would "
            "scale the trajectory's time; set it to '' (no scaling)"
        )
    own = values.get("update_rate") or 0
    rate = float(own) if own > 0 else float(update_rate)
    if rate <= 0.0:
        return 0.0, (
            f"ros.update_rate: {controller} does not say its update_rate, and {distro} samples the trajectory one "
            "update period ahead; set ros.update_rate to the controller manager's update_rate (Hz)"
        )
    if own > 0 and update_rate > 0 and abs(float(own) - update_rate) > 1e-9 * update_rate:
        return 0.0, (
            f"ros.update_rate: {update_rate:g} Hz, but {controller} runs at update_rate {own} Hz; set ros.update_rate "
            f"= {own} or leave it 0 (read from the controller)"
        )
    return 1.0 / rate, ""


def check_parameters(
    controller: str,
    values: dict[str, Any],
    joints: tuple[str, ...],
    *,
    distro: str = "auto",
    update_rate: float = 0.0,
) -> tuple[JtcParameters, str]:
    """(the controller model's parameters, '' or why the controller cannot execute the bridge's messages as
    verified) from the parameter `values` read from `controller` (None: not declared; the default applies).
    distro: ``ros.distro`` ("auto": `detect_distro`, Humble when nothing tells); update_rate: ``ros.update_rate``
    (Hz, 0: the controller's own ``update_rate`` parameter)."""
    found = detect_distro(values)
    used = found or (distro if distro != "auto" else "humble")
    bad = distro not in ("auto", *DISTROS)
    if bad or (distro != "auto" and found is not None and found != distro):
        why = f"ros.distro: {distro!r}, but {controller} has the parameters of {found or 'no known release'}; "
        return JtcParameters(), why + 'set ros.distro = "auto" or the release the robot runs'
    lookahead, why = _timing(controller, used, values, update_rate)
    end_velocity = values.get("allow_nonzero_velocity_at_trajectory_end")
    params = JtcParameters(
        allow_nonzero_velocity_at_trajectory_end=used == "humble" if end_velocity is None else bool(end_velocity),
        allow_partial_joints_goal=bool(values.get("allow_partial_joints_goal") or False),
        interpolation_method=str(values.get("interpolation_method") or "splines"),
        distro=used,
        lookahead=lookahead,
    )
    if params.interpolation_method != "splines":
        return params, (
            f"{controller}.interpolation_method: {params.interpolation_method!r}; the bridge needs 'splines' "
            "(the default)"
        )
    have = values.get("joints")
    if have is not None:
        missing = [j for j in joints if j not in have]
        if missing:
            return params, (
                f"{controller}.joints: no {', '.join(missing)} among the controller's joints ({', '.join(have)}); "
                "map crtraj's actuators to them with [ros.joints]"
            )
    return params, why or _point_before(controller, used, values) or _tolerances(controller, values, joints)
