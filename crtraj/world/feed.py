"""Live obstacle states over UDP JSON, as a motion-capture bridge would send them.

Each datagram is one JSON object, or a list of them::

    {"id": "balloon1", "center": [x, y, z], "radius": r, "timestamp": t}

center and radius in mm, timestamp in s on the sender's clock (used only to
order messages of one obstacle; a message not newer than the last one of its
id is ignored). Freshness is measured on the receiver's monotonic clock: an
obstacle whose last message arrived more than ``max_age`` s ago is stale, and
a stale feed must make the replanner hold. Bad messages are counted and
never stop the feed. The socket binds 127.0.0.1 only.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from crtraj.core.errors import InputError

_KEYS = ("id", "center", "radius", "timestamp")


class StaleFeedError(RuntimeError):
    """The obstacle feed is stale (or incomplete): the caller must hold."""


@dataclass(frozen=True)
class FeedState:
    """A snapshot of the feed. centers (m, 3) mm, radii (m,) mm, velocities (m, 3) mm/s and
    radius_rates (m,) mm/s (finite differences of the last two messages per id, zero after one),
    ages (m,) s since each message arrived, age: the oldest of them (inf when empty).
    stale: True when any obstacle is older than max_age or an expected id is missing."""

    ids: tuple[str, ...]
    centers: np.ndarray
    radii: np.ndarray
    velocities: np.ndarray
    radius_rates: np.ndarray
    timestamps: np.ndarray
    ages: np.ndarray
    age: float
    stale: bool
    reason: str = ""

    def predict(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Centers and radii extrapolated `dt` s ahead at constant rates (radii kept >= 0)."""
        return self.centers + dt * self.velocities, np.maximum(self.radii + dt * self.radius_rates, 0.0)


@dataclass
class _Track:
    center: np.ndarray
    radius: float
    timestamp: float
    received: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius_rate: float = 0.0


def _parse(obj: Any) -> tuple[str, np.ndarray, float, float]:
    """Validate one message; `InputError` naming the bad field."""
    if not isinstance(obj, dict):
        raise InputError(f"message: expected a JSON object, got {type(obj).__name__}")
    for k in obj:
        if k not in _KEYS:
            raise InputError(f"message.{k}: unknown key (known: {', '.join(_KEYS)})")
    for k in _KEYS:
        if k not in obj:
            raise InputError(f"message.{k}: missing")
    oid = obj["id"]
    if isinstance(oid, bool) or not isinstance(oid, (str, int)) or str(oid) == "":
        raise InputError(f"message.id: expected a non-empty string or integer, got {oid!r}")
    c = obj["center"]
    if not isinstance(c, list) or len(c) != 3 or not all(_num(x) for x in c):
        raise InputError(f"message.center: expected 3 finite numbers (mm), got {c!r}")
    r = obj["radius"]
    if not _num(r) or r < 0:
        raise InputError(f"message.radius: expected a finite number >= 0 (mm), got {r!r}")
    ts = obj["timestamp"]
    if not _num(ts):
        raise InputError(f"message.timestamp: expected a finite number (s), got {ts!r}")
    return str(oid), np.array(c, dtype=float), float(r), float(ts)


def _num(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


class ObstacleFeed:
    """Receives obstacle states on a UDP socket bound to 127.0.0.1 (port 0: the OS picks).

    max_age: s after which an obstacle's state is stale. expected: ids that
    must all be present for the feed to be fresh (None: whatever has been seen;
    an empty feed is always stale).
    """

    def __init__(self, port: int = 0, *, max_age: float = 0.1, expected: Iterable[str] | None = None) -> None:
        if not (math.isfinite(max_age) and max_age > 0):
            raise InputError(f"feed.max_age: must be > 0, got {max_age}")
        self.max_age = float(max_age)
        self.expected = None if expected is None else tuple(str(e) for e in expected)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(("127.0.0.1", port))
        except OSError as exc:
            self._sock.close()
            raise InputError(f"feed port {port}: cannot bind 127.0.0.1 ({exc.strerror})") from None
        self._sock.settimeout(0.05)
        self._tracks: dict[str, _Track] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.received = 0
        self.rejected = 0
        self.out_of_order = 0
        self.last_error = ""
        self._thread = threading.Thread(target=self._loop, name="crtraj-obstacle-feed", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self._sock.close()

    def __enter__(self) -> ObstacleFeed:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- input
    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            self.ingest(data, time.monotonic())

    def ingest(self, data: bytes, now: float) -> int:
        """Apply one datagram received at `now` (monotonic s); returns how many states it updated."""
        try:
            msg = json.loads(data.decode("utf-8"))
            items = msg if isinstance(msg, list) else [msg]
            parsed = [_parse(m) for m in items]
        except (UnicodeDecodeError, json.JSONDecodeError, InputError) as exc:
            with self._lock:
                self.rejected += 1
                self.last_error = str(exc).splitlines()[0]
            return 0
        n = 0
        with self._lock:
            for oid, c, r, ts in parsed:
                self.received += 1
                tr = self._tracks.get(oid)
                if tr is not None and ts <= tr.timestamp:
                    self.out_of_order += 1
                    continue
                if tr is None:
                    self._tracks[oid] = _Track(c, r, ts, now)
                else:
                    h = ts - tr.timestamp
                    tr.velocity = (c - tr.center) / h
                    tr.radius_rate = (r - tr.radius) / h
                    tr.center, tr.radius, tr.timestamp, tr.received = c, r, ts, now
                n += 1
        return n

    # ---------------------------------------------------------------- output
    def latest(self, now: float | None = None) -> FeedState:
        """The newest state of every obstacle, flagged stale when any is too old or missing."""
        now = time.monotonic() if now is None else now
        with self._lock:
            ids = tuple(sorted(self._tracks))
            tr = [self._tracks[i] for i in ids]
            centers = np.array([t.center for t in tr]).reshape(-1, 3)
            radii = np.array([t.radius for t in tr])
            vel = np.array([t.velocity for t in tr]).reshape(-1, 3)
            rates = np.array([t.radius_rate for t in tr])
            stamps = np.array([t.timestamp for t in tr])
            ages = np.array([now - t.received for t in tr])
        age = float(ages.max()) if ages.size else math.inf
        reason = ""
        missing = [e for e in (self.expected or ()) if e not in ids]
        if not ids:
            reason = "no obstacle state received yet"
        elif missing:
            reason = f"no state for obstacle(s) {', '.join(missing)}"
        elif age > self.max_age:
            oldest = ids[int(np.argmax(ages))]
            reason = f"obstacle {oldest} state is {age * 1000:.0f} ms old (limit {self.max_age * 1000:.0f} ms)"
        return FeedState(ids, centers, radii, vel, rates, stamps, ages, age, bool(reason), reason)

    def require_fresh(self, now: float | None = None) -> FeedState:
        """`latest`, raising `StaleFeedError` (with the reason) when it is stale."""
        st = self.latest(now)
        if st.stale:
            raise StaleFeedError(f"obstacle feed stale: {st.reason}")
        return st

    # ---------------------------------------------------------------- sender
    @staticmethod
    def send(
        address: tuple[str, int],
        states: Sequence[dict[str, Any]],
        sock: socket.socket | None = None,
    ) -> None:
        """Send obstacle states (dicts with id, center, radius, timestamp) as one datagram,
        as a motion-capture bridge would."""
        data = json.dumps(list(states), allow_nan=False).encode("utf-8")
        own = sock is None
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if own else sock
        try:
            s.sendto(data, address)
        finally:
            if own:
                s.close()
