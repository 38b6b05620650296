"""Use cases of the commands that talk to a device or simulate one: stream, approach, home, the simulated
devices, the feed replay and the ROS 2 bridge.

Public names load on first use (`crtraj.core.lazy.lazy_exports`); the modules behind them are private.
"""

from __future__ import annotations

from crtraj.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "crtraj.app.devices._approach": ("plan_approach",),
        "crtraj.app.devices._feed_replay": ("feed_replay_command",),
        "crtraj.app.devices._home": ("home_command",),
        "crtraj.app.devices._ros_bridge": (
            "RosBridgeRequest",
            "ros_bridge_command",
            "run_ros_bridge",
        ),
        "crtraj.app.devices._sim_device": ("sim_device_command",),
        "crtraj.app.devices._sim_dynamixel": ("sim_dynamixel_command",),
        "crtraj.app.devices._stream": (
            "admit_result",
            "failure_line",
            "print_report",
            "stream_command",
            "stream_motion",
        ),
    },
)
