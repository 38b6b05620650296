"""The live view's frames (issue 30): one message per frame from the drawing process to the server, the page's
numbers grown alike by the server and by the page, the feed's message to the drawing process read back exactly,
and the live actuator fractions equal to the whole run's finite differences. (The page in a browser:
tests/test_viz_live_page.py.)"""

from __future__ import annotations

import json
import os
import signal
import time
import urllib.request

import numpy as np
import pytest
from conftest import BALL, straight_loop

from crtraj.control.horizon import ReplanOptions
from crtraj.control.loop import LoopOptions
from crtraj.viz.live import LiveView
from crtraj.viz.live._child import pack, unpack
from crtraj.viz.live._page import ActuatorFractions, LivePage
from crtraj.viz.page import append_rows
from crtraj.viz.view import Visualizer
from crtraj.world.scene import Scene

HANG_S = 300.0  # a hang bound only


class _Records:
    """A loop observer that keeps every (StateRecord, StepRecord or None) it is told of."""

    def __init__(self) -> None:
        self.entries: list = []

    def observe(self, state, step) -> None:
        self.entries.append((state, step))


@pytest.fixture(scope="module")
def loop_records(model):
    """A short loop among one moving ball (sqp, 3 s): its run and every record the loop handed its observer."""
    scene = Scene(obstacles=(BALL,), safety_distance=5.0)
    opts = ReplanOptions(horizon=6, points=12, solver="sqp")
    loop = straight_loop(model, scene, options=opts, loop_options=LoopOptions(duration=3.0))
    rec = _Records()
    run = loop.run(observer=rec)
    return run, rec.entries


def test_the_feeds_message_reads_back_exactly(loop_records, model):
    """`pack` (on the feed thread) and `unpack` (in the drawing process): every field of the newest state and of
    each record comes back bit for bit; the first record carries its actuation, the others their executed
    samples."""
    _, entries = loop_records
    new = entries[:4]
    head, buf = pack(entries[7][0], new)
    state, back = unpack(json.loads(head), buf, model.robot.nx)
    assert state.t == entries[7][0].t and np.array_equal(state.x, entries[7][0].x)
    assert np.array_equal(state.centers, entries[7][0].centers) and np.array_equal(state.radii, entries[7][0].radii)
    assert len(back) == len(new) and back[0][1] is None and np.array_equal(back[0][0].q, new[0][0].q)
    for (s, k), (s0, k0) in zip(back[1:], new[1:], strict=True):
        assert s.t == s0.t and np.array_equal(s.x, s0.x) and np.array_equal(s.planned, s0.planned)
        assert np.array_equal(s.centers, s0.centers) and np.array_equal(s.radii, s0.radii)
        assert (k.step_status, k.iter_time, k.replanned) == (str(k0.step_status), k0.iter_time, bool(k0.replanned))
        assert np.array_equal(k.executed, np.ravel(k0.executed))
    with pytest.raises(ValueError, match="the header describes"):
        unpack(json.loads(head), buf + bytes(8), model.robot.nx)


def test_live_fractions_equal_the_whole_runs_finite_differences(loop_records, model):
    """Step by step, as the records come, the largest actuator velocity and acceleration fraction of each step
    equal those of the whole run's executed actuation (`ReplanRun.executed`, one row per tracking period),
    differenced at once over the run: the carried last sample and last velocity join the steps seamlessly."""
    run, entries = loop_records
    limits, (_, rest) = model.robot.actuator_limits(), model.robot.cable_matrix()
    live = ActuatorFractions(limits, rest)
    got = []
    for state, step in entries:
        if step is None:
            live.start(state.t, state.q)
        else:
            got.append(live.step(state.t, step.executed))
    values = limits.command(run.executed, np.asarray(rest))
    V = np.diff(values, axis=0) / run.control_dt  # V[i]: over period i + 1
    A = np.diff(V, axis=0) / run.control_dt  # A[i]: from period i + 1 to i + 2
    n = len(run.executed[1:]) // run.steps
    vf = (np.abs(V) / limits.vmax).max(axis=1).reshape(run.steps, n).max(axis=1)
    af = np.concatenate([[np.nan], (np.abs(A) / limits.amax).max(axis=1)]).reshape(run.steps, n)
    af = np.nanmax(af, axis=1)
    assert run.steps > 20 and np.nanmax(vf) > 0.01  # the robot moved
    np.testing.assert_allclose(np.array(got), np.stack([vf, af], axis=1), rtol=1e-9, atol=1e-12)


def _get(url: str) -> dict:
    with urllib.request.urlopen(url, timeout=HANG_S) as r:
        return json.loads(r.read())


def test_one_request_per_frame_and_the_server_keeps_the_pages_numbers(loop_records, model):
    """A `LivePage` drawing a run's records in chunks on a served Visualizer: after the first frame (which also
    aims the camera) each frame is exactly one request to the server, and the server's page data (data.json),
    grown from the frames' rows, equals the page's own numbers after every frame."""
    run, entries = loop_records
    vis = Visualizer(model, server=True, timeout=HANG_S)
    try:
        page = LivePage(vis, model, safety_distance=5.0, deadline=0.004, names=["ball"], goal=run.goal)
        page.push()
        window = vis._window
        sent = []
        request = window._request
        window._request = lambda *frames: (sent.append(frames[0]), request(*frames))[1]
        url = vis.url + "data.json"
        head = entries[:30]
        chunks = [head[i : i + 7] for i in range(0, 30, 7)]
        for i, chunk in enumerate(chunks):
            before = len(sent)
            page.draw(chunk[-1][0], chunk)
            if i:
                assert sent[before:] == [b"crtraj_frame"], sent[before:]
            assert _get(url) == json.loads(json.dumps(page.data())), i
    finally:
        vis.close()
    assert len(page.t) == 30 and page.velocity[0] is None and page.velocity[1] is not None


def _rows(k: int, t: list[float], events: list) -> dict:
    n = len(t)
    return {"k": k, "t": t, "status": ["move"] * n, "near": [0] * n, "tip_error": [0.1] * n,
            "iteration": [0.001] * n, "velocity": [0.5] * n, "acceleration": [0.2] * n,
            "clearance": [[3.0] * n], "events": events, "closest_t": t[-1]}  # fmt: skip


def test_append_rows_skips_what_the_page_has_and_refuses_a_gap():
    """Rows that overlap the page's numbers add only the new steps (and only events after the page's last time);
    rows that start beyond the page's end are refused (the page fetches the whole data instead)."""
    run = {**{f: [] for f in ("t", "status", "near", "tip_error", "iteration", "velocity", "acceleration")},
           "clearance": [[]], "events": [], "closest_t": 0.0}  # fmt: skip
    append_rows(run, _rows(0, [0.0, 0.1], [{"kind": "hold", "t": 0.1, "text": ""}]))
    events = [{"kind": "hold", "t": 0.1, "text": ""}, {"kind": "replan", "t": 0.3, "text": ""}]
    append_rows(run, _rows(1, [0.1, 0.2, 0.3], events))
    assert run["t"] == [0.0, 0.1, 0.2, 0.3] and run["clearance"] == [[3.0] * 4] and run["closest_t"] == 0.3
    assert [e["kind"] for e in run["events"]] == ["hold", "replan"]
    append_rows(run, _rows(2, [0.2], []))  # nothing new
    assert len(run["t"]) == 4
    with pytest.raises(ValueError, match="step 6 does not follow step 3"):
        append_rows(run, _rows(6, [0.6], []))


def test_a_frame_the_server_refuses_raises(model):
    """Rows that do not follow the server's page data (a gap) are refused by the server, and the drawing side
    hears it (a RuntimeError naming the step), instead of a page that silently misses steps."""
    vis = Visualizer(model, server=True, timeout=HANG_S)
    try:
        page = LivePage(vis, model, safety_distance=5.0, deadline=0.004, names=["ball"], goal=np.zeros(3))
        page.push()
        rows = _rows(5, [0.5], [])
        with pytest.raises(RuntimeError, match="step 5 does not follow step -1"):
            vis._window.send_frame([], np.zeros((0, 4, 4)), rows)
    finally:
        vis.close()


def _wait_for(condition, what: str) -> None:
    """Poll `condition` every 10 ms, bounded by HANG_S (a hang bound only)."""
    end = time.monotonic() + HANG_S
    while not condition():
        assert time.monotonic() < end, f"no {what} within {HANG_S:g} s"
        time.sleep(0.01)


def test_a_server_too_slow_for_one_frame_does_not_end_the_live_view(loop_records, model):
    """The live server (which runs below the loop's priority) is stopped while the drawing process waits for its
    reply: that one draw is reported late (the feed counts it failed) and the view goes on. The next draw that
    reaches the server sends the page's whole data first, so the server's page (data.json) has every observed
    step, in order, with none missing, none twice (before: the drawing process died and the page froze)."""
    run, entries = loop_records
    view = LiveView(model, run.goal, Scene(obstacles=(BALL,), safety_distance=5.0), 0.004, timeout=2.0, nice=0)
    feed, server = view.feed, view.vis._window.server_proc
    try:
        feed.observe(*entries[0])
        _wait_for(lambda: feed.drawn == 1, "first draw")
        os.kill(server.pid, signal.SIGSTOP)
        try:
            feed.observe(*entries[1])
            _wait_for(lambda: feed.failed == 1, "late draw")
        finally:
            os.kill(server.pid, signal.SIGCONT)
        # each further state is one more draw; a draw late again (a busy machine) only means one more resync
        k = 2
        while True:
            drawn, failed = feed.drawn, feed.failed
            feed.observe(*entries[k])
            k += 1
            _wait_for(lambda d=drawn, f=failed: feed.drawn + feed.failed > d + f, "draw")
            if feed.drawn > drawn or k == len(entries):
                break
        data = _get(view.url + "data.json")
    finally:
        view.close()
    assert feed.drawn >= 2, feed.summary()
    assert data["runs"][0]["t"] == pytest.approx([s.t for s, _ in entries[:k]], abs=0.0)
    assert [s or "" for s in data["runs"][0]["status"]] == ["", *(str(st.step_status) for _, st in entries[1:k])]
