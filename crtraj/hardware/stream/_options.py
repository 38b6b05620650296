"""The streamer's options: the ``[stream]`` section of a problem file (rates in Hz, times in s, tolerances in
actuator units: rad for servos, mm for the z stage)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from crtraj.core.options import Options, option


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
