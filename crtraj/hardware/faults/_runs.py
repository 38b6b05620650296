"""The bus going silent at many times of one stream, and what the servos then did, measured independently.

A host that dies (SIGKILL) and a USB adapter pulled out look the same to the servos: from some instant on, no
instruction packet reaches the bus. `SilencePort` is the simulator's port (`crtraj.hardware.dynamixel.SimPort`)
that, while one stream runs, keeps a copy of the servos (`ServoChain`) at each of many times: the copy taken
just before the first packet at or after time t is exactly the chain a host killed at t leaves behind (the
run is deterministic on its virtual clock, and a silent bus changes nothing but the time). So one stream gives
the servo side of any number of kills.

`measure_stop` then reads such a chain densely (1 ms samples of the shafts, second differences), from the
silence until every servo rests: the largest deceleration over each actuator's limit (the profile register
rounds up by at most one unit, allowed), the distance each actuator travelled, the time to rest, and, with a
`clearance` function of actuator values, the smallest clearance of the body on the way. `FaultPort` injects one
fault at a time and records every servo's true current at every packet (what the tendon carried, not what the
link read). Units: s, ticks, actuator units (rad, mm), mm.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from crtraj.core.clock import Clock
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import ServoChain, SimPort, X

SAMPLE = 1e-3  # s between the dense samples of a stop
REST = 0.5  # ticks: a shaft that moves less over `REST_SPAN` s rests
REST_SPAN = 0.1  # s


class SilencePort(SimPort):
    """`SimPort` that keeps a copy of the chain at each of `times` (clock s, sorted): `silent[j]` is (t_j, the
    clock time of the first packet not sent, the chain as that packet would have found it)."""

    def __init__(self, chain: ServoChain, clock: Clock, times: Sequence[float], *, name: str = "sim") -> None:
        super().__init__(chain, clock, name=name)
        self.times = sorted(float(t) for t in times)
        self.silent: list[tuple[float, float, ServoChain]] = []

    def writePort(self, packet: list[int] | bytes) -> int:  # noqa: N802 - the SDK's name
        now = self.clock.now()
        while len(self.silent) < len(self.times) and now >= self.times[len(self.silent)]:
            self.silent.append((self.times[len(self.silent)], now, copy.deepcopy(self.chain)))
        return super().writePort(packet)


class FaultPort(SimPort):
    """`SimPort` with `fault(chain, at)` at clock time `at` (s); every packet first records the true Present
    Current of every servo (`currents`: (clock time, (n,) signed 2.69 mA units))."""

    def __init__(
        self, chain: ServoChain, clock: Clock, at: float, fault: Callable[[ServoChain, float], None], *, name: str
    ) -> None:
        super().__init__(chain, clock, name=name)
        self.at, self.fault, self.done = at, fault, False
        self.currents: list[tuple[float, np.ndarray]] = []

    def writePort(self, packet: list[int] | bytes) -> int:  # noqa: N802 - the SDK's name
        now = self.clock.now()
        if not self.done and now >= self.at:
            self.done = True
            self.fault(self.chain, self.at)
        self.currents.append((now, np.array([self.chain.current(i, now) for i in self.chain.ids])))
        return super().writePort(packet)


@dataclass(frozen=True)
class StopMeasure:
    """A stop measured densely. decel: (n,) largest |second difference| of each shaft over its acceleration
    limit (profile rounding allowed: at most 1); distance: (n,) travel of each actuator (rad, mm); rest: s from
    the silence until every shaft rests; clearance: smallest clearance (mm, beyond D_sf) on the way (inf: not
    measured); tripped: every servo's Bus Watchdog reads -1; values: (m, n) the actuator values sampled;
    current: (n,) largest |Present Current| (2.69 mA units) on the way (zeros: not measured)."""

    decel: np.ndarray
    distance: np.ndarray
    rest: float
    clearance: float
    tripped: bool
    values: np.ndarray
    current: np.ndarray


def measure_stop(
    chain: ServoChain,
    acts: Actuators,
    start: float,
    *,
    horizon: float = 3.0,
    clearance: Callable[[np.ndarray], np.ndarray] | None = None,
    currents: bool = False,
) -> StopMeasure:
    """The stop of `chain` after the bus fell silent at `start` (device s), sampled every `SAMPLE` s until every
    shaft rests (at most `horizon` s). clearance: (m, n) actuator values -> (m,) clearance (mm), or None.
    currents: also the largest |Present Current| of each servo (a read of every servo per sample)."""
    bus = acts.bus
    per_tick = np.asarray(bus.per_rev) / np.asarray(bus.ticks_per_rev)  # actuator units per tick
    bound = acts.amax / per_tick + X.ACCELERATION_UNIT / 3600.0 * np.asarray(bus.ticks_per_rev)  # ticks/s^2
    shafts, reads = [chain.shaft(start)], [chain.positions(start)]
    peak = np.zeros(len(bus.ids))
    span = round(REST_SPAN / SAMPLE)
    while len(shafts) * SAMPLE < horizon:
        t = start + len(shafts) * SAMPLE
        shafts.append(chain.shaft(t))
        reads.append(chain.positions(t))
        if currents:
            peak = np.maximum(peak, [abs(chain.current(i, t)) for i in bus.ids])
        if len(shafts) > span and np.max(np.abs(shafts[-1] - shafts[-1 - span])) < REST:
            break
    s = np.array(shafts)
    acc = np.abs(np.diff(s, 2, axis=0)) / SAMPLE**2 if len(s) > 2 else np.zeros((1, len(bus.ids)))
    values = np.array(reads) * np.asarray(bus.resolution)
    return StopMeasure(
        decel=np.max(acc, axis=0) / bound,
        distance=np.max(np.abs(s - s[0]), axis=0) * per_tick,
        rest=(len(s) - 1 - span) * SAMPLE,
        clearance=float(np.min(clearance(values))) if clearance is not None else float("inf"),
        tripped=all(chain.register(i, X.BUS_WATCHDOG, 1) & 0xFF == X.WATCHDOG_TRIPPED for i in bus.ids),
        values=values,
        current=peak,
    )
