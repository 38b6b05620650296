"""The streamer's run record: JSON lines (header, frames sent, telemetry received, events, report).

Every line is flushed as it is written, so a crash loses at most the line being written; with ``fsync`` it also
survives a power loss. Times in s, values in actuator units (rad for servos, mm for the z stage).
"""

from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from crtraj import __version__
from crtraj.core.errors import InputError
from crtraj.core.fileio import to_jsonable
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.stream._options import StreamOptions
from crtraj.hardware.transport import TransportError


class RunLog:
    """JSON-lines record of a run, flushed after every line. path: the file (None: record nothing)."""

    def __init__(self, path: str | Path | None, fsync: bool) -> None:
        self.path = None if path is None else Path(path)
        self._fsync = fsync
        self._fh = None
        if self.path is not None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._fh = self.path.open("w", encoding="utf-8")
            except OSError as exc:
                raise InputError(f"--log: cannot write {self.path} ({exc.strerror})") from None

    def write(self, obj: dict[str, Any]) -> None:
        """Append one record (a JSON object on one line); `TransportError` if the file cannot be written."""
        if self._fh is None:
            return
        try:
            self._fh.write(json.dumps(to_jsonable(obj), allow_nan=False, separators=(",", ":")) + "\n")
            self._fh.flush()
            if self._fsync:
                os.fsync(self._fh.fileno())
        except OSError as exc:
            raise TransportError(f"run log {self.path}: {exc}") from None

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def header_record(transport: str, session: int, options: StreamOptions, actuators: Actuators) -> dict[str, Any]:
    """The run log's first line: when, which crtraj, the link (`transport`: its description), the session
    number, the `StreamOptions` and the `Actuators` (their names and units)."""
    return {
        "type": "header",
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "crtraj_version": __version__,
        "transport": transport,
        "session": session,
        "options": options.to_dict(),
        "actuators": actuators.to_dict(),
        "names": list(actuators.names),
        "units": list(actuators.units),
    }
