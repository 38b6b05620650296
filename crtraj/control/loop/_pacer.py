"""The closed loop's pacer: times every iteration, judges it against the step deadline, and paces a
real-time run, all on one injected `crtraj.core.clock.Clock`. Units: s."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from crtraj.control.ports import Device, ObstacleSource
from crtraj.core.clock import Clock

# s a live run waits for a live source's first obstacle states before it refuses to start
FIRST_STATES_WAIT = 2.0


class CallableClock:
    """A `Clock` from a time function (s) and a sleep function (a ROS clock, a test's own)."""

    def __init__(self, now: Callable[[], float], sleep: Callable[[float], None] = time.sleep) -> None:
        self._now, self._sleep = now, sleep

    def now(self) -> float:
        return self._now()

    def sleep(self, seconds: float) -> None:
        self._sleep(seconds)


class Pacer:
    """Iteration timing and real-time pacing of one run (`start` begins it) on `clock`.

    dt: the loop's step (s); a real-time step more than dt behind its time counts as late.
    """

    def __init__(self, clock: Clock, dt: float) -> None:
        self.clock, self.dt = clock, dt
        self.start(False, None)

    def start(self, realtime: bool, device: Device | None) -> None:
        """Begin a run: paced by the clock when `realtime`, by the device when there is one."""
        self.realtime, self.device = realtime, device
        self.t0 = 0.0
        self.late = 0  # real-time steps that finished more than one step late

    def now(self) -> float:
        """The clock's time (s)."""
        return self.clock.now()

    def first_states(self, obstacles: ObstacleSource, live: bool) -> tuple[Any, str]:
        """The obstacles at t = 0: (scene, '') or (None, why). A live source is given a moment (up to
        FIRST_STATES_WAIT s on the clock) to deliver its first states."""
        scene0, why = obstacles.at(0.0)
        deadline = self.clock.now() + FIRST_STATES_WAIT
        while scene0 is None and live and self.clock.now() < deadline:
            self.clock.sleep(0.01)
            scene0, why = obstacles.at(0.0)
        return scene0, why

    def begin(self) -> None:
        """Loop time 0 is now (after the setup and warm-up); a device starts its own clock."""
        self.t0 = self.clock.now()
        if self.device is not None:
            # a device paces on its own clock: `Device.begin` takes the wall time (perf_counter) of loop time 0
            self.device.begin(time.perf_counter())

    def pace(self, t: float) -> None:
        """Wait until loop time t (s) is due in a real-time run; count the steps that came late."""
        if self.device is not None:
            self.late += self.device.pace(t)
        elif self.realtime:
            lag = self.clock.now() - self.t0 - t
            if lag < 0.0:
                self.clock.sleep(-lag)
            elif lag > self.dt:
                self.late += 1
