"""Dynamixel servos (Protocol 2.0, X-series): the protocol, the link, its connect-time checks (bus watchdog, drive
mode), homing and its state, the servo bus layout, and the simulated servo chain behind a pseudo-terminal.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.hardware.dynamixel._homing": ("Homer",),
        "crtraj.hardware.dynamixel._homing_check": (
            "ReadOnlyLink",
            "proven",
        ),
        "crtraj.hardware.dynamixel._homing_spec": (
            "read_homing",
            "read_stop",
        ),
        "crtraj.hardware.dynamixel._homing_state": (
            "HomingState",
            "homing_command",
            "state_path",
            "windows",
        ),
        "crtraj.hardware.dynamixel._link": (
            "DEFAULT_BAUD",
            "open_dynamixel",
            "parse_url",
        ),
        "crtraj.hardware.dynamixel._protocol": (
            "HW_ERROR_NAMES",
            "X",
        ),
        "crtraj.hardware.dynamixel._servo_bus": (
            "ServoBus",
            "read_bus_keys",
        ),
        "crtraj.hardware.dynamixel._sim_chain": ("ServoChain",),
        "crtraj.hardware.dynamixel._sim_port": ("SimPort",),
        "crtraj.hardware.dynamixel._sim_pty": ("SimDynamixel",),
        "crtraj.hardware.dynamixel._sim_robot": (
            "home_in_place",
            "robot_chain",
            "stops",
        ),
        "crtraj.hardware.dynamixel._watchdog": ("watchdog_units",),
    },
)
