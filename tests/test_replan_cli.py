"""`crtraj replan` end to end on the paper's simulation 2 (problems/paper_dynamic.toml)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from conftest import PAPER, paper_copy

from crtraj.cli import main
from crtraj.io.problem import Problem
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent


def _clearance_from_waypoints(res: dict) -> np.ndarray:
    """Clearance (mm, minus D_sf) of each recorded backbone, from the file alone (obstacle states included)."""
    out = []
    body = res["robot"]["body_radius"]
    dsf = res["scene"]["safety_distance"]
    for w in res["waypoints"]:
        P = np.array(w["backbone"])
        C = np.array(w["obstacles"]["centers"])
        R = np.array(w["obstacles"]["radii"])
        d = np.linalg.norm(P[:, None, :] - C[None], axis=-1).min(axis=0) - R
        out.append(d.min() - body - dsf)
    return np.array(out)


def test_paper_simulation_2_reaches_the_goal_without_collision(tmp_path, capsys):
    out = tmp_path / "replan"
    assert main(["replan", str(PAPER), "--out", str(out), "--no-html"]) == 0
    text = capsys.readouterr().out
    assert "reached goal yes" in text and "collisions 0" in text
    res = json.loads((out / "run.json").read_text())
    assert res["kind"] == "replan" and res["status"] == "reached" and res["success"]
    s = res["summary"]
    assert s["collisions"] == 0 and s["safety_violations"] == 0
    assert s["final_tip_error_mm"] <= 0.5
    assert _clearance_from_waypoints(res).min() > 0.0
    # the obstacle states in the file are the scene's
    scene = Scene.from_table(Problem.load(PAPER).section("scene"))
    w = res["waypoints"][-1]
    _, R = scene.states(w["t"])
    np.testing.assert_allclose(w["obstacles"]["radii"], R)
    for name in ("run.json", "run.npz", "run.png"):
        assert (out / name).stat().st_size > 0


def test_paper_simulation_2_without_safety_collides(tmp_path, capsys):
    out = tmp_path / "nosafe"
    assert main(["replan", str(PAPER), "--out", str(out), "--no-safety", "--no-html", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "replan failed: unsafe" in err[0] and "touching an obstacle" in err[0]
    res = json.loads((out / "run.json").read_text())
    s = res["summary"]
    assert not res["success"]
    assert s["min_clearance_mm"] < 0.0 and s["collisions"] > 0
    assert _clearance_from_waypoints(res).min() < 0.0


def test_bad_problem_is_one_line_error(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    text = PAPER.read_text().replace(
        'robot = "robots/cdsr2.toml"', f'robot = "{PAPER.parent / "robots" / "cdsr2.toml"}"'
    )
    bad.write_text(text.replace("horizon = 10", "horizon = 0"))
    assert main(["replan", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "replan.horizon" in err[0]


def _short_problem(tmp_path: Path, duration: float) -> Path:
    """Simulation 2, `duration` s long, starting 10 mm further from the upper sphere (a live start must
    allow for the sphere growing while the first reference is planned), without the 4 ms step deadline: the
    feed's threads share this process, and what the test checks must not depend on how fast it runs."""
    values = {("loop", "duration"): duration, ("task", "start"): [-50.0, 110.0, 400.0]}
    return paper_copy(tmp_path, "short.toml", values)


def test_stream_writes_the_verified_run_to_a_device(tmp_path, capsys):
    # static obstacles: a slowed replay of the verified run is still safe, so it may be streamed
    frames = tmp_path / "frames.bin"
    out = tmp_path / "o"
    static = PAPER.parent / "paper_static.toml"
    rc = main(["replan", str(static), "--out", str(out), "--no-html", "--quiet",
               "--stream", f"file://{frames}", "--time-scale", "5"])  # fmt: skip
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "stream done" in text
    assert frames.stat().st_size > 1000
    assert (out / "stream.jsonl").stat().st_size > 0
    # (among moving obstacles a slowed replay is re-verified at its new times, as `crtraj stream` does:
    # tests/test_verify.py streams one that stays safe and refuses one that does not)


def test_live_feed_from_the_command_line(tmp_path, capsys, monkeypatch):
    """Sequenced with events, not timing: the bridge sends the scene frozen at its t = 0 state until the loop
    has passed its start check, and the loop reads the feed only after the first state has arrived, so the
    outcome does not depend on how long building the loop takes on a loaded machine."""
    import socket
    import threading
    import time

    import crtraj.app.replan
    from crtraj.control.loop._pacer import Pacer
    from crtraj.world.feed import ObstacleFeed

    scene = Scene.from_table(Problem.load(PAPER).section("scene"))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:  # a free port for the feed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    stop, started = threading.Event(), threading.Event()
    feeds: list[ObstacleFeed] = []

    class FirstStateFeed(ObstacleFeed):
        """The CLI's feed, returned only once the bridge's first state has been received."""

        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            feeds.append(self)
            assert self.wait_for(1, timeout=60.0), "the bridge never reached the feed"

    begin = Pacer.begin

    def begin_after_start_check(self) -> None:
        started.set()  # the start configuration has been checked against the t = 0 state
        begin(self)

    monkeypatch.setattr(crtraj.app.replan, "ObstacleFeed", FirstStateFeed)  # the feed `crtraj replan` opens
    monkeypatch.setattr(Pacer, "begin", begin_after_start_check)  # loop time 0: after the start check

    def send() -> None:
        t0 = time.monotonic()
        t_start: float | None = None
        while not stop.is_set():
            now = time.monotonic()
            if t_start is None and started.is_set():
                t_start = now
            t = 0.0 if t_start is None else now - t_start  # obstacle time: frozen until the run starts
            C, R = scene.states(t)
            states = [
                {"id": o.name, "center": C[i].tolist(), "radius": float(R[i]), "timestamp": now - t0}
                for i, o in enumerate(scene.obstacles)
            ]
            ObstacleFeed.send(("127.0.0.1", port), states)
            stop.wait(0.01)

    th = threading.Thread(target=send, daemon=True)
    th.start()
    try:
        out = tmp_path / "live"
        rc = main(["replan", str(_short_problem(tmp_path, 1.5)), "--out", str(out), "--no-html",
                   "--feed", f"udp://127.0.0.1:{port}", "--feed-max-age", "1.0"])  # fmt: skip
    finally:
        stop.set()
        th.join(5.0)
    cap = capsys.readouterr()
    text = cap.out
    assert feeds and started.is_set()
    assert rc == 1, cap.err  # 1.5 s is not enough to reach the goal: reported, not hidden
    assert f"udp://127.0.0.1:{port}" in text and "live obstacles" in text
    res = json.loads((out / "run.json").read_text())
    assert res["summary"]["live_obstacles"] is True
    assert res["status"] == "timeout"
    assert res["summary"]["safety_violations"] == 0
    counts = res["summary"]["status_counts"]
    assert counts.get("move", 0) + counts.get("suboptimal", 0) > 5  # it moved (suboptimal: at the iteration cap)
    assert res["feed"]["rejected"] == 0 and res["feed"]["accepted"] > 10 and res["options"]["feed"]["max_speed"] > 0
    # the recorded obstacle states are what was sent (radii within the scene's breathing ranges)
    radii = np.array([w["obstacles"]["radii"] for w in res["waypoints"]])
    assert np.all(radii[:, 0] <= 70.5) and np.all(radii[:, 1] <= 60.5)
