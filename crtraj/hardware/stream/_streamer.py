"""Hardware streamer: fixed-rate, time-stamped actuator set-points with limits, watchdog and e-stop.

`Streamer` sends one frame every 1/rate s (default 100 Hz) over a
`Transport` (UDP, serial or a dry-run file) and reads the device's telemetry.
Set-points come either from a whole admitted motion (`run_path`: only what
`crtraj.hardware.admission.admit` let through) or,
one control step at a time, from a replanner (`start`, `send_setpoint`,
`finish`, `close`); between buffered set-points the stream interpolates
linearly at the stream rate.

The actuator limits are enforced in one place, `FrameSender.emit`: every frame passes `LimitsGate` before
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

`Streamer` is a facade over its parts: the queued set-points and their interpolation (`setpoint_buffer`), the
device's telemetry, acknowledgements and watchdog timers (`stream_monitor`), the states and their events
(`stream_state`), the one way frames leave (`stream_sender`), one period's work (`stream_cycle`), the fixed-rate
loop (`stream_pacing`) and the run log (`stream_log`). All of them read one injected `crtraj.core.clock.Clock`.
"""

from __future__ import annotations

import contextlib
import math
import secrets
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.clock import Clock, VirtualClock, default_clock
from crtraj.core.errors import AdmissionError, InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.admission import AdmittedMotion
from crtraj.hardware.dynamixel import open_dynamixel
from crtraj.hardware.limits import LimitsGate
from crtraj.hardware.protocol import ESTOP, HOLD, MOVE, SEQ_MOD, Telemetry
from crtraj.hardware.stream._braking import Braking
from crtraj.hardware.stream._buffer import SetpointBuffer
from crtraj.hardware.stream._cycle import StreamCycle
from crtraj.hardware.stream._log import RunLog, header_record
from crtraj.hardware.stream._monitor import StreamMonitor
from crtraj.hardware.stream._options import StreamOptions
from crtraj.hardware.stream._pacing import RatePacer
from crtraj.hardware.stream._path import ApproachPlanner, approach_frames, check_admitted, refusal_text
from crtraj.hardware.stream._sender import FrameSender, StreamParts
from crtraj.hardware.stream._state import (
    CLOSED,
    DONE,
    ERROR,
    ESTOPPED,
    HELD,
    IDLE,
    LIVE,
    TERMINAL,
    StreamError,
    StreamStateMachine,
)
from crtraj.hardware.transport import Transport, TransportError

__all__ = ["StreamReport", "Streamer", "open_link"]


def open_link(target: str, actuators: Actuators, **dynamixel: Any) -> Transport:
    """The link to `target` (`Transport.open`); a ``dynamixel://`` bus needs the actuators (ids, tick scales)
    and takes `dynamixel` as keywords of `DynamixelTransport` (e.g. ``homing``)."""
    if target.startswith("dynamixel://"):
        return open_dynamixel(target, actuators, **dynamixel)
    return Transport.open(target)


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
    duration: float = 0.0  # s, on the stream's clock (wall time unless a virtual clock was injected)
    late_ticks: int = 0  # ticks started more than one period late
    max_lateness: float = 0.0  # s
    log: str | None = None
    events: tuple[tuple[float, str, str], ...] = ()
    brakes: int = 0  # stops planned within the acceleration limits, verified and sent
    brake_frames: int = 0
    latched: int = 0  # stops that fell back to latching the last set-point (check failed, refused, closed)
    # the largest actuator speed and acceleration of every frame sent, its stops and holds included, as fractions
    # of the limits (the limits gate's finite differences; None before any frame): what the device received
    max_velocity_fraction: float | None = None
    max_acceleration_fraction: float | None = None

    @property
    def ok(self) -> bool:
        return self.status == DONE

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["ok"] = self.ok
        return d


class Streamer:
    """Streams actuator set-points to a device at a fixed rate, within the actuator limits.

    A facade over its parts: the set-point buffer (`SetpointBuffer`), the watch on the device's telemetry and
    acknowledgements (`StreamMonitor`) and the state machine (`StreamStateMachine`).

    transport: the link (`Transport.open(url)`); actuators: limits and the cable/servo conversion (bound to the robot
    with `Actuators.for_robot` when set-points are given as actuation q); log: JSON-lines run record path (None: no
    record). realtime: pace `run_path` by the clock (default: only when the transport has telemetry, so a dry run is
    instant). clock: the time source (s) that paces and times the stream (default `crtraj.core.clock.default_clock()`,
    the `WallClock`; tests inject a `VirtualClock`). session: this run's session number (default: random, non-zero);
    first_seq: the PING's sequence number (set-points follow from first_seq + 1, wrapping).
    """

    def __init__(
        self,
        transport: Transport,
        actuators: Actuators,
        options: StreamOptions | None = None,
        log: str | Path | None = None,
        *,
        realtime: bool | None = None,
        clock: Clock | None = None,
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
        self._log = RunLog(log, self.options.fsync)
        self._gate = LimitsGate(actuators, self._dt)
        self._machine = StreamStateMachine(default_clock() if clock is None else clock, self._log)
        self._buffer = SetpointBuffer(self._dt)
        self._monitor = StreamMonitor(self.session, actuators, self.options, self._log, first_seq)
        parts = StreamParts(self._machine, self._buffer, self._monitor, self._log)
        self._sender = FrameSender(transport, self._gate, self.session, first_seq, parts)
        braking = Braking(actuators, self._dt)  # plans the stop of a hold or e-stop
        self._cycle = StreamCycle(self.options, transport, self._gate, parts, self._sender, braking)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pacer = RatePacer(self._dt)
        self._report: StreamReport | None = None

    # ---------------------------------------------------------- construction
    @classmethod
    def open(
        cls,
        target: str,
        actuators: Actuators,
        options: StreamOptions | None = None,
        log: str | Path | None = None,
        *,
        link: dict[str, Any] | None = None,
        **kw: Any,
    ) -> Streamer:
        """Open ``udp://HOST:PORT``, ``serial://DEV?baud=N``, ``file://PATH`` or ``dynamixel://DEV?baud=N``
        (the servos of ``actuators.bus``, `crtraj.hardware.dynamixel._link`, with `link` as its keywords, e.g. the
        ``homing`` state file its power-up check reads) and wrap it."""
        return cls(open_link(target, actuators, **(link or {})), actuators, options, log, **kw)

    def __enter__(self) -> Streamer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def _clock(self) -> Clock:
        """The stream's one clock (the state machine's: events, pacing and timeouts read it)."""
        return self._machine.clock

    # ------------------------------------------------------------ inspection
    @property
    def state(self) -> str:
        return self._machine.state

    @property
    def reason(self) -> str:
        """Why the stream is held or stopped ('' while running normally)."""
        return self._machine.reason

    @property
    def position(self) -> np.ndarray | None:
        """Last commanded actuator values (rad, mm): where a new set-point sequence must start."""
        with self._lock:
            return self._gate.position

    @property
    def telemetry(self) -> Telemetry | None:
        """The last valid telemetry frame."""
        return self._monitor.last

    @property
    def sent_stamp(self) -> float:  # s, trajectory time: the last move frame sent, a stop's frames included
        return self._buffer.sent_stamp

    @property
    def buffer(self) -> SetpointBuffer:
        """The queued set-points (read them; queue through `send_values` / `send_path`)."""
        return self._buffer

    # ---------------------------------------------------------------- start
    def start(self, initial: np.ndarray | None = None, *, background: bool = True) -> None:
        """Connect: wait for the device's first telemetry (its positions are the start), then run the fixed-rate
        loop in a background thread (``background=False``: caller runs it). initial: start positions (actuator
        values) for links without telemetry."""
        if self.state != IDLE:
            raise StreamError(f"start: streamer is already {self.state}")
        self._machine.mark_start()
        self._log.write(header_record(self.transport.description, self.session, self.options, self.actuators))
        if self.transport.has_telemetry:
            initial = self._handshake().positions
        elif initial is None:
            raise StreamError("start: this link has no telemetry; pass the initial actuator positions")
        init = np.asarray(initial, dtype=float)
        if init.shape != (self.actuators.n,):
            raise StreamError(f"start: device reports {init.size} actuators, the robot has {self.actuators.n}")
        v = self._gate.reset(init)
        if v is not None:
            reason = f"device start position refused: {v.message()}"
            self._machine.fail(reason, "refused", reason)
            raise StreamError(reason)
        self._machine.begin(f"{self.transport.description} at {self.options.rate:g} Hz")
        if background:
            self._thread = threading.Thread(target=self._run_loop, name="crtraj-streamer", daemon=True)
            self._thread.start()

    def _handshake(self) -> Telemetry:
        """PING until the first telemetry arrives. A PING carries no values and commands nothing,
        so it bypasses the limits gate; every set-point frame goes through `FrameSender.emit`."""
        deadline = self._clock.now() + self.options.connect_timeout
        next_ping = self._clock.now()
        while True:
            try:
                if self._clock.now() >= next_ping:
                    self._sender.ping(self._dt)
                    next_ping += 0.05
                self._cycle.poll_telemetry(self._clock.now())
            except TransportError as exc:
                self._machine.transport_failed(exc)
                raise StreamError(f"{self.reason} (is the device running?)") from None
            if self._monitor.last is not None:
                return self._monitor.last
            if self._clock.now() > deadline:
                reason = f"no telemetry from {self.transport.description} within {self.options.connect_timeout:g} s"
                self._machine.fail(reason, "no-telemetry", reason)
                raise StreamError(reason + " (is the device running?)")
            self._clock.sleep(0.005)

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
            self._machine.check_accepting(self._buffer.finished)
            self._buffer.append(tt, v)

    def send_path(self, stamps: np.ndarray, values: np.ndarray) -> None:
        """Queue many set-points at once (stamps (M,) s, values (M, n) rad or mm)."""
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
            self._machine.check_accepting(self._buffer.finished)
            self._buffer.extend(stamps, values)

    def finish(self) -> None:
        """No more set-points: stream to the last one, hold there and wait for the device to settle."""
        with self._lock:
            self._buffer.finish()

    # -------------------------------------------------------------- control
    def hold(self, reason: str = "hold requested") -> None:
        """Latch a hold at the last commanded positions (until `resume`)."""
        with self._lock:
            if self.state not in TERMINAL and self.state != IDLE:
                self._machine.latch(reason, self._clock.now())

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of every frame sent (holds too), as fractions of the limits."""
        with self._lock:
            return self._sender.limit_fractions()

    def wait_stopped(self, timeout: float) -> bool:
        """Wait up to `timeout` s (stream clock) until a held or e-stopped stream has sent its stop (the last frame
        commands rest; closing before latches the hold, a stop outside the limits); True when it has."""
        deadline = self._clock.now() + timeout
        while True:
            with self._lock:
                moving = self.state in (HELD, ESTOPPED) and bool(np.any(self._gate.velocity != 0.0))
            if not moving:
                return True
            if self._thread is None or not self._thread.is_alive() or self._clock.now() >= deadline:
                return False
            self._clock.sleep(self._dt)

    def resume(self) -> None:
        """Leave a latched hold at rest (braking: `StreamError`; `wait_stopped`); new set-points start at `position`."""
        with self._lock:
            if self.state != HELD or np.any(self._gate.velocity != 0.0):
                why = "still braking to rest (wait_stopped first)" if self.state == HELD else f"{self.state}, not held"
                raise StreamError(f"resume: stream is {why}")  # a gate reset mid-stop: a stop in one period
            self._buffer.clear()  # queued set-points are discarded
            self._cycle.clear_brake()
            self._monitor.source_ok()
            self._gate.reset(self._gate.position)
            self._machine.resume()

    def estop(self, reason: str = "e-stop requested") -> None:
        """Emergency stop: send ESTOP now and on every tick until closed. Terminal."""
        with self._lock:
            if self.state in (IDLE, CLOSED, ERROR, ESTOPPED):
                return
            now = self._clock.now()
            self._machine.estop(reason, now)
            try:
                if not self._cycle.brake_step(now):  # the stop's first frame, or the e-stop at rest
                    self._sender.hold(ESTOP)
            except TransportError as exc:
                self._machine.event("transport-error", str(exc))

    # ------------------------------------------------------------ whole path
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
        injects a planner, `crtraj.app.devices._approach`), by default the straight
        move in actuator space (`SetpointPath.with_approach`). Either way the
        approach's frames pass the motion's `FrameVerifier` (body, D_sf,
        limits, against the motion's scene at their times) before the first
        frame leaves; `plan_approach` raising `AdmissionError` (no safe
        approach) or a failed check ends the run with status ``refused`` and
        nothing sent.
        """
        check_admitted(motion, self.actuators, self.options.rate)
        self._cycle.check_stops_with(motion.verifier)  # stops checked like frames
        if not self._realtime:  # a dry run streams as fast as the CPU allows
            self._machine.use_clock(VirtualClock())
        if initial is None and not self.transport.has_telemetry:
            if approach:
                raise StreamError("--approach needs a device with telemetry (its position is the approach start)")
            initial = motion.values[0]
        try:
            self.start(initial, background=False)
        except StreamError as exc:
            return self.close(status=ERROR if self.state == ERROR else None, message=str(exc))
        here = self._gate.position
        stamps, values = motion.stamps, motion.values
        if approach:
            try:
                stamps, values = approach_frames(motion, here, self.actuators, self.options.rate, plan_approach)
            except AdmissionError as exc:
                return self._refuse(f"refused before sending: {exc}")
        v = self._gate.check_path(values, stamps, start=here)
        if v is not None:
            return self._refuse(refusal_text(v, values, here, self.actuators, self._dt))
        self.send_path(stamps, values)
        self.finish()
        try:
            self.run()
        except KeyboardInterrupt:
            with self._lock:
                self._machine.latch("interrupted (Ctrl-C)", self._clock.now())
            with contextlib.suppress(KeyboardInterrupt):  # brake to rest first (a second Ctrl-C: latch at once)
                self._pacer.run(self._clock, self._braking_tick, self._stop)
            return self.close(status="interrupted", message="interrupted (Ctrl-C): hold commanded")
        return self.close()

    def _braking_tick(self, now: float) -> bool:
        """One period of a held stream's stop (a latch at once is a stop outside the limits); False at rest."""
        with self._lock:
            self._cycle.tick(now)
            return self._cycle.is_braking and self.state == HELD

    def _refuse(self, message: str) -> StreamReport:
        self._machine.event("refused", message)
        return self.close(status="refused", message=message)

    # ----------------------------------------------------------------- loop
    def run(self) -> None:
        """Run the fixed-rate loop in the calling thread (after ``start(background=False)``) until
        the stream is done, stopped, or has held for one watchdog period after a fault."""
        if self._thread is not None:
            raise StreamError("run: the loop already runs in the background")
        self._run_loop(stop_when_latched=True)

    def _run_loop(self, stop_when_latched: bool = False) -> None:
        self._pacer.run(self._clock, lambda now: self._step(now, stop_when_latched), self._stop)

    def _step(self, now: float, stop_when_latched: bool) -> bool:
        """One period of the loop; False when the loop ends."""
        with self._lock:
            self._cycle.tick(now)
            ends = self._machine.loop_ends(now, self.options.watchdog, stop_when_latched)
            return not ends or (self._cycle.is_braking and self.state in (HELD, ESTOPPED))

    # ---------------------------------------------------------------- close
    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the background loop to end (done, e-stop or error); True if it ended."""
        th = self._thread
        if th is None:
            return self.state in TERMINAL
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
            if self.state in LIVE and self._sender.counts["frames"]:
                if self._cycle.is_braking:  # closed before the stop ended: the last resort is the latch
                    self._cycle.count_latched()
                try:
                    self._sender.hold(HOLD)
                except TransportError as exc:
                    self._machine.event("transport-error", str(exc))
            report = self._final_report(status, message)
            with contextlib.suppress(TransportError):
                self._log.write({"type": "report", **report.to_dict()})
            self._log.close()
            self.transport.close()
            self._machine.close()
            self._report = report
            return report

    def _final_report(self, status: str | None, message: str | None) -> StreamReport:
        tel = self._monitor.last
        counts = self._sender.counts
        brakes = self._cycle.brake_counts
        err = self._cycle.final_error
        if err is None and tel is not None and self._gate.position is not None and counts[MOVE]:
            err = float(np.max(np.abs(tel.positions - self._gate.position)))
        started = self.state != IDLE or counts["frames"]
        return StreamReport(
            status=self._machine.final_status(status),
            message=message or self.reason or ("completed" if self.state == DONE else ""),
            **self._sender.tallies(),
            telemetry=self._monitor.received,
            telemetry_errors=self._monitor.errors,
            device={} if tel is None else tel.counters(),
            final_error=err,
            duration=self._clock.now() - self._machine.t_start if started else 0.0,
            late_ticks=self._pacer.late_ticks,
            max_lateness=max(self._pacer.max_lateness, 0.0),
            log=None if self._log.path is None else str(self._log.path),
            events=tuple(self._machine.events),
            brakes=brakes.braked,
            brake_frames=brakes.frames,
            latched=brakes.latched,
        )
