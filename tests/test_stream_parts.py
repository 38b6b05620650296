"""The streamer's parts on their own: the set-point buffer, the state machine and the device monitor.

Each part is driven directly (no transport, no thread) and checked against values worked out here by hand.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from crtraj.core.clock import VirtualClock
from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.protocol import Telemetry
from crtraj.hardware.stream._buffer import SetpointBuffer
from crtraj.hardware.stream._log import RunLog
from crtraj.hardware.stream._monitor import StreamMonitor
from crtraj.hardware.stream._options import StreamOptions
from crtraj.hardware.stream._pacing import RatePacer
from crtraj.hardware.stream._state import StreamError, StreamStateMachine

DT = 0.01


@pytest.fixture(scope="module")
def acts(robot):
    return Actuators.from_robot(robot)


# ------------------------------------------------------------------ buffer
def test_buffer_interpolates_linearly_between_set_points():
    """Between two queued set-points the cursor's values are the straight line between them."""
    buf = SetpointBuffer(DT)
    a, b = np.array([0.0, 1.0]), np.array([1.0, -3.0])
    buf.append(0.0, a)
    buf.append(0.05, b)
    buf.finish()
    buf.begin()
    for k in range(5):
        due = buf.due()
        w = k * DT / 0.05
        assert due.kind == "move" and due.stamp == pytest.approx(k * DT)
        np.testing.assert_allclose(due.values, a + w * (b - a), rtol=0, atol=1e-12)
        buf.advance(due)


def test_buffer_sends_the_final_set_point_at_its_own_time_then_settles():
    """A final time off the rate grid is sent at that time, once; then the buffer asks to settle."""
    buf = SetpointBuffer(DT)
    last = np.array([2.0])
    buf.extend(np.array([0.0, 0.025]), np.array([[0.0], last]))
    buf.finish()
    buf.begin()
    stamps = []
    while (due := buf.due()).kind == "move":
        stamps.append(due.stamp)
        buf.advance(due)
    assert stamps == pytest.approx([0.0, 0.01, 0.02, 0.025])
    assert due.kind == "settle" and due.stamp == 0.025
    assert buf.sent_stamp == 0.025  # holds repeat the final stamp


def test_buffer_on_grid_stamp_is_the_set_point_itself():
    """A cursor stamp on the set-points' own grid returns that very set-point (bit for bit what was verified)."""
    buf = SetpointBuffer(DT)
    values = [np.array([0.1 * k + 1e-17]) for k in range(4)]
    for k, v in enumerate(values):
        buf.append(k * DT, v)
    buf.finish()
    buf.begin()
    for k in range(3):
        due = buf.due()
        assert due.values is values[k]
        buf.advance(due)


def test_buffer_underruns_past_its_last_set_point_until_more_come():
    """A live source that has not caught up: the cursor reports an underrun for the stamp it needs."""
    buf = SetpointBuffer(DT)
    buf.append(0.0, np.array([0.0]))
    buf.begin()
    first = buf.due()
    assert first.kind == "move" and first.stamp == 0.0
    buf.advance(first)
    due = buf.due()
    assert due.kind == "underrun" and due.stamp == pytest.approx(DT)
    buf.append(0.02, np.array([1.0]))
    due = buf.due()
    assert due.kind == "move" and due.values[0] == pytest.approx(0.5)


def test_buffer_refuses_times_that_do_not_increase_and_keeps_what_it_had():
    """Times must increase; a refused set-point leaves the queue unchanged."""
    buf = SetpointBuffer(DT)
    buf.append(0.5, np.array([0.0]))
    with pytest.raises(InputError, match=r"^t: set-point times must increase \(got 0.5 s after 0.5 s\)"):
        buf.append(0.5, np.array([1.0]))
    with pytest.raises(InputError, match=r"got 0.2 s after 0.5 s"):
        buf.extend(np.array([0.2, 0.9]), np.zeros((2, 1)))
    assert buf.stamps == [0.5] and len(buf) == 1


def test_buffer_ready_after_prebuffer_span_or_finish():
    """Streaming starts once the queue spans the prebuffer time, or the source said it is done."""
    buf = SetpointBuffer(DT)
    assert not buf.ready(0.1)
    buf.extend(np.array([0.0, 0.05]), np.zeros((2, 1)))
    assert not buf.ready(0.1)
    buf.append(0.1, np.zeros(1))
    assert buf.ready(0.1)
    buf.clear()
    buf.append(1.0, np.zeros(1))
    assert not buf.ready(0.1)
    buf.finish()
    assert buf.ready(0.1)


# ----------------------------------------------------------- state machine
def _machine(clock: VirtualClock | None = None) -> StreamStateMachine:
    return StreamStateMachine(clock or VirtualClock(), RunLog(None, False))


def test_machine_latches_once_and_keeps_the_first_reason():
    """A second fault while held changes nothing: the report names the first."""
    clock = VirtualClock(10.0)
    m = _machine(clock)
    m.t_start = 10.0
    m.begin("link at 100 Hz")
    clock.advance(0.25)
    m.latch("source stalled", clock.now(), "stalled")
    m.latch("telemetry lost", clock.now() + 1.0, "telemetry-lost")
    assert (m.state, m.reason, m.latched_at) == ("held", "source stalled", 10.25)
    assert m.final_status(None) == "stalled" and m.final_status("interrupted") == "interrupted"
    assert [(t, name) for t, name, _ in m.events] == [(0.0, "start"), (0.25, "stalled")]


def test_machine_resume_only_from_held_and_refuses_sources_while_held():
    """Held: sources are refused with the reason; resume goes back to waiting; resume otherwise is an error."""
    m = _machine()
    with pytest.raises(StreamError, match="not started"):
        m.check_accepting(False)
    m.begin("")
    m.check_accepting(False)
    m.latch("hold requested", 0.0)
    with pytest.raises(StreamError, match=r"held \(hold requested\)"):
        m.check_accepting(False)
    m.resume()
    assert (m.state, m.reason, m.status_override, m.latched_at) == ("waiting", "", None, None)
    with pytest.raises(StreamError, match="resume: stream is waiting, not held"):
        m.resume()


def test_machine_closes_running_states_and_keeps_outcomes():
    """Closing a running stream reports closed; done, e-stop and error stay what they are."""
    m = _machine()
    m.begin("")
    assert m.final_status(None) == "closed"
    m.close()
    assert m.state == "closed"
    m2 = _machine()
    m2.begin("")
    m2.fail("device did not reach", "not-settled", "device did not reach", status="not-settled")
    assert m2.final_status(None) == "not-settled"
    m2.close()
    assert m2.state == "error"


def test_loop_ends_at_once_on_outcomes_and_after_one_watchdog_when_latched():
    """Done ends the loop at once; an e-stop after its frames repeated one watchdog; a hold only when asked."""
    m = _machine()
    m.begin("")
    assert not m.loop_ends(5.0, 0.1, stop_when_latched=True)
    m.latch("hold requested", 1.0)
    assert not m.loop_ends(1.05, 0.1, stop_when_latched=True)
    assert m.loop_ends(1.1, 0.1, stop_when_latched=True) and not m.loop_ends(9.0, 0.1, stop_when_latched=False)
    e = _machine()
    e.begin("")
    e.estop("e-stop requested", 2.0)
    assert not e.loop_ends(2.09, 0.1, stop_when_latched=False) and e.loop_ends(2.1, 0.1, stop_when_latched=False)
    d = _machine()
    d.begin("")
    d.done(None)
    assert d.loop_ends(0.0, 0.1, stop_when_latched=False)


# ------------------------------------------------------------------- pacing
def test_pacer_steps_once_per_period_and_counts_late_starts():
    """On a virtual clock the steps start every period; after a step that took 2.5 periods the next one starts
    late (counted) and the one after at once, to catch up with the period grid."""
    clock, starts = VirtualClock(), []

    def step(now: float) -> bool:
        starts.append(now)
        if len(starts) == 3:
            clock.advance(2.5 * DT)  # this step's work took 25 ms
        return len(starts) < 6

    pacer = RatePacer(DT)
    pacer.run(clock, step, threading.Event())
    assert starts == pytest.approx([0.0, 0.01, 0.02, 0.045, 0.045, 0.05])
    assert pacer.late_ticks == 1 and pacer.max_lateness == pytest.approx(0.015)


def test_pacer_resynchronises_after_a_long_stall_instead_of_bursting():
    """More than five periods behind, the next steps keep the period from now rather than catching up."""
    clock, starts = VirtualClock(), []

    def step(now: float) -> bool:
        starts.append(now)
        if len(starts) == 2:
            clock.advance(1.0)
        return len(starts) < 4

    RatePacer(DT).run(clock, step, threading.Event())
    assert starts == pytest.approx([0.0, 0.01, 1.01, 1.02])


# ------------------------------------------------------------------ monitor
def _tel(acts, seq: int, ack: int, positions, session: int = 7) -> bytes:
    return Telemetry(seq=seq, stamp=0.0, ack=ack, status=0, positions=np.asarray(positions), session=session).encode()


def test_monitor_checks_session_order_and_size(acts):
    """Telemetry of another session, out of order or of the wrong size is not taken; bad ones are counted."""
    mon = StreamMonitor(7, acts, StreamOptions(), RunLog(None, False), first_seq=0)
    zero = np.zeros(acts.n)
    assert mon.accept(_tel(acts, 1, 0, zero, session=8), 0.0, 0.0) is None
    assert mon.accept(_tel(acts, 2, 0, zero), 0.1, 0.1) is not None
    assert mon.accept(_tel(acts, 1, 0, zero), 0.2, 0.2) is None  # older than the newest: dropped, not an error
    assert mon.accept(_tel(acts, 3, 0, np.zeros(acts.n + 1)), 0.3, 0.3) is None
    assert mon.accept(b"\x00garbage", 0.4, 0.4) is None
    assert (mon.received, mon.errors, mon.last.seq, mon.last_time) == (1, 3, 2, 0.1)
    assert mon.silence(0.35) == pytest.approx(0.25)


def test_monitor_reports_the_oldest_unacknowledged_set_point(acts):
    """Acknowledging seq 2 drops 1 and 2; seq 3 then stalls once it is older than ack_timeout."""
    opts = StreamOptions(ack_timeout=0.2)
    mon = StreamMonitor(7, acts, opts, RunLog(None, False), first_seq=0)
    for seq, t in ((1, 0.0), (2, 0.01), (3, 0.02)):
        mon.sent(seq, t, np.full(acts.n, float(seq)))
    tel = mon.accept(_tel(acts, 1, 2, np.full(acts.n, 2.0)), 0.1, 0.1)
    assert mon.ack_stall(tel, 0.22) is None  # 200 ms: not yet
    why = mon.ack_stall(tel, 0.25)
    assert why is not None and why.startswith(
        "device stopped acknowledging: set-point seq 3 unacknowledged after 230 ms"
    )


def test_monitor_following_error_names_the_worst_actuator(acts):
    """The measured positions are compared with the acknowledged set-point; the largest error is named."""
    opts = StreamOptions(following_tolerance=0.5)
    mon = StreamMonitor(7, acts, opts, RunLog(None, False), first_seq=0)
    cmd = np.zeros(acts.n)
    mon.sent(1, 0.0, cmd)
    measured = cmd.copy()
    measured[2] = 0.4
    tel = mon.accept(_tel(acts, 1, 1, measured), 0.0, 0.0)
    assert mon.following_error(tel) is None
    measured[-1] = -0.75
    tel = mon.accept(_tel(acts, 2, 1, measured), 0.01, 0.01)
    why = mon.following_error(tel)
    assert why is not None and why.startswith(f"following error: {acts.names[-1]} measured -0.75 {acts.units[-1]}")
    assert "|error| 0.75 > following_tolerance 0.5" in why
