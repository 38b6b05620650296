"""Record what the ROS 2 bridge sent and received to an MCAP file (`crtraj ros-bridge --record FILE`).

Every message is stored CDR-serialized (rclpy's ``serialize_message``, as a rosbag2 MCAP file holds
it) on a channel named by its topic, with a ``ros2msg`` schema: the message definition and its
dependencies as ``.msg`` text, read from the installed message packages, so Foxglove and
``ros2 bag`` can decode the run. The file is written under a temporary name next to FILE and
renamed to FILE by `commit` (an interrupted run leaves no half file under FILE).
Log times in ns of the system clock.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from pathlib import Path
from typing import Any

from crtraj.core.errors import InputError
from crtraj.core.fileio import StagedFile

log = logging.getLogger(__name__)

_PRIMITIVES = frozenset(
    {
        "bool",
        "byte",
        "char",
        "float32",
        "float64",
        "int8",
        "uint8",
        "int16",
        "uint16",
        "int32",
        "uint32",
        "int64",
        "uint64",
        "string",
        "wstring",
    }
)
_SEPARATOR = "=" * 80


def _msg_text(full_name: str) -> str:
    """The .msg definition of ``pkg/msg/Type`` from the installed package's share folder (the prefixes of
    AMENT_PREFIX_PATH, then this Python's prefix, where the pip wheels install them)."""
    pkg, _, name = full_name.split("/")
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p] + [sys.prefix]
    for prefix in prefixes:
        f = Path(prefix) / "share" / pkg / "msg" / f"{name}.msg"
        if f.is_file():
            return f.read_text()
    raise InputError(f"--record: no message definition of {full_name} under {', '.join(prefixes)}")


def _field_types(text: str, pkg: str) -> list[str]:
    """The message types (``pkg/msg/Type``) the fields of a .msg definition use."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        typ = line.split()[0].split("[", 1)[0].split("<=", 1)[0]
        if typ in _PRIMITIVES:
            continue
        if "/" in typ:
            dep_pkg, dep = typ.split("/")[0], typ.split("/")[-1]
        else:
            dep_pkg, dep = pkg, typ
        out.append(f"{dep_pkg}/msg/{dep}")
    return out


def schema_text(full_name: str) -> str:
    """The ros2msg schema of ``pkg/msg/Type``: its definition, then each dependency once after a separator
    line and ``MSG: pkg/Type`` (the layout rosbag2 writes)."""
    main = _msg_text(full_name)
    parts, seen = [main], {full_name}
    queue = _field_types(main, full_name.split("/")[0])
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        text = _msg_text(dep)
        pkg, _, name = dep.split("/")
        parts.append(f"{_SEPARATOR}\nMSG: {pkg}/{name}\n{text}")
        queue.extend(_field_types(text, pkg))
    return "\n".join(parts)


# the message types the bridge sends and receives (their schemas are read before the run starts)
RECORDED_TYPES = (
    "trajectory_msgs/msg/JointTrajectory",
    "sensor_msgs/msg/JointState",
    "visualization_msgs/msg/MarkerArray",
    "nav_msgs/msg/Path",
)


class McapRecorder:
    """Writes messages to `path` (under a temporary name until `commit`). Thread-safe: the node's spin
    thread writes what it receives while the loop writes what it sends."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        try:
            from mcap.writer import Writer
        except ImportError as exc:
            raise InputError(f"--record: needs the mcap package (pip install -e '.[ros]'): {exc}") from None
        schemas = {name: schema_text(name) for name in RECORDED_TYPES}
        self.path = Path(path)
        self._staged = StagedFile(self.path)  # removed on every exit that does not commit (crtraj.core.fileio)
        self._fh = open(self._staged.path, "wb")  # noqa: SIM115 - closed by commit / discard
        self._writer = Writer(self._fh)
        self._writer.start(profile="ros2", library="crtraj")
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self._texts = schemas
        self._channels: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self.messages = 0
        self._open = True

    def write(self, topic: str, msg: Any, log_time_ns: int) -> None:
        """Add `msg` on `topic` at `log_time_ns` (its header stamp, when it has one, is the publish time)."""
        from rclpy.serialization import serialize_message

        data = serialize_message(msg)
        with self._lock:
            if not self._open:
                return
            channel = self._channel(topic, msg)
            seq = self._seq.get(channel, 0)
            self._seq[channel] = seq + 1
            stamp = getattr(getattr(msg, "header", None), "stamp", None)
            publish = log_time_ns if stamp is None else int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
            self._writer.add_message(channel, log_time=log_time_ns, data=data, publish_time=publish, sequence=seq)
            self.messages += 1

    def _channel(self, topic: str, msg: Any) -> int:
        name = type_name(msg)
        if topic not in self._channels:
            if name not in self._schemas:
                text = (self._texts.get(name) or schema_text(name)).encode("utf-8")
                self._schemas[name] = self._writer.register_schema(name=name, encoding="ros2msg", data=text)
            self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self._schemas[name]
            )
        return self._channels[topic]

    def commit(self) -> Path:
        """Finish the file and rename it to `path`."""
        with self._lock:
            self._open = False
            self._writer.finish()
            self._fh.close()
        self._staged.commit()
        log.info("ros: recorded %d messages to %s", self.messages, self.path)
        return self.path

    def discard(self) -> None:
        """Drop the temporary file (nothing is written to `path`)."""
        with self._lock:
            if self._open:
                self._open = False
                self._fh.close()
        self._staged.discard()


def type_name(msg: Any) -> str:
    """``pkg/msg/Type`` of a generated rclpy message instance."""
    module = type(msg).__module__.split(".")[0]
    return f"{module}/msg/{type(msg).__name__}"
