"""The page around the scene, in a real (headless Chromium) browser: the panel's numbers against run.json,
the closest-approach line where the page's camera projects it, the comparison's two robots, offline opening,
and `crtraj view --png/--mp4`."""

from __future__ import annotations

import io
import json
import re
import subprocess
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from conftest import require_tool
from matplotlib.colors import rgb_to_hsv

from crtraj.cli import main
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.viz.chromium import Chromium

PROBLEMS = Path(__file__).resolve().parent.parent / "problems"
W, H = 1280, 800
PANE = (W - 300, H - 210)  # the scene pane: the panel takes 300 px on the right, the plots 210 px at the bottom


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The paper's simulation 2, run by `crtraj replan`, and its page (`crtraj view --html`)."""
    out = tmp_path_factory.mktemp("run")
    assert main(["replan", str(PROBLEMS / "paper_dynamic.toml"), "--out", str(out), "--quiet", "--no-html"]) in (0, 1)
    assert main(["view", str(out / "run.json"), "--html", str(out / "view.html"), "--no-play"]) == 0
    return out


@pytest.fixture(scope="module")
def chromium() -> str:
    """Chromium's executable; skips locally (fails under CI=true) without one. The tests ask for it (or `browser`)
    before `run`, so that without Chromium they fail (skip) at once, not after the simulation."""
    return require_tool("chromium", "chromium-browser", "google-chrome", hint="Debian: apt-get install chromium")


@pytest.fixture(scope="module")
def browser(chromium):
    """A headless Chromium."""
    with Chromium(timeout=300.0) as b:
        yield b


def _doc(run):
    return json.loads((run / "run.json").read_text())


def _dense_closest(model, x, centers, radii):
    """Independent closest approach at one configuration: 2001 backbone points; (distance per sphere (mm) from
    the body's surface, the body point and the sphere point of the nearest pair)."""
    P = np.asarray(model.points(x[None], 2001)).reshape(-1, 3)
    C, R = np.asarray(centers), np.asarray(radii)
    gap = np.linalg.norm(P[:, None] - C[None], axis=-1) - R - model.robot.body_radius
    i = int(np.argmin(gap.min(axis=0)))
    p = P[np.argmin(gap[:, i])]
    u = (C[i] - p) / np.linalg.norm(C[i] - p)
    return gap.min(axis=0), p + model.robot.body_radius * u, C[i] - R[i] * u


def _panel(tab):
    return dict(
        tab.evaluate("[...document.querySelectorAll('#crtraj-hud td.v')].map(e => [e.dataset.key, e.textContent])")
    )


def _number(text):
    return float(re.match(r"\s*(-?[0-9.]+)", text).group(1))


def test_panel_shows_the_recorded_numbers_at_three_times(browser, run):
    """Seeked to three waypoints, the panel shows that step's status, tip error and iteration time from run.json,
    and each obstacle's distance (and clearance beyond D_sf) measured independently, at 2001 backbone points, on
    the recorded configuration."""
    doc = _doc(run)
    wps = doc["waypoints"]
    model = Model(load_robot(PROBLEMS / "robots" / "cdsr2.toml"))
    dsf = doc["scene"]["safety_distance"]
    tab = browser.open((run / "view.html").as_uri(), W, H, offline=True)
    try:
        for k in (3, len(wps) // 2, len(wps) - 2):
            t = wps[k]["t"] - wps[0]["t"]
            tab.seek(t + 1e-4)  # inside step k, before step k+1
            panel = _panel(tab)
            w = wps[k]
            assert tab.evaluate("document.getElementById('crtraj-time').textContent") == f"t = {t + 1e-4:.2f} s"
            assert panel["0-status"] == w["status"], k
            # The page keeps 6 decimals and the panel prints 2: a value rounded twice may differ from one rounded
            # once by one unit in the last printed place, so each shown number is checked to half a unit plus that
            # first rounding.
            assert panel["0-tip_error"].endswith(" mm"), k
            assert abs(_number(panel["0-tip_error"]) - w["tip_error"]) <= 0.005 + 1e-6, k
            assert " / 4.0 ms" in panel["0-iteration"], k
            assert abs(_number(panel["0-iteration"]) - 1e3 * w["iteration_time"]) <= 0.005 + 1e-3, k
            dist, _, _ = _dense_closest(model, np.array(w["x"]), w["obstacles"]["centers"], w["obstacles"]["radii"])
            shown = np.array([_number(panel[f"0-distance-{i}"]) for i in range(len(dist))])
            np.testing.assert_allclose(shown, dist, atol=0.1)
            beyond = np.array([_number(panel[f"0-clearance-{i}"]) for i in range(len(dist))])
            np.testing.assert_allclose(beyond, dist - dsf, atol=0.1)
    finally:
        tab.close()


def test_headline_answers_when_which_obstacle_how_close_and_whether_the_loop_held(browser, run):
    """The line under the controls says, without another file: the closest approach's time, obstacle and distance
    (found here independently: every waypoint at 2001 backbone points), the hold, fallback and deadline-miss
    counts that run.json's summary (the loop's own counts) gives, and the iterations over the deadline."""
    doc = _doc(run)
    wps, summary = doc["waypoints"], doc["summary"]
    model = Model(load_robot(PROBLEMS / "robots" / "cdsr2.toml"))
    names = [o["name"] for o in doc["scene"]["obstacle"]]
    dense = []
    for w in wps:
        d, _, _ = _dense_closest(model, np.array(w["x"]), w["obstacles"]["centers"], w["obstacles"]["radii"])
        dense.append(d)
    dense = np.array(dense)  # (waypoints, obstacles) mm, surface to surface
    dist = float(dense.min())
    tab = browser.open((run / "view.html").as_uri(), W, H, offline=True)
    try:
        text = tab.evaluate("document.getElementById('crtraj-verdict').textContent")
    finally:
        tab.close()
    m = re.search(r"closest: ([0-9.]+) mm to (\S+) at ([0-9.]+) s \(([-+0-9.]+) mm beyond D_sf", text)
    assert m, text
    t = np.array([w["t"] - wps[0]["t"] for w in wps])
    k, j = int(np.argmin(np.abs(t - float(m.group(3))))), names.index(m.group(2))
    assert abs(t[k] - float(m.group(3))) < 0.006, text  # a waypoint's time, to the 2 decimals shown
    assert abs(float(m.group(1)) - dist) < 0.1, (text, dist)
    assert dense[k, j] - dist < 0.1, (text, dense[k, j], dist)  # that obstacle at that time is the closest approach
    assert abs(float(m.group(4)) - (dist - doc["scene"]["safety_distance"])) < 0.1
    assert f"smallest distance over the executed motion {summary['min_distance_mm']:.2f} mm" in text, text
    assert summary["min_distance_mm"] <= dist + 0.1  # the executed samples include the frames
    counts = summary["status_counts"]
    assert f"{counts.get('hold', 0)} hold steps, {counts.get('fallback', 0)} fallback steps" in text, text
    assert f"{summary['deadline_misses']} deadline misses (solve later than 4 ms, unused)" in text, text
    over = sum(w["iteration_time"] > 4e-3 for w in doc["waypoints"] if w.get("iteration_time") is not None)
    assert f"{over} iterations over 4 ms" in text, text


def test_distance_line_is_where_the_camera_projects_it(browser, run, tmp_path):
    """At the closest approach (found independently), the pixels the closest-approach layer changes (the
    picture with it against the picture without it) lie on the segment between the two projected closest
    points and reach both ends."""
    doc = _doc(run)
    wps = doc["waypoints"]
    model = Model(load_robot(PROBLEMS / "robots" / "cdsr2.toml"))
    best = [_dense_closest(model, np.array(w["x"]), w["obstacles"]["centers"], w["obstacles"]["radii"]) for w in wps]
    k = int(np.argmin([b[0].min() for b in best]))
    _, a, b = best[k]
    tab = browser.open((run / "view.html").as_uri(), W, H, offline=True)
    try:
        tab.seek(wps[k]["t"] - wps[0]["t"])
        pa, pb = (np.array(tab.evaluate(f"crtrajView.project({p.tolist()})")) for p in (a, b))
        shots = []
        for on in ("true", "false"):
            tab.evaluate(f"viewer.set_property(['meshcat', 'closest'], 'visible', {on})")
            tab.seek(wps[k]["t"] - wps[0]["t"])
            shots.append(mpimg.imread(io.BytesIO(tab.screenshot()), format="png")[: PANE[1], : PANE[0], :3])
    finally:
        tab.close()
    ys, xs = np.nonzero(np.abs(shots[0] - shots[1]).max(axis=-1) > 0.1)
    assert len(xs) > 5, "the closest-approach layer changes nothing on screen"
    px = np.stack([xs, ys], axis=1).astype(float)
    ab = pb - pa
    s = np.clip((px - pa) @ ab / (ab @ ab), 0, 1)
    off = np.linalg.norm(px - (pa + s[:, None] * ab), axis=1)
    assert np.percentile(off, 95) < 4.0, (np.percentile(off, 95), pa, pb)
    for end in (pa, pb):
        assert np.linalg.norm(px - end, axis=1).min() < 3.0, end


def _green(img, min_sat=0.12):
    hsv = rgb_to_hsv(img)
    h = hsv[..., 0] * 360
    return (h >= 95) & (h < 150) & (hsv[..., 1] >= min_sat)


def test_compare_view_draws_two_robots(browser, run, tmp_path):
    """`crtraj view A B`: B's robot (here held at A's last configuration) is drawn as a ghost at its tip,
    where a page of A alone has no segment-2 green; both runs are in the panel."""
    doc = _doc(run)
    held = json.loads(json.dumps(doc))
    last = doc["waypoints"][-1]
    for w in held["waypoints"]:
        w["x"], w["tip"] = last["x"], last["tip"]
        w.pop("backbone", None)
    (tmp_path / "b.json").write_text(json.dumps(held))
    page = tmp_path / "ab.html"
    assert main(["view", str(run / "run.json"), str(tmp_path / "b.json"), "--html", str(page), "--no-play"]) == 0
    probe = f"crtrajView.project({last['tip']})"
    pictures = {}
    for name, path in (("ab", page), ("a", run / "view.html")):
        tab = browser.open(path.as_uri(), W, H, offline=True)
        try:
            tab.seek(0.0)
            tip = np.array(tab.evaluate(probe))
            panel = _panel(tab)
            pictures[name] = (mpimg.imread(io.BytesIO(tab.screenshot()), format="png")[..., :3], panel)
        finally:
            tab.close()
    x, y = (round(float(v)) for v in tip)
    for name, expect in (("ab", True), ("a", False)):
        img, panel = pictures[name]
        window = _green(img[max(0, y - 12) : y + 12, max(0, x - 12) : x + 12])
        assert (window.sum() > 20) == expect, (name, window.sum())
        assert ("1-status" in panel) == expect
    # A's own robot is at its start in both: segment-2 green at its first tip
    assert _green(pictures["ab"][0][: PANE[1], : PANE[0]]).sum() > 200


def test_page_opens_offline_and_loads_nothing(browser, run):
    """With the network off the page becomes ready (the browser would fail `open` otherwise) and it loaded no
    resource but its own file and data: URLs."""
    tab = browser.open((run / "view.html").as_uri(), W, H, offline=True)
    try:
        urls = tab.evaluate("performance.getEntriesByType('resource').map(e => e.name)")
        assert tab.evaluate("window.crtrajView.isReady()") is True
    finally:
        tab.close()
    assert all(u.startswith(("data:", "file:", "blob:")) for u in urls), urls
    html = (run / "view.html").read_text(encoding="utf-8")
    assert not re.search(r"""(src|href)=["']?https?:""", html)


def test_cli_png_is_a_picture_of_the_asked_size(chromium, run, tmp_path, capsys):
    out = tmp_path / "at2.png"
    assert main(["view", str(run / "run.json"), "--png", str(out), "--at", "2", "--size", "640x400"]) == 0
    assert f"wrote {out} (640x400 px at t = 2.00 s)" in capsys.readouterr().out
    img = mpimg.imread(out)
    assert img.shape[:2] == (400, 640)
    assert img[..., :3].reshape(-1, 3).std(axis=0).max() > 0.05  # not one flat colour


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--size", "640by400"], r"^crtraj: error: --size: expected WIDTHxHEIGHT in pixels"),
        (["--size", "10x10"], r"^crtraj: error: --size: width and height must be in \[64, 4096\] px, got 10x10$"),
        (["--at", "1e6"], r"^crtraj: error: --at: expected a time in \[0, [0-9.]+\] s, got 1000000.0$"),
    ],
)
def test_cli_picture_errors_are_one_line(run, tmp_path, capsys, args, message):
    out = tmp_path / "x.png"
    assert main(["view", str(run / "run.json"), "--png", str(out), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert re.match(message, err) and "\n" not in err, err
    assert not out.exists()


def test_cli_mp4_without_ffmpeg_says_so_in_one_line(run, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no ffmpeg (nor anything else) on PATH
    assert main(["view", str(run / "run.json"), "--mp4", str(tmp_path / "v.mp4")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("crtraj: error: --mp4: ffmpeg is not installed") and "\n" not in err, err


def test_cli_mp4_is_a_video_of_the_run(tmp_path, capsys):
    """A short plan at 4 fps: a video of the asked size with one frame per 1/4 s of the run."""
    require_tool("chromium", "chromium-browser", "google-chrome", hint="Debian: apt-get install chromium")
    ffprobe = require_tool("ffprobe", hint="Debian: apt-get install ffmpeg")
    robot = load_robot(PROBLEMS / "robots" / "cdsr2.toml")
    X = np.linspace([0.1, 0.0, 0.0, 0.2, 0.0], [0.5, -0.3, 0.4, -0.2, -40.0], 11)
    wps = [{"t": 0.2 * i, "x": X[i].tolist()} for i in range(len(X))]
    doc = {"kind": "plan", "robot": robot.to_dict(), "waypoints": wps, "status": "exact", "success": True}
    src = tmp_path / "p.json"
    src.write_text(json.dumps(doc))
    out = tmp_path / "p.mp4"
    assert main(["view", str(src), "--mp4", str(out), "--fps", "4", "--size", "320x240"]) == 0
    assert "wrote" in capsys.readouterr().out
    probe = subprocess.run(
        [ffprobe, "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
         "stream=width,height,nb_read_frames", "-of", "json", str(out)],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    stream = json.loads(probe.stdout)["streams"][0]
    assert (stream["width"], stream["height"]) == (320, 240)
    assert int(stream["nb_read_frames"]) == 9  # 0, 0.25, ..., 2.0 s
