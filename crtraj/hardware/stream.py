"""Hardware streamer: fixed-rate, time-stamped actuator set-points with limits, watchdog and e-stop.

`Streamer` sends one frame every 1/rate s (default 100 Hz) over a
`Transport` (UDP, serial or a dry-run file) and reads the device's telemetry.
Set-points come either from a whole admitted motion (`run_path`: only what
`crtraj.hardware.admission.admit` let through) or,
one control step at a time, from a replanner (`start`, `send_setpoint`,
`finish`, `close`); between buffered set-points the stream interpolates
linearly at the stream rate.

The actuator limits are enforced in one place, `_emit`: every frame passes `LimitsGate` before
it reaches the transport. A refused set-point is reported, never clamped,
and the stream latches a hold. The watchdog latches a hold when the source
has no set-point for the current time for longer than ``watchdog`` (default
100 ms), or when telemetry stops for that long. `estop` sends an emergency
stop at once. Any transport error stops the stream and is reported.

Every run opens its own session (a random number, see docs/protocol.md), so
frames of an earlier run or a forged high sequence number cannot lock it
out. While the device should be moving, the streamer also checks that its
acknowledgements advance (every set-point acknowledged within
``ack_timeout``) and that its measured positions follow the acknowledged
set-point within ``following_tolerance``; either failure latches a hold at
once, with status ``ack-stalled`` or ``following-error`` and the reason.

Every run is recorded as JSON lines (header, each frame sent, each telemetry
frame received, events, final report), flushed line by line so a crash loses
at most the line being written. Times in s, values in actuator units (rad
for servos, mm for the z stage).
"""

from __future__ import annotations

import bisect
import contextlib
import json
import math
import os
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from crtraj import __version__
from crtraj.core.errors import AdmissionError, InputError
from crtraj.core.fileio import to_jsonable
from crtraj.core.options import Options, option
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion
from crtraj.hardware.dynamixel import open_dynamixel
from crtraj.hardware.limits import LimitsGate, Violation
from crtraj.hardware.protocol import (
    ESTOP,
    HOLD,
    KIND_NAMES,
    MOVE,
    SEQ_MOD,
    STATUS_ESTOP,
    Frame,
    FrameError,
    Telemetry,
    seq_after,
    seq_next,
)
from crtraj.hardware.setpoints import SetpointPath
from crtraj.hardware.transport import Transport, TransportError

# (admitted motion, the device's actuator values) -> the motion's path with an approach ending at its first time;
# raises AdmissionError when no safe approach exists. The app layer injects a planner (crtraj.app.approach).
ApproachPlanner = Callable[[AdmittedMotion, np.ndarray], SetpointPath]

# States. Terminal: done, estop, error, closed. Latched (hold frames until resume/close): held.
IDLE, WAITING, STREAMING, SETTLING, HELD, DONE, ESTOPPED, ERROR, CLOSED = (
    "idle",
    "waiting",
    "streaming",
    "settling",
    "held",
    "done",
    "estop",
    "error",
    "closed",
)
_TERMINAL = (DONE, ESTOPPED, ERROR, CLOSED)
_CHECKED = (WAITING, STREAMING, SETTLING)  # states in which the device must follow
_MAX_UNACKED = 1 << 16


def open_link(target: str, actuators: Actuators) -> Transport:
    """The link to `target` (`Transport.open`); a ``dynamixel://`` bus needs the actuators (ids, tick scales)."""
    if target.startswith("dynamixel://"):
        return open_dynamixel(target, actuators)
    return Transport.open(target)


class StreamError(RuntimeError):
    """The stream cannot go on (no device, terminal state, held); the message says why."""


@dataclass(frozen=True)
class StreamOptions(Options):
    """The ``[stream]`` section. rate: set-points per second (Hz). watchdog: longest
    source underrun or telemetry silence before a latched hold (s).
    connect_timeout: wait for the device's first telemetry (s). prebuffer:
    buffered set-point span (s) before a live source starts moving.
    settle_tolerance: largest |measured - final| per actuator that counts as
    arrived (rad or mm); settle_timeout: how long to wait for it (s).
    ack_timeout: longest time a set-point may stay unacknowledged while
    telemetry arrives (s). following_tolerance: largest |measured -
    acknowledged set-point| per actuator while moving (rad or mm; the
    simulated device at its limits lags up to ~3.1 mm behind a z ramp: v^2 / (2 a) + tau v + one period).
    fsync: also fsync the run log after every line (survives power loss,
    slower)."""

    SECTION: ClassVar[str] = "stream"

    rate: float = option(100.0, gt=0.0, le=10000.0)
    watchdog: float = option(0.1, gt=0.0)
    connect_timeout: float = option(1.0, gt=0.0)
    prebuffer: float = option(0.1, ge=0.0)
    settle_tolerance: float = option(0.01, gt=0.0)
    settle_timeout: float = option(2.0, gt=0.0)
    ack_timeout: float = option(0.25, gt=0.0)
    following_tolerance: float = option(5.0, gt=0.0)
    fsync: bool = option(False)

    @property
    def dt(self) -> float:
        """Period between set-points (s)."""
        return 1.0 / self.rate


@dataclass(frozen=True)
class StreamReport:
    """Outcome of a run. status: done | held | estop | error | refused | closed | stalled |
    telemetry-lost | ack-stalled | following-error | not-settled | interrupted."""

    status: str
    message: str
    frames: int
    moves: int
    holds: int
    estops: int
    telemetry: int
    telemetry_errors: int
    device: dict[str, int] = field(default_factory=dict)
    final_error: float | None = None  # max |measured - last commanded| at the end (rad or mm)
    duration: float = 0.0  # s, wall time
    late_ticks: int = 0  # ticks started more than one period late
    max_lateness: float = 0.0  # s
    log: str | None = None
    events: tuple[tuple[float, str, str], ...] = ()

    @property
    def ok(self) -> bool:
        return self.status == DONE

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["ok"] = self.ok
        return d


class _RunLog:
    """JSON-lines record of a run, flushed after every line."""

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
        if self._fh is not None:
            self._fh.close()
            self._fh = None


class _VirtualClock:
    """Time that advances only when slept: a dry run streams as fast as the CPU allows."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.now += max(s, 0.0)


class Streamer:
    """Streams actuator set-points to a device at a fixed rate, within the actuator limits.

    transport: the link (`Transport.open(url)`); actuators: limits and the
    cable/servo conversion (bound to the robot with `Actuators.for_robot`
    when set-points are given as actuation q); log: JSON-lines run record
    path (None: no record). realtime: pace `run_path` by the wall clock
    (default: only when the transport has telemetry, so a dry run is instant).
    clock, sleep: time source (s) and its sleep (tests inject a virtual clock).
    session: this run's session number (default: random, non-zero); first_seq:
    the PING's sequence number (set-points follow from first_seq + 1, wrapping).
    """

    def __init__(
        self,
        transport: Transport,
        actuators: Actuators,
        options: StreamOptions | None = None,
        log: str | Path | None = None,
        *,
        realtime: bool | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        session: int | None = None,
        first_seq: int = 0,
    ) -> None:
        if session is not None and not 0 < session < SEQ_MOD:
            raise ValueError(f"session must be in 1..{SEQ_MOD - 1}, got {session}")
        if not 0 <= first_seq < SEQ_MOD:
            raise ValueError(f"first_seq must be in 0..{SEQ_MOD - 1}, got {first_seq}")
        self.session = secrets.randbelow(SEQ_MOD - 1) + 1 if session is None else int(session)
        self.transport = transport
        self.actuators = actuators
        self.options = options or StreamOptions()
        self._dt = self.options.dt
        self._realtime = transport.has_telemetry if realtime is None else realtime
        self._clock, self._sleep = clock, sleep
        self._log = _RunLog(log, self.options.fsync)
        self._gate = LimitsGate(actuators, self._dt)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._state = IDLE
        self._reason = ""
        self._status_override: str | None = None
        self._seq = first_seq
        self._first_seq = first_seq
        # set-points not yet acknowledged: (seq, send time, values); the last acknowledged one
        self._unacked: deque[tuple[int, float, np.ndarray]] = deque()
        self._ack = first_seq
        self._acked_values: np.ndarray | None = None
        self._limited_base: int | None = None
        self._counts = {"frames": 0, MOVE: 0, HOLD: 0, ESTOP: 0, "telemetry": 0, "telemetry_errors": 0}
        self._bt: list[float] = []
        self._bv: list[np.ndarray] = []
        self._finished = False
        self._tau0 = 0.0
        self._k = 0
        self._tau = 0.0
        self._underrun_since: float | None = None
        self._latched_at: float | None = None
        self._settle_since: float | None = None
        self._final_sent = False
        self._final_error: float | None = None
        self._last_move_seq = first_seq
        self._last_tel: Telemetry | None = None
        self._last_tel_time = 0.0
        self._refused_base: int | None = None
        self._t_start = 0.0
        self._late = 0
        self._max_late = 0.0
        self._events: list[tuple[float, str, str]] = []
        self._report: StreamReport | None = None

    # ---------------------------------------------------------- construction
    @classmethod
    def open(
        cls,
        target: str,
        actuators: Actuators,
        options: StreamOptions | None = None,
        log: str | Path | None = None,
        **kw: Any,
    ) -> Streamer:
        """Open ``udp://HOST:PORT``, ``serial://DEV?baud=N``, ``file://PATH`` or ``dynamixel://DEV?baud=N``
        (the servos of ``actuators.bus``, `crtraj.hardware.dynamixel`) and wrap it."""
        return cls(open_link(target, actuators), actuators, options, log, **kw)

    def __enter__(self) -> Streamer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------ inspection
    @property
    def state(self) -> str:
        return self._state

    @property
    def reason(self) -> str:
        """Why the stream is held or stopped ('' while running normally)."""
        return self._reason

    @property
    def position(self) -> np.ndarray | None:
        """Last commanded actuator values (rad, mm): where a new set-point sequence must start."""
        with self._lock:
            return self._gate.position

    @property
    def telemetry(self) -> Telemetry | None:
        """The last valid telemetry frame."""
        return self._last_tel

    # ---------------------------------------------------------------- start
    def start(self, initial: np.ndarray | None = None, *, background: bool = True) -> None:
        """Connect: wait for the device's first telemetry (its positions are the start),
        then run the fixed-rate loop in a background thread (``background=False``: caller runs it).

        initial: start positions (actuator values) for links without telemetry.
        """
        if self._state != IDLE:
            raise StreamError(f"start: streamer is already {self._state}")
        self._t_start = self._clock()
        self._log.write(
            {
                "type": "header",
                "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                "crtraj_version": __version__,
                "transport": self.transport.description,
                "session": self.session,
                "options": self.options.to_dict(),
                "actuators": self.actuators.to_dict(),
                "names": list(self.actuators.names),
                "units": list(self.actuators.units),
            }
        )
        if self.transport.has_telemetry:
            tel = self._handshake()
            initial = tel.positions
        elif initial is None:
            raise StreamError("start: this link has no telemetry; pass the initial actuator positions")
        init = np.asarray(initial, dtype=float)
        if init.shape != (self.actuators.n,):
            raise StreamError(f"start: device reports {init.size} actuators, the robot has {self.actuators.n}")
        v = self._gate.reset(init)
        if v is not None:
            self._state = ERROR
            self._reason = f"device start position refused: {v.message()}"
            self._event("refused", self._reason)
            raise StreamError(self._reason)
        self._state = WAITING
        self._event("start", f"{self.transport.description} at {self.options.rate:g} Hz")
        if background:
            self._thread = threading.Thread(target=self._run_loop, name="crtraj-streamer", daemon=True)
            self._thread.start()

    def _handshake(self) -> Telemetry:
        """PING until the first telemetry arrives. A PING carries no values and commands nothing,
        so it bypasses the limits gate; every set-point frame goes through `_emit`."""
        deadline = self._clock() + self.options.connect_timeout
        next_ping = self._clock()
        while True:
            try:
                if self._clock() >= next_ping:
                    self.transport.send(Frame.ping(self.session, self._first_seq, self._dt).encode())
                    wall = self._clock() - self._t_start
                    self._log.write({"type": "tx", "wall": wall, "seq": self._first_seq, "kind": "ping"})
                    next_ping += 0.05
                self._poll_telemetry(self._clock())
            except TransportError as exc:
                self._state = ERROR
                self._reason = f"transport error: {exc}"
                self._event("transport-error", str(exc))
                raise StreamError(f"{self._reason} (is the device running?)") from None
            if self._last_tel is not None:
                return self._last_tel
            if self._clock() > deadline:
                self._state = ERROR
                self._reason = (
                    f"no telemetry from {self.transport.description} within {self.options.connect_timeout:g} s"
                )
                self._event("no-telemetry", self._reason)
                raise StreamError(self._reason + " (is the device running?)")
            self._sleep(0.005)

    # -------------------------------------------------------------- sources
    def send_setpoint(self, t: float, q: Any) -> None:
        """Queue the set-point for trajectory time t (s): robot actuation q (nq,) in mm.

        Times must increase. Raises `InputError` for bad input and
        `StreamError` when the stream is held or stopped (see `reason`).
        """
        self.send_values(t, self.actuators.command(np.asarray(q, dtype=float).reshape(-1), "q"))

    def send_values(self, t: float, values: Any) -> None:
        """Queue actuator values (rad, mm) for trajectory time t (s)."""
        tt = float(t)
        if not math.isfinite(tt):
            raise InputError(f"t: must be finite, got {t}")
        v = np.asarray(values, dtype=float)
        if v.shape != (self.actuators.n,):
            raise InputError(f"values: expected {self.actuators.n} ({', '.join(self.actuators.names)}), got {v.shape}")
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise InputError(f"{self.actuators.names[int(bad[0])]}: must be finite, got {v[bad[0]]}")
        with self._lock:
            self._check_accepting()
            if self._bt and not tt > self._bt[-1]:
                raise InputError(f"t: set-point times must increase (got {tt:g} s after {self._bt[-1]:g} s)")
            self._bt.append(tt)
            self._bv.append(v)

    def send_path(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """Queue many set-points at once (stamps (M,) s, values (M, n))."""
        stamps = np.asarray(stamps, dtype=float)
        values = np.asarray(values, dtype=float)
        if values.ndim != 2 or values.shape != (stamps.size, self.actuators.n):
            raise InputError(f"values: expected shape ({stamps.size}, {self.actuators.n}), got {values.shape}")
        if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(values))):
            raise InputError("set-points: contain NaN or infinity")
        if stamps.size > 1 and not np.all(np.diff(stamps) > 0):
            k = int(np.flatnonzero(~(np.diff(stamps) > 0))[0]) + 1
            raise InputError(f"t[{k}]: set-point times must increase (got {stamps[k]:g} s after {stamps[k - 1]:g} s)")
        with self._lock:
            self._check_accepting()
            if self._bt and stamps.size and not stamps[0] > self._bt[-1]:
                raise InputError(f"t: set-point times must increase (got {stamps[0]:g} s after {self._bt[-1]:g} s)")
            self._bt.extend(stamps.tolist())
            self._bv.extend(values)

    def _check_accepting(self) -> None:
        if self._state == IDLE:
            raise StreamError("streamer not started: call start() first")
        if self._finished:
            raise StreamError("finish() was called: no more set-points")
        if self._state == HELD:
            raise StreamError(f"stream is held ({self._reason}); call resume() to continue from `position`")
        if self._state in _TERMINAL:
            raise StreamError(f"stream is {self._state}: {self._reason}")

    def finish(self) -> None:
        """No more set-points: stream to the last one, hold there and wait for the device to settle."""
        with self._lock:
            self._finished = True

    # -------------------------------------------------------------- control
    def hold(self, reason: str = "hold requested") -> None:
        """Latch a hold at the last commanded positions (until `resume`)."""
        with self._lock:
            if self._state not in _TERMINAL and self._state != IDLE:
                self._latch(reason, self._clock())

    def resume(self) -> None:
        """Leave a latched hold. Buffered set-points are discarded; new ones must
        start at `position` (at rest), as after `start`."""
        with self._lock:
            if self._state != HELD:
                raise StreamError(f"resume: stream is {self._state}, not held")
            self._bt.clear()
            self._bv.clear()
            self._finished = False
            self._underrun_since = None
            self._latched_at = None
            self._status_override = None
            self._reason = ""
            self._gate.reset(self._gate.position)
            self._state = WAITING
            self._event("resume", "")

    def estop(self, reason: str = "e-stop requested") -> None:
        """Emergency stop: send ESTOP now and on every tick until closed. Terminal."""
        with self._lock:
            if self._state in (IDLE, CLOSED, ERROR) or self._state == ESTOPPED:
                return
            self._state = ESTOPPED
            self._reason = reason
            self._latched_at = self._clock()
            self._event("estop", reason)
            try:
                self._send_hold(ESTOP)
            except TransportError as exc:
                self._event("transport-error", str(exc))

    # ------------------------------------------------------------ whole path
    # Over 60 lines by its docstring and its refusals written out; the body is: check, connect, frames, send.
    def run_path(
        self,
        motion: AdmittedMotion,
        *,
        approach: bool = False,
        initial: np.ndarray | None = None,
        plan_approach: ApproachPlanner | None = None,
    ) -> StreamReport:
        """Stream a whole admitted motion in the calling thread and close; returns the report.

        motion: made by `crtraj.hardware.admission.admit` for this streamer's
        actuators and rate; anything else raises `AdmissionError` before
        anything is sent. Its verified frames are sent exactly; they must start
        where the device is (status ``refused`` with the reason otherwise).
        approach: first move from the device's position to the motion's start,
        ending at the motion's first time: `plan_approach(motion, here)` gives
        it (a `SetpointPath`, the motion's path with an approach; the app layer
        injects a planner, `crtraj.app.approach`), by default the straight
        move in actuator space (`SetpointPath.with_approach`). Either way the
        approach's frames pass the motion's `FrameVerifier` (body, D_sf,
        limits, against the motion's scene at their times) before the first
        frame leaves; `plan_approach` raising `AdmissionError` (no safe
        approach) or a failed check ends the run with status ``refused`` and
        nothing sent.
        """
        if not isinstance(motion, AdmittedMotion):
            raise AdmissionError(
                f"run_path: streams only a motion admitted by crtraj.hardware.admission.admit, "
                f"got {type(motion).__name__}"
            )
        if not motion.admitted_for(self.actuators):
            raise AdmissionError("run_path: the motion was admitted for other actuators than this streamer's")
        if motion.rate != self.options.rate:
            raise AdmissionError(
                f"run_path: the motion was verified at {motion.rate:g} Hz, this streamer sends at "
                f"{self.options.rate:g} Hz; admit it with rate={self.options.rate:g}"
            )
        if not self._realtime:
            vc = _VirtualClock()
            self._clock, self._sleep = vc, vc.sleep
        if initial is None and not self.transport.has_telemetry:
            if approach:
                raise StreamError("--approach needs a device with telemetry (its position is the approach start)")
            initial = motion.values[0]
        try:
            self.start(initial, background=False)
        except StreamError as exc:
            return self.close(status=ERROR if self._state == ERROR else None, message=str(exc))
        here = self._gate.position
        stamps, values = motion.stamps, motion.values
        if approach:
            try:
                stamps, values = self._approach_frames(motion, here, plan_approach)
            except AdmissionError as exc:
                msg = f"refused before sending: {exc}"
                self._event("refused", msg)
                return self.close(status="refused", message=msg)
        v = self._gate.check_path(values, stamps, start=here)
        if v is not None:
            msg = self._refusal_text(v, values, here)
            self._event("refused", msg)
            return self.close(status="refused", message=msg)
        self.send_path(stamps, values)
        self.finish()
        try:
            self.run()
        except KeyboardInterrupt:
            with self._lock:
                self._latch("interrupted (Ctrl-C)", self._clock())
                self._tick(self._clock())
            return self.close(status="interrupted", message="interrupted (Ctrl-C): hold commanded")
        return self.close()

    def _approach_frames(
        self, motion: AdmittedMotion, here: np.ndarray, plan_approach: ApproachPlanner | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The approach's frames, verified, followed by the motion's verified frames (`AdmissionError` if unsafe)."""
        if plan_approach is not None:
            path = plan_approach(motion, here)
        else:
            path = motion.path.with_approach(here, self.actuators)
        rate = self.options.rate
        stamps, values = path.sample(rate)
        na = path.approach_frames(rate)
        # the motion's own frames are the verified ones, on the same grid: sampling with an approach must give
        # them back bit for bit, or what is sent would not be what was verified
        if len(stamps) - na != len(motion.stamps) or not (
            np.array_equal(stamps[na:], motion.stamps) and np.array_equal(values[na:], motion.values)
        ):
            raise AdmissionError("approach: the approach changed the motion's verified set-points")
        if motion.verifier is None:
            raise AdmissionError("approach: the motion carries no verifier")
        # the approach and its join into the motion: body and limits from the device's position at rest
        why = motion.verifier.failure(stamps[: na + 1], values[: na + 1], start=here)
        if why is not None:
            raise AdmissionError(f"approach: {why}")
        return np.concatenate([stamps[:na], motion.stamps]), np.concatenate([values[:na], motion.values])

    def _refusal_text(self, v: Violation, values: np.ndarray, here: np.ndarray) -> str:
        msg = f"refused before sending: {v.message()}"
        d = np.abs(values[0] - here)
        if v.quantity in ("velocity", "acceleration") and np.any(d > self.actuators.amax * self._dt**2 * (1 + 1e-9)):
            i = int(np.argmax(d / self.actuators.amax))
            msg += (
                f"; the path starts {d[i]:.4g} {self.actuators.units[i]} ({self.actuators.names[i]}) away from "
                "the device's position: move there first (--approach)"
            )
        return msg

    # ----------------------------------------------------------------- loop
    def run(self) -> None:
        """Run the fixed-rate loop in the calling thread (after ``start(background=False)``) until
        the stream is done, stopped, or has held for one watchdog period after a fault."""
        if self._thread is not None:
            raise StreamError("run: the loop already runs in the background")
        self._run_loop(stop_when_latched=True)

    def _run_loop(self, stop_when_latched: bool = False) -> None:
        dt = self._dt
        nxt = self._clock()
        while not self._stop.is_set():
            now = self._clock()
            late = now - nxt
            if late > dt:
                self._late += 1
            self._max_late = max(self._max_late, late)
            with self._lock:
                self._tick(now)
                state, latched_at = self._state, self._latched_at
            # hold / e-stop frames repeat for one watchdog period so a lossy link delivers them
            repeated = latched_at is not None and now - latched_at >= self.options.watchdog
            if state == ESTOPPED and repeated:
                return
            if state in _TERMINAL and state != ESTOPPED:
                return
            if stop_when_latched and state == HELD and repeated:
                return
            nxt += dt
            delay = nxt - self._clock()
            if delay > 0:
                self._sleep(delay)
            elif -delay > 5 * dt:
                nxt = self._clock()  # far behind (machine stalled): resynchronise rather than burst

    def _tick(self, now: float) -> None:
        """One period: read telemetry, run the watchdogs, send one frame. Caller holds the lock."""
        if self._state in (DONE, ERROR, CLOSED, IDLE):
            return
        try:
            self._poll_telemetry(now)
            if self._state == ESTOPPED:
                self._send_hold(ESTOP)
                return
            if self._state not in (HELD, DONE) and self.transport.has_telemetry:
                silent = now - self._last_tel_time
                if silent > self.options.watchdog:
                    self._latch(f"telemetry lost: nothing valid for {silent * 1000:.0f} ms", now, "telemetry-lost")
            if self._state == HELD:
                self._send_hold(HOLD)
            elif self._state == WAITING:
                self._tick_waiting(now)
            elif self._state == STREAMING:
                self._tick_streaming(now)
            elif self._state == SETTLING:
                self._tick_settling(now)
        except TransportError as exc:
            self._state = ERROR
            self._reason = f"transport error: {exc}"
            self._event("transport-error", str(exc))

    def _tick_waiting(self, now: float) -> None:
        ready = bool(self._bt) and (self._finished or self._bt[-1] - self._bt[0] >= self.options.prebuffer)
        if not ready:
            self._send_hold(HOLD)
            return
        self._tau0 = self._bt[0]
        self._tau = self._tau0
        self._k = 0
        self._final_sent = False
        self._underrun_since = None
        self._state = STREAMING
        self._event("streaming", f"from t={self._tau0:g} s")
        self._tick_streaming(now)

    def _tick_streaming(self, now: float) -> None:
        tau = self._tau0 + self._k * self._dt
        last = self._bt[-1]
        final = False
        if tau < last - 1e-9:
            values, stamp = self._interpolate(tau), tau
        elif self._finished:
            if self._final_sent:
                self._state = SETTLING
                self._settle_since = now
                self._event("settling", f"final set-point at t={last:g} s")
                self._tick_settling(now)
                return
            values, stamp, final = self._bv[-1], last, True  # the final set-point, maybe off the rate grid
        elif tau <= last + 1e-9:
            values, stamp = self._bv[-1], tau
        else:
            if self._underrun_since is None:
                self._underrun_since = now
                self._event("underrun", f"no set-point for t={tau:g} s yet: holding", now)
            if now - self._underrun_since > self.options.watchdog:
                self._latch(
                    f"source stalled: no set-point for t={tau:g} s within {self.options.watchdog * 1000:.0f} ms",
                    now,
                    "stalled",
                )
            self._send_hold(HOLD)
            return
        self._underrun_since = None
        if self._emit(MOVE, values, stamp):
            self._tau = stamp
            self._k += 1
            self._final_sent = final

    def _tick_settling(self, now: float) -> None:
        self._send_hold(HOLD)
        tel = self._last_tel
        if not self.transport.has_telemetry:
            self._finish_ok(None)
            return
        if tel is not None and not seq_after(self._last_move_seq, tel.ack):
            err = float(np.max(np.abs(tel.positions - self._gate.position)))
            if err <= self.options.settle_tolerance:
                self._finish_ok(err)
                return
        if now - (self._settle_since or now) > self.options.settle_timeout:
            err = None if tel is None else float(np.max(np.abs(tel.positions - self._gate.position)))
            self._state = ERROR
            self._status_override = "not-settled"
            self._reason = (
                f"device did not reach the final set-point within {self.options.settle_timeout:g} s "
                f"(error {err if err is None else f'{err:.4g}'})"
            )
            self._event("not-settled", self._reason)

    def _finish_ok(self, err: float | None) -> None:
        self._state = DONE
        self._final_error = err
        self._event("done", "" if err is None else f"final error {err:.3g}")

    def _interpolate(self, tau: float) -> np.ndarray:
        j = bisect.bisect_right(self._bt, tau)
        if j <= 0:
            return self._bv[0]
        if j >= len(self._bt):
            return self._bv[-1]
        t0, t1 = self._bt[j - 1], self._bt[j]
        # a stamp on the set-points' own grid (up to rounding: tau0 + k dt vs t0 + (k - n) dt) sends that
        # set-point exactly, so what leaves is bit for bit what was verified
        eps = 1e-9 * max(1.0, abs(tau))
        if tau - t0 <= eps:
            out = self._bv[j - 1]
        elif t1 - tau <= eps:
            out = self._bv[j]
        else:
            w = (tau - t0) / (t1 - t0)
            out = (1 - w) * self._bv[j - 1] + w * self._bv[j]
        if j > 4096:  # drop consumed set-points of long live streams
            del self._bt[: j - 2]
            del self._bv[: j - 2]
        return out

    # -------------------------------------------------------------- sending
    def _send_hold(self, kind: int) -> None:
        p = self._gate.position
        if p is not None:
            self._emit(kind, p, self._tau)

    def _emit(self, kind: int, values: np.ndarray, stamp: float) -> bool:
        """The only way a frame leaves: gate check, encode, send, record. False if refused."""
        values = np.asarray(values, dtype=float)
        v = self._gate.check(kind, values, stamp)
        if v is not None:
            if kind == MOVE:
                self._latch(f"set-point refused: {v.message()}", self._clock(), "refused")
                self._send_hold(HOLD)
            else:  # cannot happen: hold values are the gate's own position
                self._state = ERROR
                self._reason = f"internal: {KIND_NAMES[kind]} frame refused: {v.message()}"
                self._event("error", self._reason)
            return False
        frame = Frame(kind, seq_next(self._seq), stamp, values, self.session)
        self.transport.send(frame.encode())
        self._seq = frame.seq
        if kind == MOVE:
            self._last_move_seq = self._seq
        if self.transport.has_telemetry:
            self._unacked.append((frame.seq, self._clock(), values))
            if len(self._unacked) > _MAX_UNACKED:  # a dead link while held: keep the newest only
                self._unacked.popleft()
        self._gate.commit(kind, values)
        self._counts["frames"] += 1
        self._counts[kind] += 1
        self._log.write(
            {
                "type": "tx",
                "wall": self._clock() - self._t_start,
                "seq": frame.seq,
                "kind": KIND_NAMES[kind],
                "stamp": stamp,
                "values": values,
            }
        )
        return True

    def _latch(self, reason: str, now: float, status: str = "held") -> None:
        if self._state in (HELD, *_TERMINAL):
            return
        self._state = HELD
        self._reason = reason
        self._latched_at = now
        self._status_override = None if status == "held" else status
        self._event(status, reason, now)

    # ------------------------------------------------------------- telemetry
    def _poll_telemetry(self, now: float) -> None:
        if not self.transport.has_telemetry:
            return
        newest: Telemetry | None = None
        for data in self.transport.receive():
            try:
                msg = Frame.decode(data)
            except FrameError as exc:
                self._counts["telemetry_errors"] += 1
                self._log.write({"type": "rx-bad", "wall": now - self._t_start, "error": str(exc)})
                continue
            if not isinstance(msg, Telemetry):
                self._counts["telemetry_errors"] += 1
                self._log.write({"type": "rx-bad", "wall": now - self._t_start, "error": "not a telemetry frame"})
                continue
            if msg.session != self.session:
                self._counts["telemetry_errors"] += 1
                self._log.write(
                    {"type": "rx-bad", "wall": now - self._t_start, "error": f"telemetry of session {msg.session}"}
                )
                continue
            if self._last_tel is not None and not seq_after(msg.seq, self._last_tel.seq):
                continue  # reordered or duplicated: keep the newest
            if msg.positions.size != self.actuators.n:
                self._counts["telemetry_errors"] += 1
                self._log.write(
                    {"type": "rx-bad", "wall": now - self._t_start, "error": f"{msg.positions.size} positions"}
                )
                continue
            self._last_tel = msg
            self._last_tel_time = now
            self._counts["telemetry"] += 1
            self._log.write(
                {
                    "type": "rx",
                    "wall": now - self._t_start,
                    "seq": msg.seq,
                    "stamp": msg.stamp,
                    "ack": msg.ack,
                    "status": msg.status,
                    "counters": msg.counters(),
                    "positions": msg.positions,
                }
            )
            if self._refused_base is None:
                self._refused_base = msg.refused
            if self._limited_base is None:
                self._limited_base = msg.limited
            self._take_ack(msg.ack)
            if self._state in (WAITING, STREAMING, SETTLING, HELD):
                if msg.status & STATUS_ESTOP:
                    self._state = ESTOPPED
                    self._reason = "device reports an e-stop"
                    self._latched_at = now
                    self._event("estop", self._reason)
                elif msg.refused > self._refused_base:
                    self._refused_base = msg.refused
                    self._latch(
                        "device refused a set-point (its limits are stricter than the robot file's)", now, "refused"
                    )
            if msg.limited > self._limited_base:
                # the device's servo limited a step (it still follows, slower): the following-error
                # check decides whether that matters
                self._event("device-limited", f"device flagged {msg.limited - self._limited_base} set-point(s)")
                self._limited_base = msg.limited
            if self._state in _CHECKED:
                self._check_following(msg)
            newest = msg
        # after the whole batch: telemetry that queued up while this thread was starved must not
        # make frames it sent just before the stall look unacknowledged
        if newest is not None and self._state in _CHECKED:
            self._check_acks(newest, now)

    def _take_ack(self, ack: int) -> None:
        """Drop the set-points the device acknowledged; remember the values of the acknowledged one."""
        if seq_after(ack, self._seq) or not seq_after(ack, self._ack):
            return  # not one we sent, or no news
        self._ack = ack
        while self._unacked and not seq_after(self._unacked[0][0], ack):
            seq, _, values = self._unacked.popleft()
            if seq == ack:
                self._acked_values = values

    def _check_acks(self, tel: Telemetry, now: float) -> None:
        """Latch a hold when the device's acknowledgements stop advancing (it ignores our frames)."""
        if self._unacked and now - self._unacked[0][1] > self.options.ack_timeout:
            seq, sent, _ = self._unacked[0]
            self._latch(
                f"device stopped acknowledging: set-point seq {seq} unacknowledged after "
                f"{(now - sent) * 1000:.0f} ms (last ack {tel.ack}; device counts stale {tel.stale}, "
                f"other session {tel.foreign})",
                now,
                "ack-stalled",
            )

    def _check_following(self, tel: Telemetry) -> None:
        """Latch a hold when the measured positions do not follow the acknowledged set-point."""
        if self._acked_values is None:
            return
        err = np.abs(tel.positions - self._acked_values)
        i = int(np.argmax(err))
        if err[i] > self.options.following_tolerance:
            u = self.actuators.units[i]
            self._latch(
                f"following error: {self.actuators.names[i]} measured {tel.positions[i]:.4g} {u}, "
                f"commanded {self._acked_values[i]:.4g} {u} (|error| {err[i]:.4g} > following_tolerance "
                f"{self.options.following_tolerance:g})",
                self._clock(),
                "following-error",
            )

    # ---------------------------------------------------------------- close
    def _event(self, name: str, message: str, now: float | None = None) -> None:
        # `now`: the clock reading the decision behind the event used, so that the logged times are the ones the
        # rules compared (a fresh reading here would come microseconds later, and differ between two events)
        wall = (self._clock() if now is None else now) - self._t_start
        if len(self._events) < 1000:
            self._events.append((wall, name, message))
        self._log.write({"type": "event", "wall": wall, "event": name, "message": message})

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the background loop to end (done, e-stop or error); True if it ended."""
        th = self._thread
        if th is None:
            return self._state in _TERMINAL
        th.join(timeout)
        return not th.is_alive()

    def close(self, status: str | None = None, message: str | None = None) -> StreamReport:
        """Stop the loop, command a hold if still moving, close link and log; return the report."""
        if self._report is not None:
            return self._report
        self._stop.set()
        if self._thread is not None and threading.current_thread() is not self._thread:
            self._thread.join(2.0)
        with self._lock:
            if self._state in (WAITING, STREAMING, SETTLING, HELD) and self._counts["frames"]:
                try:
                    self._send_hold(HOLD)
                except TransportError as exc:
                    self._event("transport-error", str(exc))
            final = (
                status
                or self._status_override
                or ({WAITING: CLOSED, STREAMING: CLOSED, SETTLING: CLOSED, IDLE: CLOSED}.get(self._state, self._state))
            )
            msg = message or self._reason or ("completed" if self._state == DONE else "")
            tel = self._last_tel
            err = self._final_error
            if err is None and tel is not None and self._gate.position is not None and self._counts[MOVE]:
                err = float(np.max(np.abs(tel.positions - self._gate.position)))
            report = StreamReport(
                status=final,
                message=msg,
                frames=self._counts["frames"],
                moves=self._counts[MOVE],
                holds=self._counts[HOLD],
                estops=self._counts[ESTOP],
                telemetry=self._counts["telemetry"],
                telemetry_errors=self._counts["telemetry_errors"],
                device={} if tel is None else tel.counters(),
                final_error=err,
                duration=self._clock() - self._t_start if self._state != IDLE or self._counts["frames"] else 0.0,
                late_ticks=self._late,
                max_lateness=max(self._max_late, 0.0),
                log=None if self._log.path is None else str(self._log.path),
                events=tuple(self._events),
            )
            with contextlib.suppress(TransportError):
                self._log.write({"type": "report", **report.to_dict()})
            self._log.close()
            self.transport.close()
            if self._state not in (DONE, ESTOPPED, ERROR):
                self._state = CLOSED
            self._report = report
            return report
