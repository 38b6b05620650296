"""ROS 2 bridge timing on loopback (the [ros] extra): transport round trip and a real-time closed-loop run.

1. Round trip: the bridge's node publishes a JointTrajectory (one step, 5 points), a robot node
   answers each with a JointState; N round trips, one at a time.
2. The paper's simulation 2 (problems/paper_dynamic.toml) through `crtraj ros-bridge` in real time
   against a robot node that plays each trajectory (JointState at 100 Hz, interpolated) and publishes
   the breathing spheres as SPHERE markers at 50 Hz: the run's outcome, its iteration times and how
   late each step's trajectory reached the robot after the step's start time (computation + transport).

Run: python benchmarks/ros_bridge_timing.py [--round-trips 500]
Prints medians / p90 / max from one run; timings depend on the machine's load.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import Marker, MarkerArray

from crtraj.app.devices._ros_bridge import RosBridgeRequest, run_ros_bridge
from crtraj.control.loop._closed_loop import ClosedLoop
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.ros._messages import si_scale
from crtraj.hardware.ros._node import RosNode, ros_environment
from crtraj.hardware.ros._options import RosOptions
from crtraj.io.problem import Problem
from crtraj.io.results import read_result

ROOT = Path(__file__).resolve().parent.parent
DOMAIN = 10 + os.getpid() % 90


def _stamp(t: float) -> Time:
    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _secs(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


class Robot:
    """Plays the trajectories in real time (each from its start stamp, linear between points; values in ROS
    units, rad and m) and
    publishes JointState at 100 Hz and the scene's spheres at 50 Hz (scene time 0 until the first
    trajectory arrives, then s since); echo=True answers every trajectory at once with a JointState
    instead (the round-trip test)."""

    def __init__(self, ros: RosOptions, names, start, scene=None, echo: bool = False) -> None:
        ros_environment(ros)
        self.ros, self.names, self.scene, self.echo = ros, list(names), scene, echo
        self.position = np.asarray(start, dtype=float)
        self.knots_t, self.knots_v = np.zeros(1), self.position[None].copy()  # the motion it executes (wall s)
        self.late: list[float] = []  # s from each trajectory's start stamp to its arrival
        self.t0: float | None = None  # when the first trajectory arrived
        self.lock = threading.Lock()
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=ros.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("robot_sim", context=self.ctx)
        qos = QoSProfile(depth=ros.depth)
        self.js = self.node.create_publisher(JointState, ros.joint_state_topic, qos)
        self.mk = self.node.create_publisher(MarkerArray, ros.obstacle_topic, qos)
        self.node.create_subscription(JointTrajectory, ros.trajectory_topic, self._on_traj, qos)
        if not echo:
            self.node.create_timer(0.01, self._tick)
            self.node.create_timer(0.02, self._obstacles)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.thread = threading.Thread(target=self.ex.spin, daemon=True)
        self.thread.start()

    def _on_traj(self, msg: JointTrajectory) -> None:
        now = time.time()
        start = _secs(msg.header.stamp)
        self.late.append(now - start)
        self.t0 = now if self.t0 is None else self.t0  # the spheres start breathing (continuously) from here
        if self.echo:
            self._publish(self.position, now)
            return
        offs = np.array([_secs(p.time_from_start) for p in msg.points])
        P = np.array([list(p.positions) for p in msg.points])
        with self.lock:  # a controller follows the current trajectory until the new one's start, then it
            at = self._at(start)
            keep = self.knots_t < start
            self.knots_t = np.concatenate([self.knots_t[keep], [start], start + offs])
            self.knots_v = np.concatenate([self.knots_v[keep], at[None], P])

    def _at(self, now: float) -> np.ndarray:
        return np.array([np.interp(now, self.knots_t, self.knots_v[:, i]) for i in range(self.knots_v.shape[1])])

    def _publish(self, values, now: float) -> None:
        msg = JointState(name=self.names, position=[float(v) for v in values])
        msg.header.stamp = _stamp(now)
        self.js.publish(msg)

    def _tick(self) -> None:
        now = time.time()
        with self.lock:
            self.position = self._at(now)
        self._publish(self.position, now)

    def _obstacles(self) -> None:
        now = time.time()
        centers, radii = self.scene.states(0.0 if self.t0 is None else max(now - self.t0, 0.0))
        out = []
        for o, c, r in zip(self.scene.obstacles, centers, radii, strict=True):
            m = Marker(ns=o.name, id=0, type=2, action=0)
            m.header.frame_id, m.header.stamp = self.ros.frame_id, _stamp(now)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(v) / 1000 for v in c)
            m.scale.x = m.scale.y = m.scale.z = 2 * float(r) / 1000
            out.append(m)
        self.mk.publish(MarkerArray(markers=out))

    def close(self) -> None:
        self.ex.shutdown(timeout_sec=5.0)
        self.thread.join(10.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def _stats(name: str, a, unit: str = "ms", scale: float = 1e3) -> None:
    a = np.asarray(a, dtype=float) * scale
    print(
        f"{name:<52s} median {np.median(a):7.3f} {unit}, p90 {np.percentile(a, 90):7.3f}, "
        f"max {a.max():7.3f}, min {a.min():7.3f} (n={a.size})"
    )


def round_trips(acts: Actuators, start: np.ndarray, n: int) -> None:
    ros = RosOptions(domain_id=DOMAIN)
    node = RosNode(ros, acts)
    robot = Robot(ros, acts.names, start * si_scale(acts.units), echo=True)
    try:
        for _ in range(2000):
            if robot.js.get_subscription_count() and node.matched()[0]:
                break
            time.sleep(0.005)
        offs = 0.02 * np.arange(1, 6)
        P = np.repeat(start[None], 5, axis=0)
        rtt = []
        for k in range(n + 20):
            t = time.time()
            node.publish_trajectory(t, offs, P, np.zeros_like(P))
            if node.wait_joint_state(t, 5.0) is None:
                raise RuntimeError(f"round trip {k}: no answer within 5 s")
            if k >= 20:  # warm-up
                rtt.append(time.time() - t)
        _stats("JointTrajectory -> JointState round trip", rtt)
    finally:
        robot.close()
        node.close()


def closed_loop(problem_path: Path, acts: Actuators, start: np.ndarray, scene, lead: float) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        text = problem_path.read_text().replace(
            'robot = "robots/cdsr2.toml"', f'robot = "{ROOT / "problems/robots/cdsr2.toml"}"'
        )
        p = Path(tmp) / "paper_dynamic_ros.toml"
        p.write_text(text + f"\n[ros]\ndomain_id = {DOMAIN}\nlead = {lead}\n")
        ros = Problem.load(p).options(RosOptions, "ros")
        robots = []
        t = time.perf_counter()
        code = run_ros_bridge(
            RosBridgeRequest(p, out=Path(tmp) / "run", html=False, quiet=True),
            ready=lambda node, feed: robots.append(Robot(ros, acts.names, start * si_scale(acts.units), scene)),
        )
        wall = time.perf_counter() - t
        for r in robots:
            r.close()
        res = read_result(Path(tmp) / "run" / "run.json")
        s = res.data["summary"]
        print(
            f"paper_dynamic in real time: exit {code}, {res.status}, {s['steps']} steps, collisions "
            f"{s['collisions']}, min clearance {s['min_clearance_mm']} mm, late steps {s['late_steps']}, "
            f"wall {wall:.1f} s"
        )
        print(
            f"  device: {res.data['stream']['refused_steps']} refused ({res.data['stream']['refusal'][:200]}), "
            f"{res.data['stream']['restarts']} restarts"
        )
        _stats("step iteration (NLP, checks, publish)", [w["iteration_time"] for w in res.data["waypoints"][1:]])
        _stats("trajectory arrival after its step's start", robots[0].late)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--round-trips", type=int, default=500)
    ap.add_argument("--lead", type=float, default=0.2, help="[ros] lead, s (default 0.2)")
    args = ap.parse_args()
    print(
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.node()}, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.2f}; RMW {os.environ.get('RMW_IMPLEMENTATION', 'default')}"
    )
    path = ROOT / "problems" / "paper_dynamic.toml"
    problem = Problem.load(path)
    loop = ClosedLoop.from_problem(problem)
    acts = Actuators.from_robot(problem.robot)
    start = acts.command(loop.start_command())
    round_trips(acts, start, args.round_trips)
    closed_loop(path, acts, start, loop.scene, args.lead)


if __name__ == "__main__":
    main()
