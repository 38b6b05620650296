"""Motion-capture tip markers as the closed loop's `crtraj.control.ports.TipSensor`.

`SimulatedMocap`: the tip of a robot whose real parameters differ from the model the loop plans with. The
loop's actuation q (mm, in the loop's robot file) becomes servo values through that file's actuators (what
a device would be sent); the true robot's parameters (its robot file: lengths, coupling, cable radius, zero
offsets) turn those values into the tip the capture system sees, plus Gaussian noise per axis. The capture
frame is taken as calibrated (the reading is in the robot frame).

`MocapTip`: a live capture system's tip marker over UDP JSON on 127.0.0.1, one object (or a list of them)
per datagram, ``{"marker": "tip", "position": [x, y, z]}`` (or ``"x"``, ``"y"``, ``"z"`` keys) in the capture
frame (mm), mapped to the robot frame through the calibrated capture frame (``[calibration]`` of the robot
file: p_robot = R p_capture + t). Every datagram is hostile: oversized, deeply nested, non-JSON, malformed
or non-finite ones are counted and dropped; other markers are ignored. A reading older than ``max_age`` s
on the receiver's clock (injectable) is stale: the loop then gets None and keeps its last estimate.
Units: mm, rad, s.
"""

from __future__ import annotations

import json
import math
import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.model.calibration import (
    CalibrateOptions,
    CalibrationModel,
    Hardware,
    Layout,
    MarkerSite,
    rotation_matrix,
)
from crtraj.model.robot import Robot
from crtraj.world.feed import MAX_COORDINATE, MAX_DATAGRAM_BYTES, MAX_NESTING, nesting_depth_exceeds

# Datagrams read per `MocapTip.tip` call at most (the newest valid reading wins).
MAX_DRAIN = 10_000


def check_true_robot(true_robot: Robot, true_act: Actuators, commanded: Actuators) -> None:
    """Refuse (one line) a --true-robot file that is not the loop's robot with other parameters: its segment
    count (so its actuator count) must be the same, as each servo value is passed to it unchanged."""
    if true_act.n_segments != commanded.n_segments or true_act.n != commanded.n:
        raise InputError(
            f"--true-robot: robot {true_robot.name!r} has {true_act.n_segments} segments, the problem's robot has "
            f"{commanded.n_segments}: give a copy of the problem's robot file with only its parameters changed"
        )


class SimulatedMocap:
    """Tip readings of `true_robot` driven with the servo values `commanded` computes from the loop's q.

    noise: standard deviation per axis (mm; the paper's capture: 0.3). seed: the noise's seed.
    """

    def __init__(self, true_robot: Robot, commanded: Actuators, *, noise: float = 0.3, seed: int = 0) -> None:
        if not 0.0 <= noise <= 100.0:
            raise InputError(f"mocap noise: must be in [0, 100] mm, got {noise}")
        if true_robot.actuators is None:
            raise InputError(f"--true-robot: robot {true_robot.name!r} has no [robot.actuators] (its zero offsets)")
        true_act = Actuators.from_robot(true_robot)
        check_true_robot(true_robot, true_act, commanded)
        layout = Layout.build(true_robot, true_act.zero_offset, np.zeros(6), CalibrateOptions())
        site = (MarkerSite("tip", true_robot.n_segments - 1),)
        self._cm = CalibrationModel(true_robot, Hardware(true_act.spool_radius, true_act.sign), site, layout)
        self._theta = layout.prior
        self._commanded = commanded
        self._noise = float(noise)
        self._rng = np.random.default_rng(seed)

    def close(self) -> None:
        """Nothing to release (the live sensor's counterpart closes its socket)."""

    def true_tip(self, q: np.ndarray) -> np.ndarray:
        """The true robot's tip (3,) mm, without noise, for the loop's actuation q (mm)."""
        values = self._commanded.command(np.asarray(q, dtype=float))
        return np.asarray(self._cm.markers(self._theta, values)).reshape(3)

    def tip(self, t: float, q: np.ndarray) -> np.ndarray | None:
        """A noisy reading of the true tip (3,) mm."""
        return self.true_tip(q) + self._rng.normal(0.0, self._noise, 3)


class MocapTip:
    """The live capture's tip marker (see the module docstring). capture: (6,) rotation vector (rad) and
    translation (mm), capture -> robot. port: UDP port on 127.0.0.1 (0: the OS picks; `address`).
    marker: the marker's name. max_age: s after which a reading is stale. clock: monotonic s."""

    def __init__(
        self,
        capture: np.ndarray,
        *,
        port: int = 0,
        marker: str = "tip",
        max_age: float = 0.1,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        cap = np.asarray(capture, dtype=float)
        if cap.shape != (6,) or not np.all(np.isfinite(cap)):
            raise InputError("capture frame: expected 6 finite numbers (rotation vector rad, translation mm)")
        if not 0 < max_age <= 10:
            raise InputError(f"--mocap max_age: must be in (0, 10] s, got {max_age}")
        if not 0 <= port <= 65535:
            raise InputError(f"--mocap: port must be in 0..65535, got {port}")
        self._R, self._t = rotation_matrix(cap[:3]), cap[3:]
        self.marker, self.max_age, self._clock = marker, float(max_age), clock
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(("127.0.0.1", port))  # never beyond this machine
        except OSError as exc:
            self._sock.close()
            raise InputError(f"--mocap: cannot listen on 127.0.0.1:{port} ({exc.strerror})") from None
        self._sock.setblocking(False)
        self._last: tuple[float, np.ndarray] | None = None
        self.accepted = 0
        self.rejected = 0
        self.last_reason = ""

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> MocapTip:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def ingest(self, data: bytes, now: float) -> bool:
        """Take one datagram received at `now`; True when it carried a valid reading of the marker."""
        try:
            p = self._parse(data)
        except ValueError as exc:
            self.rejected += 1
            self.last_reason = str(exc)
            return False
        if p is None:
            return False
        self._last = (now, self._R @ p + self._t)
        self.accepted += 1
        return True

    def _parse(self, data: bytes) -> np.ndarray | None:
        if len(data) > MAX_DATAGRAM_BYTES:
            raise ValueError(f"datagram of {len(data)} bytes")
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError("not UTF-8") from None
        if nesting_depth_exceeds(text, MAX_NESTING):
            raise ValueError("nested too deeply")
        try:
            obj = json.loads(text)
        except (ValueError, RecursionError):
            raise ValueError("not JSON") from None
        found = None
        for msg in obj if isinstance(obj, list) else [obj]:
            if not isinstance(msg, dict):
                raise ValueError("a message is not an object")
            if msg.get("marker") != self.marker:
                continue
            xyz: Any = msg.get("position", [msg.get("x"), msg.get("y"), msg.get("z")])
            if not isinstance(xyz, list) or len(xyz) != 3:
                raise ValueError("position: expected [x, y, z]")
            for v in xyz:
                ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                if not ok or abs(v) > MAX_COORDINATE:
                    raise ValueError(f"position: {v!r} is not a finite coordinate (mm)")
            found = np.array(xyz, dtype=float)
        return found

    def poll(self) -> None:
        """Read the queued datagrams (at most MAX_DRAIN)."""
        for _ in range(MAX_DRAIN):
            try:
                data = self._sock.recv(MAX_DATAGRAM_BYTES + 1)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return
            self.ingest(data, self._clock())

    def tip(self, t: float, q: np.ndarray) -> np.ndarray | None:
        """The newest reading in the robot frame (mm), or None when there is none younger than max_age."""
        self.poll()
        if self._last is None or self._clock() - self._last[0] > self.max_age:
            return None
        return self._last[1].copy()

    def describe(self) -> dict[str, Any]:
        return {"accepted": self.accepted, "rejected": self.rejected, "last_reason": self.last_reason}
