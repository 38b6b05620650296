"""The ``[ros]`` problem section: topics, QoS, frame and timing of the ROS 2 bridge (`crtraj ros-bridge`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.options import Options, option

MAX_JOINT_NAME = 128
_TOPIC_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_/~{}")


@dataclass(frozen=True)
class RosOptions(Options):
    """The ``[ros]`` section (units s, Hz).

    controller: the robot's joint_trajectory_controller (its parameters are read from
    ``/<controller>/get_parameters`` at start when reachable). trajectory_topic: where each verified
    step is published (trajectory_msgs/JointTrajectory, rad for the servos and m for the base stage;
    default ``/<controller>/joint_trajectory``). joints: crtraj actuator name -> the robot's joint
    name (``[ros.joints]``; an actuator not listed keeps its name). joint_state_topic: the robot's
    measured joint positions (sensor_msgs/JointState, the robot's joint names, same units).
    path_topic: the tip along each executed, verified curve (nav_msgs/Path, m) for RViz.
    obstacle_topic: live obstacles (visualization_msgs/MarkerArray; SPHERE markers, ``ns`` = the
    scene's obstacle name, position and scale in m). markers_topic: what the bridge shows in RViz
    (backbone and obstacles, MarkerArray, m). frame_id: the frame of every marker sent and
    accepted. reliability and depth: the QoS of every topic (history keep-last `depth`); best_effort
    is refused, as a best_effort publisher never reaches the controller's reliable subscription.
    domain_id: the ROS domain (default: the environment's ROS_DOMAIN_ID, else 0). discovery:
    "localhost" keeps discovery on this machine (the default, as every crtraj server binds
    127.0.0.1), "subnet" lets other machines in.
    points_per_step: trajectory points per replan step (each checked before it is sent). lead: s
    each step is sent before it starts (the live obstacles are predicted that far ahead).
    arrival_margin: s a message may take to reach the controller; a step not ready that long before
    its start (more than ``lead - arrival_margin`` s late) is refused, counted and the robot held.
    state_lag: s the controller's state lags its command when it reads it for the point before a
    new trajectory (one update period of ros2_control, 1 / update_rate; the bridge's messages never
    use that point, and its verification models it).
    distro: the ros2_controllers release of the controller ("auto": told by the parameters it declares;
    `crtraj.hardware.ros._controller.detect_distro`); it decides how the messages are stamped when the
    controller's parameter service does not answer (then "auto" means Humble). update_rate: Hz of the
    controller (0: its own ``update_rate`` parameter); Jazzy and later sample the trajectory one period ahead.
    joint_state_timeout: s the bridge waits for a joint state at least as new as the step it
    measures before it gives up on the robot. following_error: mm of actuation a joint state may be off the
    curve sent to the controller at its stamp (0: unchecked); beyond it the run stops, reported: the controller
    is not executing what was verified (an inactive controller keeps its subscription but drops every
    message, and the topic gives no feedback). start_timeout: s to wait for the first joint state
    and obstacles. max_age: s after which an obstacle's state is stale (the loop then holds).
    udp_feed_port: also listen for the UDP JSON obstacle feed on 127.0.0.1 at this port (0: a
    free port the bridge prints).
    """

    SECTION: ClassVar[str] = "ros"

    controller: str = option("joint_trajectory_controller", max_len=200)
    trajectory_topic: str = option("", max_len=200)
    joints: tuple[tuple[str, str], ...] = option((), read=False)
    joint_state_topic: str = option("/joint_states", max_len=200)
    obstacle_topic: str = option("/crtraj/obstacles", max_len=200)
    markers_topic: str = option("/crtraj/markers", max_len=200)
    path_topic: str = option("/crtraj/executed_path", max_len=200)
    frame_id: str = option("world", max_len=200)
    reliability: str = option("reliable", choices=("reliable", "best_effort"))
    depth: int = option(10, ge=1, le=1000)
    domain_id: int | None = option(None, ge=0, le=232)
    discovery: str = option("localhost", choices=("localhost", "subnet"))
    points_per_step: int = option(5, ge=1, le=100)
    lead: float = option(0.2, ge=0.0, le=10.0)
    arrival_margin: float = option(0.02, ge=0.0, le=1.0)
    state_lag: float = option(0.01, ge=0.0, le=1.0)
    distro: str = option("auto", choices=("auto", "humble", "jazzy", "rolling"))
    update_rate: float = option(0.0, ge=0.0, le=100000.0)
    joint_state_timeout: float = option(1.0, gt=0.0, le=60.0)
    following_error: float = option(3.0, ge=0.0, le=1000.0)
    start_timeout: float = option(10.0, gt=0.0, le=600.0)
    max_age: float = option(0.2, gt=0.0, le=60.0)
    udp_feed_port: int = option(0, ge=0, le=65535)

    @property
    def trajectory_topic_name(self) -> str:
        """The trajectory topic: ``trajectory_topic``, else ``/<controller>/joint_trajectory``."""
        return self.trajectory_topic or f"/{self.controller}/joint_trajectory"

    def joint_name(self, actuator: str) -> str:
        """The robot's joint name of crtraj actuator `actuator`."""
        return dict(self.joints).get(actuator, actuator)

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        sub = t.table("joints")
        pairs = tuple((key, sub.str(key, max_len=MAX_JOINT_NAME)) for key in sub.keys())
        sub.finish()
        return {"joints": pairs}

    def to_dict(self) -> dict[str, Any]:
        out = super().to_dict()
        out["joints"] = dict(self.joints)
        return out

    def _check(self) -> None:
        if self.lead <= self.arrival_margin:
            raise InputError(
                f"ros.arrival_margin: must be less than ros.lead ({self.lead:g} s), got {self.arrival_margin:g} s "
                "(every step would be refused as late)"
            )
        if self.reliability == "best_effort":
            raise InputError(
                "ros.reliability: best_effort is refused: joint_trajectory_controller subscribes reliable, and a "
                "best_effort publisher never reaches it (trajectories would be lost silently); use reliable"
            )
        if not self.controller or not set(self.controller) <= _TOPIC_CHARS or self.controller.startswith("/"):
            raise InputError(
                f"ros.controller: not a controller name (letters, digits, _ and /), got {self.controller[:60]!r}"
            )
        for actuator, joint in self.joints:
            if not joint or not joint.isprintable() or not actuator:
                raise InputError(f"ros.joints.{actuator[:40]}: expected a non-empty joint name, got {joint[:60]!r}")
        seen: dict[str, str] = {}
        for actuator, joint in self.joints:
            if joint in seen:
                raise InputError(
                    f"ros.joints: {seen[joint]} and {actuator} both map to joint {joint[:60]!r}; give each actuator "
                    "its own joint name"
                )
            seen[joint] = actuator
        for key in ("trajectory_topic_name", "joint_state_topic", "obstacle_topic", "markers_topic", "path_topic"):
            name = getattr(self, key)
            key = key.removesuffix("_name")
            if not name or not set(name) <= _TOPIC_CHARS or "//" in name or name.endswith("/"):
                raise InputError(f"ros.{key}: not a ROS topic name (letters, digits, _ and /), got {name[:60]!r}")
        if not self.frame_id or not self.frame_id.isprintable():
            raise InputError(f"ros.frame_id: expected a non-empty printable frame name, got {self.frame_id[:60]!r}")
