"""Ports of the closed loop: what it needs from an obstacle source and from a device.

The loop (`crtraj.control.loop.ClosedLoop`) talks to the world, to hardware and to a live view only through
these protocols, so it never imports hardware or viewing code. Implementations live in the layer that owns
them: `crtraj.world.sources` (obstacle sources), `crtraj.hardware.link` (a device driven through the
streamer) and `crtraj.viz.live._feed` (a live view, `StepObserver`). Units: mm, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np


class DeviceError(RuntimeError):
    """A device could not take a command (refused before sending, late, held, stopped or disconnected
    meanwhile); the message says why. The loop catches only this from a device; whether the device is lost
    for good is `Device.problem`'s answer at the next step."""


@dataclass(frozen=True)
class Landing:
    """The motion a device will execute over one step as committed now, whatever became of the step the
    loop planned (sent, refused, held, late): per control period, the set-point in force (commands) and
    the actuation at the period's end (executed), both (n, nq) mm. The last row is where the next step
    starts; the last two give its velocity and the set-point's last change, the history the next step's
    acceleration limits continue from. A robot at rest has every row equal."""

    commands: np.ndarray
    executed: np.ndarray

    @property
    def q(self) -> np.ndarray:
        """Actuation (mm) at the next step's start."""
        return self.executed[-1]

    @property
    def qc(self) -> np.ndarray:
        """The set-point (mm) in force at the next step's start."""
        return self.commands[-1]

    @classmethod
    def at_rest(cls, q: np.ndarray, periods: int) -> Landing:
        """Resting at actuation q (mm) with the set-point there, for `periods` control periods."""
        rows = np.repeat(np.asarray(q, dtype=float).reshape(1, -1), periods, axis=0)
        return cls(rows, rows.copy())

    @classmethod
    def first_order(cls, q: np.ndarray, velocity: np.ndarray, tau: float) -> Landing:
        """From actuation q (n, nq) mm and its velocity (n, nq) mm/s at the ends of the control periods, under
        first-order servos of time constant tau (s): the set-point in force is q + tau dq/dt."""
        q = np.asarray(q, dtype=float)
        return cls(q + tau * np.asarray(velocity, dtype=float), q.copy())


@runtime_checkable
class ObstacleSource(Protocol):
    """Where the obstacle states of each step come from.

    live: the states are measured as the run goes (only meaningful in real time) rather than known
    in advance.
    """

    live: bool

    def at(self, t: float) -> tuple[Any, str]:
        """(the obstacles as a `crtraj.world.scene.Scene` valid from loop time t (s), '') or
        (None, why there is no trustworthy state)."""
        ...

    def new_events(self) -> list[Any]:
        """Events (objects with ``to_dict()``) the source recorded since the last call, e.g. rejected
        feed messages; [] for a source without any."""
        ...

    def describe(self) -> dict[str, Any]:
        """Counters and options of a live source for the run record ({} for a known-motion source)."""
        ...


@runtime_checkable
class Device(Protocol):
    """A device the loop drives live: its telemetry is the measured state, each verified move is sent.

    Actuation q is in mm (cables, base stage); times are loop time in s. Any method may raise
    `DeviceError` when the device cannot take a command.
    """

    def start_actuation(self) -> np.ndarray:
        """Where the device is at the start (actuation q, mm)."""
        ...

    def begin(self, t_origin: float) -> None:
        """Start the device's clock: loop time 0 is wall time t_origin (`time.perf_counter`, s)."""
        ...

    def problem(self) -> str:
        """Why the loop cannot drive the device any more ('' when it can)."""
        ...

    def measure(self, t: float, q: np.ndarray, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
        """(measured actuation, command in force, whether telemetry gave them) at loop time t; the
        model's q, qc come back unchanged when there is no telemetry."""
        ...

    def move(self, t: float, q0: np.ndarray, commands: np.ndarray, control_dt: float) -> None:
        """Send the verified motion of the step starting at t from q0 under `commands` (one per control
        period of control_dt s); `DeviceError` when it was not sent (refused, late, held meanwhile)."""
        ...

    def landing(self, t: float, periods: int, control_dt: float) -> Landing:
        """What the robot executes over the step from loop time t (`periods` control periods of control_dt s)
        as committed now: the loop asks after every step the device did not take as planned (a `DeviceError`
        from `move`, a hold, a stale step) and plans the next step from its last row, never from its own
        unexecuted plan. A device that stops on a committed curve answers with that curve (moving until its
        rest point, then resting there); a held device with its stop, else at rest where it is."""
        ...

    def pace(self, t: float) -> bool:
        """Wait until loop time t is due; True when the loop is more than one step late."""
        ...

    def hold(self, reason: str) -> None:
        """Stop at the last sent position (recoverable: the next move resumes)."""
        ...

    def estop(self, reason: str) -> None:
        """Emergency stop (final)."""
        ...

    def finish(self, q_final: np.ndarray) -> Any:
        """Bring the device to rest at q_final (mm) and close it; returns the device's report."""
        ...

    def limit_fractions(self) -> dict[str, float]:
        """Largest actuator speed and acceleration of what was sent to the device, as fractions of the
        limits ({"max_velocity_fraction", "max_acceleration_fraction"}; NaN when nothing was sent)."""
        ...

    def describe(self) -> dict[str, Any]:
        """What the device did, for the run record."""
        ...


@runtime_checkable
class TipSensor(Protocol):
    """A direct measurement of the tip in the robot frame, e.g. a motion-capture marker mapped through the
    calibrated capture frame (``[calibration]`` of a robot file written by ``crtraj calibrate``).

    The loop compares it with its model's tip: the difference is model error the loop can correct
    (`ClosedLoop` with ``tip_feedback``). Units: mm, s.
    """

    def tip(self, t: float, q: np.ndarray) -> np.ndarray | None:
        """The measured tip (3,) mm at loop time t, or None when the marker is not seen. q: the actuation
        (mm) the loop believes in force (a simulated sensor uses it; a real one ignores it)."""
        ...


@runtime_checkable
class StepObserver(Protocol):
    """Something that watches a running loop, e.g. a live view (`crtraj.viz.live._feed.LiveFeed`).

    Called on the loop's thread once per recorded state, so it must cost O(1): keep references and return,
    never copy arrays, draw or wait (the records are frozen and the loop never changes their arrays).
    """

    def observe(self, state: Any, step: Any) -> None:
        """The newest `crtraj.control.loop.StateRecord` (t s, x, centers mm, ...) and the
        `StepRecord` of the step that led to it (None for the record at the start)."""
        ...
