"""Replay a scene's obstacles as a motion-capture bridge would send them (`crtraj feed-replay`).

`FeedReplay` samples each obstacle of a `crtraj.world.scene.Scene` from its own time functions at a fixed
rate and turns each sample into the feed's datagram format (`crtraj.world.feed`: ``{"id", "center",
"radius", "timestamp"}``, mm and s), with what a real bridge adds: Gaussian measurement noise on every
coordinate and on the radius, a fixed latency plus uniform jitter between measuring and delivering,
and messages that never arrive. Everything random comes from one seeded generator, so a replay is
reproducible; the clock and the sleep are injected, so a test can run a replay on virtual time.

Timestamps are scene time: a message measured at replay time t carries ``timestamp = t`` and the
obstacle's state at scene time t (the replay starts the scene's clock when it starts). Units: mm, s.
"""

from __future__ import annotations

import heapq
import json
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.options import Options, option


@dataclass(frozen=True)
class ReplayOptions(Options):
    """How `FeedReplay` degrades the scene's true obstacle states (units mm, s, Hz).

    rate: Hz, measurements per second and obstacle (100, a typical capture rate).
    noise: mm, standard deviation of the Gaussian noise on each centre coordinate and on the radius
    (0.3, the paper's capture accuracy). latency: s from measuring to sending every message (0).
    jitter: s, a uniform extra delay in [0, jitter] per message (0; messages may then arrive out of
    order, as over a real network). dropout: probability that a message is never sent (0).
    duration: s of scene time replayed (at most one day). seed: the random generator's seed.
    """

    SECTION: ClassVar[str] = "feed-replay"  # the command whose flags these are

    rate: float = option(100.0, gt=0.0, le=1000.0)
    noise: float = option(0.3, ge=0.0, le=100.0)
    latency: float = option(0.0, ge=0.0, le=10.0)
    jitter: float = option(0.0, ge=0.0, le=10.0)
    dropout: float = option(0.0, ge=0.0, le=0.99)
    duration: float = option(120.0, gt=0.0, le=86400.0)
    seed: int = option(0, ge=0, le=2**31 - 1)


@dataclass(frozen=True)
class ReplayCounts:
    """What a replay did: measured (messages sampled), sent, dropped (never sent), datagrams."""

    measured: int
    sent: int
    dropped: int
    datagrams: int


class FeedReplay:
    """Sends a scene's obstacle states on a schedule (see the module docstring).

    scene: the obstacles (each needs a name: the feed id). options: `ReplayOptions`.
    Messages measured at the same instant that are due at the same instant share one datagram.
    """

    def __init__(self, scene: Any, options: ReplayOptions | None = None) -> None:
        names = [o.name for o in scene.obstacles]
        if not names:
            raise InputError("scene.obstacle: the scene has no obstacles to replay")
        if not all(names):
            raise InputError("scene.obstacle: every replayed obstacle needs a name (its feed id)")
        self.scene = scene
        self.options = ReplayOptions() if options is None else options
        self.ids = tuple(names)
        self._rng = np.random.default_rng(self.options.seed)
        self._measured = self._sent = self._dropped = self._datagrams = 0
        self._pending: list[tuple[float, int, float, str]] = []  # (due, order, timestamp, id) heap
        self._order = 0
        self._next = 0  # index of the next measurement instant
        self.started: float | None = None  # clock() at replay time 0, once `run` started

    # ---------------------------------------------------------------- samples
    def truth(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The true obstacle states at scene time t (s): centres (m, 3) mm, radii (m,) mm."""
        return self.scene.states(float(t))

    def messages(self, oids: list[str], t: float) -> list[dict[str, Any]]:
        """The feed messages for obstacles `oids` measured at scene time t, each with the replay's noise."""
        c, r = self.truth(t)  # one evaluation of the scene for every obstacle measured at t
        s = self.options.noise
        out = []
        for oid in oids:
            j = self.ids.index(oid)
            noise = self._rng.normal(0.0, s, 4) if s > 0.0 else np.zeros(4)
            center = [float(v) for v in c[j] + noise[:3]]
            out.append({"id": oid, "center": center, "radius": max(float(r[j] + noise[3]), 0.0), "timestamp": float(t)})
        return out

    def _measure_until(self, now: float) -> None:
        """Schedule every measurement instant up to `now` (s): each obstacle's message is dropped or
        queued for delivery at its instant plus latency and jitter."""
        o = self.options
        period = 1.0 / o.rate
        while True:
            t = self._next * period
            if t > now + 1e-12 or t > o.duration + 1e-12:
                return
            self._next += 1
            for oid in self.ids:
                self._measured += 1
                if self._rng.random() < o.dropout:
                    self._dropped += 1
                    continue
                delay = o.latency + (self._rng.uniform(0.0, o.jitter) if o.jitter > 0.0 else 0.0)
                heapq.heappush(self._pending, (t + delay, self._order, t, oid))
                self._order += 1

    def due(self, now: float) -> list[bytes]:
        """The datagrams due for sending at replay time `now` (s), in delivery order."""
        self._measure_until(now)
        out: list[bytes] = []
        while self._pending and self._pending[0][0] <= now + 1e-12:
            due, _, ts, oid = heapq.heappop(self._pending)
            oids = [oid]
            while self._pending and self._pending[0][0] == due and self._pending[0][2] == ts:
                oids.append(heapq.heappop(self._pending)[3])
            batch = self.messages(oids, ts)
            self._sent += len(batch)
            self._datagrams += 1
            out.append(json.dumps(batch if len(batch) > 1 else batch[0]).encode())
        return out

    def next_due(self) -> float:
        """Replay time (s) of the next delivery or measurement (inf when the replay is over)."""
        o = self.options
        t_meas = self._next / o.rate
        nxt = t_meas if t_meas <= o.duration + 1e-12 else math.inf
        return min(nxt, self._pending[0][0]) if self._pending else nxt

    @property
    def finished(self) -> bool:
        return math.isinf(self.next_due())

    def counts(self) -> ReplayCounts:
        return ReplayCounts(self._measured, self._sent, self._dropped, self._datagrams)

    # -------------------------------------------------------------------- run
    def run(
        self,
        send: Callable[[bytes], None],
        clock: Callable[[], float],
        sleep: Callable[[float], None],
        stop: threading.Event | None = None,
    ) -> ReplayCounts:
        """Send every datagram at its time until the replay's duration is over or `stop` is set.

        send: delivers one datagram. clock: s, monotonic; the replay's time is clock() minus its
        value at the call. sleep: waits s (a virtual clock's sleep advances it)."""
        start = clock()
        self.started = start
        while not self.finished and not (stop is not None and stop.is_set()):
            now = clock() - start
            for datagram in self.due(now):
                send(datagram)
            wait = self.next_due() - (clock() - start)
            if wait > 0.0 and not math.isinf(wait):
                sleep(min(wait, 0.05))  # wake often enough to see `stop`
        return self.counts()
