"""Parts of the closed loop on their own (the pacer, the recorder), on a virtual clock."""

from __future__ import annotations

import numpy as np
import pytest

from crtraj.control.loop._pacer import FIRST_STATES_WAIT, CallableClock, Pacer
from crtraj.control.loop._recorder import RecorderSetup, RunRecorder
from crtraj.control.loop._run_record import StateRecord
from crtraj.core.clock import VirtualClock


class _LateSource:
    """A live obstacle source whose first state arrives at `ready` s of the clock (never when None)."""

    live = True

    def __init__(self, clock: VirtualClock, ready: float | None) -> None:
        self.clock, self.ready, self.calls = clock, ready, 0

    def at(self, t: float):
        self.calls += 1
        if self.ready is not None and self.clock.now() >= self.ready:
            return "scene", ""
        return None, "no obstacle state received yet"


def test_a_real_time_step_waits_until_it_is_due_and_a_late_one_is_counted():
    """pace(t) sleeps the clock up to loop time t; a step more than dt behind its time counts as late."""
    clock = VirtualClock(10.0)
    pacer = Pacer(clock, dt=0.1)
    pacer.start(realtime=True, device=None)
    pacer.begin()
    clock.advance(0.03)  # the step's work
    pacer.pace(0.1)
    assert clock.now() == pytest.approx(10.1) and pacer.late == 0
    clock.advance(0.35)  # a slow step: 0.25 s behind loop time 0.2, more than dt
    pacer.pace(0.2)
    assert clock.now() == pytest.approx(10.45) and pacer.late == 1


def test_a_simulated_run_is_not_paced():
    """Without real time and without a device, pace neither sleeps nor counts."""
    clock = VirtualClock(0.0)
    pacer = Pacer(clock, dt=0.1)
    pacer.start(realtime=False, device=None)
    pacer.begin()
    clock.advance(5.0)
    pacer.pace(0.1)
    assert clock.now() == 5.0 and pacer.late == 0


@pytest.mark.parametrize(("ready", "found"), [(0.5, True), (None, False)])
def test_the_wait_for_a_live_sources_first_state_is_bounded_on_the_clock(ready, found):
    """first_states polls a live source until its first state (on the clock's time), at most FIRST_STATES_WAIT s."""
    clock = VirtualClock(0.0)
    source = _LateSource(clock, ready)
    scene, why = Pacer(clock, dt=0.1).first_states(source, live=True)
    if found:
        assert scene == "scene" and why == "" and clock.now() == pytest.approx(0.5, abs=0.011)
    else:
        assert scene is None and why == "no obstacle state received yet"
        assert clock.now() == pytest.approx(FIRST_STATES_WAIT, abs=0.011)


def test_a_callable_clock_is_its_two_functions():
    """CallableClock: now() is the time function, sleep() the sleep function."""
    slept: list[float] = []
    clock = CallableClock(lambda: 42.0, slept.append)
    clock.sleep(0.25)
    assert clock.now() == 42.0 and slept == [0.25]


def _state(t: float, T: np.ndarray) -> StateRecord:
    x = np.full(2, t)
    return StateRecord(t, x, x, x, 1.0, 6.0, 0.5, x, np.zeros((0, 3)), np.zeros(0), T, np.stack([T, T], axis=1))


def test_the_recorder_keeps_each_motion_sample_once():
    """The first record keeps its samples; each later one drops its first, which is the previous record's last."""
    rec = RunRecorder(RecorderSetup(None, lambda q: q, np.zeros(3), 0.1, 2, True, None))  # type: ignore[arg-type]
    rec.record_state(_state(0.0, np.array([0.0])))
    rec.record_state(_state(0.1, np.array([0.0, 0.05, 0.1])))
    rec.record_state(_state(0.2, np.array([0.1, 0.15, 0.2])))
    dense = np.concatenate([s.dense_t for s in rec.states])
    np.testing.assert_array_equal(dense, [0.0, 0.05, 0.1, 0.15, 0.2])
    assert all(len(s.dense_x) == len(s.dense_t) for s in rec.states)
    rec.count_deadline_miss()
    assert rec.deadline_misses == 1
    rec.start()
    assert rec.states == [] and rec.deadline_misses == 0
