"""Live obstacle states over UDP JSON, as a motion-capture bridge would send them.

Each datagram is one JSON object, or a list of them::

    {"id": "balloon1", "center": [x, y, z], "radius": r, "timestamp": t}

center and radius in mm, timestamp in s on the sender's clock. The socket
binds 127.0.0.1 only. Every datagram is treated as hostile; it is rejected,
counted and recorded (`ObstacleFeed.events`, kind and one-line reason) when:

- it is larger than `MAX_DATAGRAM_BYTES` (checked before any decoding);
- it is not UTF-8, nests deeper than `MAX_NESTING` (checked by a linear scan
  before parsing, so a flood of ``[`` never reaches the recursive parser), is
  not JSON, or a message in it is malformed: unknown or missing keys, values
  that are not finite numbers, coordinates or radii beyond `MAX_COORDINATE`
  mm, timestamps beyond `MAX_TIMESTAMP` s (kind "invalid");
- a message names an id outside the `expected` ids (kind "unknown_id"; the
  other messages of the datagram still count);
- a message's timestamp is not newer than the last accepted one of its id
  ("out_of_order"), or maps to a receiver time more than
  `FeedOptions.max_skew` s away from its arrival ("timestamp").

Timing. Freshness is measured on the receiver's clock (`clock`, monotonic s;
injectable, so tests can run on virtual time). Each id keeps the smallest
offset seen between arrival and sender time; a message's measurement time on
the receiver's clock is its timestamp plus that offset, which is never later
than its arrival (a delayed message is as old as its data). A message that
maps further than max_skew from its arrival is rejected, so one absurd
timestamp cannot make every later message look old. An id that received
nothing for `max_age` s restarts from its next valid message (kind "resync":
a restarted sender, or a sender clock that jumped). An obstacle measured more
than `max_age` s ago is stale, and a stale feed must make the replanner hold.

Prediction. Velocities (mm/s) and radius rates are least-squares slopes over
the id's messages of the last `FeedOptions.velocity_window` s of sender time,
and only once those span `FeedOptions.min_span` s (zero before: two messages
microseconds apart say nothing about speed). Both are clamped to
`FeedOptions.max_speed` (logged, kind "speed_clamped"). The keep-out region
`FeedState.predict` gives always contains the last measured sphere: its
centre moves at the velocity, and its radius grows at
``max(radius rate, |velocity|)`` from the measured radius.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.options import Options, option

_KEYS = ("id", "center", "radius", "timestamp")

MAX_DATAGRAM_BYTES = 16384  # a list of ~150 obstacle messages; larger datagrams are rejected unread
MAX_NESTING = 3  # a list of objects holding a centre list; deeper JSON is rejected before parsing
MAX_COORDINATE = 1.0e6  # mm: |centre component| and radius bound (keeps every difference finite)
MAX_TIMESTAMP = 1.0e10  # s: |timestamp| bound (Unix time fits; float64 keeps sub-microsecond steps)
MAX_ID_CHARS = 128
MAX_TRACKS = 256  # ids kept when no expected ids are given
MAX_EVENTS = 1000  # rejection/clamp records kept per feed (counts stay exact beyond it)
_HISTORY = 32  # samples kept per id for the velocity fit


class StaleFeedError(RuntimeError):
    """The obstacle feed is stale (or incomplete): the caller must hold."""


@dataclass(frozen=True)
class FeedOptions(Options):
    """The ``[feed]`` problem section (units mm, s).

    max_speed: mm/s, the fastest an obstacle's centre or radius may change;
    faster estimates are clamped to it (default 500 mm/s, a brisk hand).
    velocity_window: s of sender time the velocity is fitted over (0.25).
    min_span: s the fitted messages must span before any velocity is
    estimated (0.05; shorter spans give zero velocity; at most
    velocity_window). max_skew: s a message's timestamp may map away from its
    arrival on the receiver's clock before it is rejected (0.5).
    """

    SECTION: ClassVar[str] = "feed"

    max_speed: float = option(500.0, gt=0.0, le=1.0e5)
    velocity_window: float = option(0.25, gt=0.0, le=10.0)
    min_span: float = option(0.05, gt=0.0, le=10.0)
    max_skew: float = option(0.5, gt=0.0, le=60.0)

    def _check(self) -> None:
        if self.min_span > self.velocity_window:
            raise InputError(
                f"feed.min_span: must not exceed feed.velocity_window ({self.velocity_window:g} s), "
                f"got {self.min_span:g}"
            )


@dataclass(frozen=True)
class FeedEvent:
    """One rejected (or clamped / resynchronised) message: received (s, the receiver's
    clock), kind (oversize, nesting, decode, invalid, unknown_id, too_many_ids,
    out_of_order, timestamp, speed_clamped, resync, internal) and a one-line reason."""

    received: float
    kind: str
    message: str

    def to_dict(self) -> dict[str, Any]:
        return {"received": self.received, "kind": self.kind, "message": self.message}


# kinds that are not rejections: the message was used
_NOT_REJECTIONS = ("speed_clamped", "resync")


@dataclass(frozen=True)
class FeedState:
    """A snapshot of the feed. centers (m, 3) mm, radii (m,) mm: the last measured spheres;
    velocities (m, 3) mm/s and radius_rates (m,) mm/s (windowed least-squares fits, clamped
    to the feed's max_speed; zero until the window spans min_span); growth (m,) mm/s: how
    fast the keep-out radius grows (max(radius rate, |velocity|)); ages (m,) s since each
    state was measured, age: the oldest of them (inf when empty). stale: True when any
    obstacle is older than max_age or an expected id is missing."""

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
    growth: np.ndarray | None = None

    def keep_out_growth(self) -> np.ndarray:
        """(m,) mm/s: the keep-out radius growth rate, never below the centre's speed."""
        speed = np.linalg.norm(self.velocities.reshape(-1, 3), axis=1)
        g = np.maximum(self.radius_rates, speed) if self.growth is None else np.maximum(self.growth, speed)
        return np.maximum(g, 0.0)

    def predict(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The keep-out spheres `dt` s after the measurements: centres (m, 3) mm extrapolated at
        constant velocity, radii (m,) mm grown at `keep_out_growth` from the measured radii, so
        each keep-out sphere contains its last measured sphere."""
        return self.centers + dt * self.velocities, self.radii + abs(dt) * self.keep_out_growth()


@dataclass
class _Track:
    center: np.ndarray
    radius: float
    timestamp: float  # sender s
    received: float  # receiver s (arrival of the last accepted message)
    offset: float  # smallest arrival - timestamp seen (s)
    hist: deque[tuple[float, np.ndarray, float]] = field(default_factory=lambda: deque(maxlen=_HISTORY))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius_rate: float = 0.0

    @property
    def measured(self) -> float:
        """Receiver time (s) of the last state's measurement."""
        return self.timestamp + self.offset


def _parse(obj: Any) -> tuple[str, np.ndarray, float, float]:
    """Validate one message; `InputError` naming the bad field."""
    if not isinstance(obj, dict):
        raise InputError(f"message: expected a JSON object, got {type(obj).__name__}")
    for k in obj:
        if k not in _KEYS:
            raise InputError(f"message.{str(k)[:40]}: unknown key (known: {', '.join(_KEYS)})")
    for k in _KEYS:
        if k not in obj:
            raise InputError(f"message.{k}: missing")
    oid = obj["id"]
    if isinstance(oid, bool) or not isinstance(oid, (str, int)) or not _short_id(oid):
        raise InputError(f"message.id: expected a non-empty string or integer (<= {MAX_ID_CHARS} chars)")
    c = obj["center"]
    if not isinstance(c, list) or len(c) != 3 or not all(_num(x, MAX_COORDINATE) for x in c):
        raise InputError(f"message.center: expected 3 finite numbers within +-{MAX_COORDINATE:g} mm")
    r = obj["radius"]
    if not _num(r, MAX_COORDINATE) or r < 0:
        raise InputError(f"message.radius: expected a finite number in [0, {MAX_COORDINATE:g}] mm")
    ts = obj["timestamp"]
    if not _num(ts, MAX_TIMESTAMP):
        raise InputError(f"message.timestamp: expected a finite number within +-{MAX_TIMESTAMP:g} s")
    return str(oid), np.array(c, dtype=float), float(r), float(ts)


def _short_id(oid: str | int) -> bool:
    if isinstance(oid, int):
        return -(10**MAX_ID_CHARS) < oid < 10**MAX_ID_CHARS
    return 0 < len(oid) <= MAX_ID_CHARS


def _num(x: Any, bound: float) -> bool:
    """A JSON number within +-bound (huge integers are not numbers here: float() would overflow)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    if isinstance(x, int):
        return -bound <= x <= bound
    return math.isfinite(x) and -bound <= x <= bound


def nesting_depth_exceeds(text: str, limit: int) -> bool:
    """True when JSON `text` opens more than `limit` nested arrays/objects (strings skipped).

    A linear scan without recursion, so it is safe on any input."""
    depth = 0
    in_str = esc = False
    for ch in text:
        if in_str:
            if esc:
                esc = False
            elif ch == "\\":
                esc = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            if depth > limit:
                return True
        elif ch in "]}":
            depth -= 1
    return False


class _RejectedError(Exception):
    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def _decode(data: bytes) -> list[tuple[str, np.ndarray, float, float]]:
    """The messages of one datagram, or `_RejectedError` (kind, reason). Checks size and depth first."""
    if len(data) > MAX_DATAGRAM_BYTES:
        raise _RejectedError("oversize", f"datagram: {len(data)} bytes exceeds the {MAX_DATAGRAM_BYTES}-byte limit")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise _RejectedError("decode", "datagram: not UTF-8 text") from None
    if nesting_depth_exceeds(text, MAX_NESTING):
        raise _RejectedError("nesting", f"datagram: JSON nested deeper than {MAX_NESTING} levels")
    try:
        msg = json.loads(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, huge integer literals
        raise _RejectedError("decode", f"datagram: not JSON ({str(exc).splitlines()[0][:120]})") from None
    items = msg if isinstance(msg, list) else [msg]
    try:
        return [_parse(m) for m in items]
    except InputError as exc:
        raise _RejectedError("invalid", str(exc).splitlines()[0]) from None


def _fit(hist: Iterable[tuple[float, np.ndarray, float]], min_span: float) -> tuple[np.ndarray, float]:
    """Least-squares slopes (mm/s) of centre and radius over the samples; zeros when they span < min_span."""
    h = list(hist)
    if len(h) < 2:
        return np.zeros(3), 0.0
    t = np.array([s[0] for s in h])
    t = t - t[-1]  # relative: keeps precision with large sender timestamps
    if t[-1] - t[0] < min_span:
        return np.zeros(3), 0.0
    C = np.array([s[1] for s in h])
    R = np.array([s[2] for s in h])
    tc = t - t.mean()
    den = float(tc @ tc)
    return tc @ (C - C.mean(axis=0)) / den, float(tc @ (R - R.mean()) / den)


class ObstacleFeed:
    """Receives obstacle states on a UDP socket bound to 127.0.0.1 (port 0: the OS picks).

    max_age: s after which an obstacle's state is stale. expected: ids that
    must all be present for the feed to be fresh; messages for other ids are
    rejected (None: whatever has been seen, at most `MAX_TRACKS` ids; an
    empty feed is always stale). options: `FeedOptions` (velocity window and
    bound, timestamp window). clock: the receiver's clock (monotonic s);
    inject a virtual one to run on simulated time.
    """

    def __init__(
        self,
        port: int = 0,
        *,
        max_age: float = 0.1,
        expected: Iterable[str] | None = None,
        options: FeedOptions | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (math.isfinite(max_age) and max_age > 0):
            raise InputError(f"feed.max_age: must be > 0, got {max_age}")
        self.max_age = float(max_age)
        self.expected = None if expected is None else tuple(str(e) for e in expected)
        self.options = FeedOptions() if options is None else options
        self.clock = clock
        self._tracks: dict[str, _Track] = {}
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        self._stop = threading.Event()
        self.received = 0  # messages parsed (accepted or not)
        self.datagrams = 0  # datagrams handled
        self.accepted = 0  # messages that updated a state
        self.rejected = 0  # messages (or whole datagrams) rejected
        self.out_of_order = 0
        self.last_error = ""
        self.counts: dict[str, int] = {}
        self._events: list[FeedEvent] = []
        self.events_dropped = 0
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.bind(("127.0.0.1", port))
        except OSError as exc:
            self._sock.close()
            raise InputError(f"feed port {port}: cannot bind 127.0.0.1 ({exc.strerror})") from None
        self._sock.settimeout(0.05)
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

    def configure(self, options: FeedOptions) -> None:
        """Use `options` from now on (e.g. a problem's ``[feed]`` section); refits every velocity."""
        with self._lock:
            self.options = options
            for oid, tr in self._tracks.items():
                self._refit(oid, tr, self.clock())

    @property
    def alive(self) -> bool:
        """The receiver thread is running (it only stops on `close`)."""
        return self._thread.is_alive()

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
            try:
                self.ingest(data, self.clock())
            except Exception as exc:  # the receiver must outlive any datagram
                with self._lock:
                    self.datagrams += 1
                    self._reject(self.clock(), "internal", f"datagram: {type(exc).__name__} while handling it")
                    self._arrived.notify_all()

    def _record(self, now: float, kind: str, message: str) -> None:
        """Count and keep one event (caller holds the lock)."""
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if len(self._events) < MAX_EVENTS:
            self._events.append(FeedEvent(float(now), kind, message))
        else:
            self.events_dropped += 1

    def _reject(self, now: float, kind: str, message: str) -> None:
        self.rejected += 1
        self.last_error = message
        self._record(now, kind, message)

    def ingest(self, data: bytes, now: float) -> int:
        """Apply one datagram received at `now` (receiver clock, s); returns how many states it updated."""
        try:
            parsed = _decode(bytes(data))
        except _RejectedError as rej:
            with self._lock:
                self.datagrams += 1
                self._reject(now, rej.kind, str(rej))
                self._arrived.notify_all()
            return 0
        n = 0
        with self._lock:
            self.datagrams += 1
            for oid, c, r, ts in parsed:
                self.received += 1
                n += self._apply(oid, c, r, ts, now)
            self.accepted += n
            self._arrived.notify_all()
        return n

    def _apply(self, oid: str, c: np.ndarray, r: float, ts: float, now: float) -> int:
        """Update track `oid` with one message (lock held); 1 when used, 0 when rejected."""
        o = self.options
        if self.expected is not None and oid not in self.expected:
            known = ", ".join(self.expected)
            self._reject(now, "unknown_id", f"message.id: unknown obstacle {oid[:40]!r} (expected: {known})")
            return 0
        tr = self._tracks.get(oid)
        if tr is None and self.expected is None and len(self._tracks) >= MAX_TRACKS:
            self._reject(now, "too_many_ids", f"message.id: {oid[:40]!r} would exceed {MAX_TRACKS} obstacles")
            return 0
        silent = tr is not None and now - tr.received > self.max_age
        if silent and (ts <= tr.timestamp or abs(ts + tr.offset - now) > o.max_skew):
            # silent for longer than max_age: a restarted sender or a jumped clock starts afresh
            self._record(now, "resync", f"obstacle {oid}: timestamps restarted after {now - tr.received:.3g} s")
            tr = None
        if tr is None:
            tr = _Track(c, r, ts, now, now - ts)
            tr.hist.append((ts, c, r))
            self._tracks[oid] = tr
            return 1
        if ts <= tr.timestamp:
            self.out_of_order += 1
            self._reject(now, "out_of_order", f"obstacle {oid}: timestamp {ts:.6g} s not after {tr.timestamp:.6g} s")
            return 0
        mapped = ts + tr.offset  # the sender time on the receiver's clock
        if abs(mapped - now) > o.max_skew:
            self._reject(
                now,
                "timestamp",
                f"obstacle {oid}: timestamp {ts:.6g} s maps {mapped - now:+.3g} s from its arrival "
                f"(window +-{o.max_skew:g} s)",
            )
            return 0
        tr.offset = min(tr.offset, now - ts)
        tr.center, tr.radius, tr.timestamp, tr.received = c, r, ts, now
        # keep samples spread over the window: close successors replace the newest sample
        h = tr.hist
        gap = o.velocity_window / _HISTORY
        if len(h) >= 2 and ts - h[-2][0] < gap:
            h[-1] = (ts, c, r)
        else:
            h.append((ts, c, r))
        while len(h) > 2 and ts - h[0][0] > o.velocity_window:
            h.popleft()
        self._refit(oid, tr, now)
        return 1

    def _refit(self, oid: str, tr: _Track, now: float) -> None:
        o = self.options
        v, rr = _fit(tr.hist, o.min_span)
        speed = float(np.linalg.norm(v))
        if speed > o.max_speed or abs(rr) > o.max_speed:
            self._record(
                now,
                "speed_clamped",
                f"obstacle {oid}: estimated speed {speed:.4g} mm/s / radius rate {rr:.4g} mm/s "
                f"clamped to {o.max_speed:g} mm/s",
            )
            if speed > o.max_speed:
                v = v * (o.max_speed / speed)
            rr = float(np.clip(rr, -o.max_speed, o.max_speed))
        tr.velocity, tr.radius_rate = v, rr

    def wait_for(self, datagrams: int, timeout: float = 30.0) -> bool:
        """Block until at least `datagrams` datagrams have been handled (True), or `timeout`
        wall-clock seconds pass (False; a guard against hangs, not a timing window)."""
        with self._arrived:
            return self._arrived.wait_for(lambda: self.datagrams >= datagrams, timeout)

    # ---------------------------------------------------------------- output
    def events(self, start: int = 0) -> list[FeedEvent]:
        """The recorded events from index `start` on (at most `MAX_EVENTS` are kept)."""
        with self._lock:
            return self._events[start:]

    def describe(self) -> dict[str, Any]:
        """Counters, options and the recorded events, as plain data for a run's result."""
        with self._lock:
            return {
                "max_age_s": self.max_age,
                "options": self.options.to_dict(),
                "max_datagram_bytes": MAX_DATAGRAM_BYTES,
                "datagrams": self.datagrams,
                "messages": self.received,
                "accepted": self.accepted,
                "rejected": self.rejected,
                "counts": dict(sorted(self.counts.items())),
                "events_dropped": self.events_dropped,
                "events": [e.to_dict() for e in self._events],
            }

    def latest(self, now: float | None = None) -> FeedState:
        """The newest state of every obstacle, flagged stale when any is too old or missing."""
        now = self.clock() if now is None else now
        with self._lock:
            ids = tuple(sorted(self._tracks))
            tr = [self._tracks[i] for i in ids]
            centers = np.array([t.center for t in tr]).reshape(-1, 3)
            radii = np.array([t.radius for t in tr])
            vel = np.array([t.velocity for t in tr]).reshape(-1, 3)
            rates = np.array([t.radius_rate for t in tr])
            stamps = np.array([t.timestamp for t in tr])
            ages = np.array([max(now - t.measured, 0.0) for t in tr])
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
        growth = np.maximum(np.maximum(rates, np.linalg.norm(vel, axis=1)), 0.0)
        return FeedState(ids, centers, radii, vel, rates, stamps, ages, age, bool(reason), reason, growth)

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
        ObstacleFeed.send_raw(address, json.dumps(list(states), allow_nan=False).encode("utf-8"), sock)

    @staticmethod
    def send_raw(address: tuple[str, int], data: bytes, sock: socket.socket | None = None) -> None:
        """Send one datagram of raw bytes (tests use it to send hostile ones)."""
        own = sock is None
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if own else sock
        try:
            s.sendto(data, address)
        finally:
            if own:
                s.close()
