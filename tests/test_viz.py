"""crtraj.viz.view and `crtraj view`: scene content, one key frame per waypoint, standalone HTML,
the 127.0.0.1-only server, and rendering in a real (headless Chromium) browser."""

from __future__ import annotations

import base64
import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import umsgpack
from conftest import default_sigint, require_tool
from matplotlib.colors import rgb_to_hsv
from scipy.optimize import least_squares

from crtraj.cli import main
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.fileio import atomic_write_json, to_jsonable
from crtraj.viz import ViewOptions, chromium
from crtraj.viz.geometry import cylinder_quat
from crtraj.viz.view import Visualizer

# paper simulation 1 / 2: start, goal and the two spheres (mm)
START = np.array([-50.0, 100.0, 390.0])
GOAL = np.array([10.0, -120.0, 170.0])
CENTERS = np.array([[0.0, 90.0, 330.0], [-10.0, -70.0, 250.0]])
N_WAYPOINTS = 21
PROBLEMS = Path(__file__).resolve().parent.parent / "problems"


def _ik(model, target, x0):
    """Configuration whose tip is at `target` (mm), by least squares on the model's tip and Jacobian."""
    lo, hi = model.robot.config_box()
    sol = least_squares(
        lambda x: model.tip_position(x) - target, x0, jac=lambda x: model.jacobian(x), bounds=(lo, hi), xtol=1e-12
    )
    assert np.linalg.norm(model.tip_position(sol.x) - target) < 1e-3
    return sol.x


def make_result(model, n=N_WAYPOINTS, kind="replan", obstacles=True, duration=10.0):
    """A result dict in the common format: straight-line interpolation between IK solutions for the
    paper's start and goal, two spheres whose centres drift and radii breathe (paper sim. 2)."""
    x0 = _ik(model, START, np.array([0.3, 0.3, 0.0, 0.0, 0.0]))
    x1 = _ik(model, GOAL, np.array([-0.3, -0.3, 0.0, 0.0, -100.0]))
    s = np.linspace(0.0, 1.0, n)
    X = x0 + s[:, None] * (x1 - x0)
    t = np.linspace(0.0, duration, n) + 0.5  # does not start at 0: the animation must shift it
    tips = model.tip_position(X)
    drift = np.stack([8 * np.sin(0.5 * t), 6 * np.cos(0.3 * t), np.zeros(n)], axis=-1)
    centers = CENTERS[None] + drift[:, None, :] * np.array([1.0, -1.0])[None, :, None]
    radii = np.stack([60 + 10 * np.sin(0.7 * t), 45 + 15 * np.cos(0.4 * t)], axis=-1)
    rng = np.random.default_rng(3)
    a = rng.uniform([-150, -150, 150], [150, 150, 420], (30, 3))
    edges = np.stack([a, a + rng.normal(0.0, 20.0, (30, 3))], axis=1)
    waypoints = []
    for i in range(n):
        w = {"t": t[i], "tip": tips[i], "x": X[i], "q": model.cables(X[i]), "backbone": model.points(X[i])}
        if obstacles:
            w["obstacles"] = {"centers": centers[i], "radii": radii[i]}
        waypoints.append(w)
    result = {
        "kind": kind,
        "crtraj_version": "test",
        "problem": {"name": "synthetic_sim1", "path": None, "seed": 0},
        "robot": model.robot.to_dict(),
        "scene": {"safety_distance": 5.0, "workspace": {"lo": [-150, -150, 0], "hi": [150, 150, 500]}},
        "task": {"start": START, "goal": GOAL, "goal_tolerance": 0.5},
        "status": "success",
        "success": True,
        "message": "",
        "waypoints": waypoints,
        "tree": {"edges": edges},
        "reference": {"tip": tips + np.array([0.0, 0.0, 3.0])},
    }
    return json.loads(json.dumps(to_jsonable(result)))  # exactly what a result file holds


@pytest.fixture(scope="module")
def result(model):
    return make_result(model)


@pytest.fixture(scope="module")
def shown(result):
    """An offline Visualizer with the result drawn (animation paused at the first waypoint)."""
    vis = Visualizer.for_result(result, play=False)
    yield vis
    vis.close()


def _objects(vis):
    """path -> decoded set_object command."""
    return {c["path"]: c for c in vis.scene_commands() if c["type"] == "set_object"}


def _last_transforms(vis):
    """path -> 4x4 matrix of the last set_transform (meshcat sends column-major lists)."""
    return {
        c["path"]: np.array(c["matrix"]).reshape(4, 4).T for c in vis.scene_commands() if c["type"] == "set_transform"
    }


def _animation(vis):
    anims = [c for c in vis.scene_commands() if c["type"] == "set_animation"]
    assert len(anims) == 1
    return {a["path"]: {t["name"]: t for t in a["clip"]["tracks"]} for a in anims[0]["animations"]}, anims[0]


def _html_commands(html):
    """The meshcat commands a static page replays, decoded from its data: URLs."""
    blobs = re.findall(r'fetch\("data:application/octet-binary;base64,([A-Za-z0-9+/=]+)"\)', html)
    return [umsgpack.unpackb(base64.b64decode(b)) for b in blobs]


def _keys(track):
    times = np.array([k["time"] for k in track["keys"]])
    values = np.array([k["value"] for k in track["keys"]])
    return times, values


def _rotate(q_xyzw, v):
    """Rotate v by three.js quaternions (..., 4) in x, y, z, w order."""
    q = np.asarray(q_xyzw)
    u, w = q[..., :3], q[..., 3:]
    return v + 2 * np.cross(u, np.cross(u, v) + w * v)


# ---------------------------------------------------------------- options
def test_view_options_read_from_table_and_reject_bad_values():
    o = ViewOptions.from_table(Table({"disc_spacing": 10.0, "segment_colors": ["#ff0000"], "play": False}, "view"))
    assert o.disc_spacing == 10.0 and o.segment_colors == ("#ff0000",) and o.play is False
    with pytest.raises(InputError, match=r"^view\.segment_colors\[0\]: expected a colour"):
        ViewOptions.from_table(Table({"segment_colors": ["red"]}, "view"))
    with pytest.raises(InputError, match=r"^view\.obstacle_opacity: must be <= 1"):
        ViewOptions.from_table(Table({"obstacle_opacity": 1.5}, "view"))
    with pytest.raises(InputError, match=r"^view\.disc_spcing: unknown key"):
        ViewOptions.from_table(Table({"disc_spcing": 1.0}, "view"))


def test_cylinder_quaternion_turns_y_axis_onto_direction():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(200, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = np.vstack([v, [[0, 0, 1.0], [0, 0, -1.0], [0, -1.0, 0], [1.0, 0, 0]]])  # incl. the singular -z
    q = cylinder_quat(v)  # w, x, y, z
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(_rotate(q[:, [1, 2, 3, 0]], np.array([0.0, 1.0, 0.0])), v, atol=1e-12)


# ------------------------------------------------------------------ scene
def test_scene_holds_every_named_object(shown, model, result):
    objs = _objects(shown)
    n_chords = 20  # 400 mm of backbone, a disc at least every 20 mm
    backbone = sorted(p for p in objs if p.startswith("/meshcat/robot/backbone/"))
    discs = sorted(p for p in objs if p.startswith("/meshcat/robot/discs/"))
    assert len(backbone) == n_chords and len(discs) == n_chords + 1
    for p in [
        "/meshcat/robot/base",
        "/meshcat/robot/rail",
        "/meshcat/obstacles/0",
        "/meshcat/obstacles/1",
        "/meshcat/markers/start",
        "/meshcat/markers/goal",
        "/meshcat/path/planned/line",
        "/meshcat/path/planned/dots",
        "/meshcat/path/executed/line",
        "/meshcat/tree",
        "/meshcat/workspace",
        "/meshcat/floor",
        "/meshcat/robot/tip",
        "/meshcat/shells/0",
        "/meshcat/shells/1",
        "/meshcat/closest/line",
        "/meshcat/closest/body",
        "/meshcat/closest/obstacle",
    ]:
        assert p in objs, p

    def geom(path):
        return objs[path]["object"]["geometries"][0]

    def mat(path):
        return objs[path]["object"]["materials"][0]

    # the backbone is a tube of the body radius clearance is measured with (3 mm), sent in metres; the discs
    # stand out of it by half that
    assert geom(backbone[0])["type"] == "CylinderGeometry"
    assert geom(backbone[0])["radiusTop"] == pytest.approx(model.robot.body_radius * 1e-3)
    assert geom(discs[0])["radiusTop"] == pytest.approx(1.5 * model.robot.body_radius * 1e-3)
    # one colour per segment: the first 10 chords are segment 1, the last 10 segment 2
    colors = [mat(p)["color"] for p in backbone]
    assert colors[:10] == [0x1F77B4] * 10 and colors[10:] == [0x2CA02C] * 10
    assert mat(discs[0])["color"] == 0x1F77B4 and mat(discs[-1])["color"] == 0x2CA02C
    # translucent unit spheres, scaled to the radius per frame
    assert geom("/meshcat/obstacles/0") == {**geom("/meshcat/obstacles/0"), "type": "SphereGeometry", "radius": 1.0}
    assert mat("/meshcat/obstacles/0")["transparent"] and mat("/meshcat/obstacles/0")["opacity"] < 1
    # each D_sf shell is fainter than its obstacle
    assert mat("/meshcat/shells/0")["opacity"] < mat("/meshcat/obstacles/0")["opacity"]
    # the tree holds both ends of every edge (float32, metres)
    tree = objs["/meshcat/tree"]["object"]["geometries"][0]["data"]["attributes"]["position"]
    pts = np.frombuffer(tree["array"].data, dtype=np.float32).reshape(-1, 3)
    np.testing.assert_allclose(pts, np.asarray(result["tree"]["edges"]).reshape(-1, 3) * 1e-3, atol=1e-6)
    # markers at the task's start and goal
    T = _last_transforms(shown)
    np.testing.assert_allclose(T["/meshcat/markers/start"][:3, 3], START * 1e-3, atol=1e-12)
    np.testing.assert_allclose(T["/meshcat/markers/goal"][:3, 3], GOAL * 1e-3, atol=1e-12)


def test_camera_frames_every_object(shown, result, model):
    """The robot at every waypoint, every start/goal marker and obstacle extreme (D_sf shell included) lies
    inside the camera's view cone (75 deg vertical, the page's 1.6:1 scene pane), looking at meshcat's origin,
    where the aim point is moved; and the view is filled: something comes close to its edge."""
    cmds = shown.scene_commands()
    shift = _last_transforms(shown)["/meshcat"]
    cam = [c for c in cmds if c["path"] == "/Cameras/default/rotated/<object>" and c["type"] == "set_property"]
    a, b, c = cam[-1]["value"]
    eye = np.array([a, -c, b])  # meshcat's "rotated" camera frame: local (a, b, c) is world (a, -c, b)
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    pts = [START, GOAL]
    dsf = result["scene"]["safety_distance"]
    for w in result["waypoints"]:
        for ctr, r in zip(w["obstacles"]["centers"], w["obstacles"]["radii"], strict=True):
            pts += [np.array(ctr) + (r + dsf) * e for e in np.vstack([np.eye(3), -np.eye(3)])]
    X = np.array([w["x"] for w in result["waypoints"]])
    pts += list(np.asarray(model.points(X, 21)).reshape(-1, 3))
    P = (shift @ np.c_[np.array(pts) * 1e-3, np.ones(len(pts))].T).T[:, :3] - eye
    depth = P @ fwd
    tan, aspect = np.tan(np.radians(75 / 2)), 1.6
    assert np.all(depth > 0.05)
    assert np.all(np.abs(P @ up) / depth < tan) and np.all(np.abs(P @ right) / depth < tan * aspect)
    # and it is framed tightly, and centred: both edges of the tighter direction are nearly reached
    v, h = (P @ up) / depth / tan, (P @ right) / depth / (tan * aspect)
    assert max(min(v.max(), -v.min()), min(h.max(), -h.min())) > 0.85, (v.min(), v.max(), h.min(), h.max())


def test_display_puts_every_cylinder_on_the_backbone(model):
    x = np.array([0.7, -0.4, -1.2, 0.9, -35.0])
    with Visualizer(model, server=False) as vis:
        vis.display(x)
        T = _last_transforms(vis)
    joints = model.points(x, 21) * 1e-3  # independent: the model's own 21 evenly spread points
    for i in range(20):
        M = T[f"/meshcat/robot/backbone/{i:03d}"]
        # a three.js cylinder of height 1 spans y in [-0.5, 0.5]; its ends must be the chord's ends
        ends = (M @ np.array([[0, -0.5, 0, 1], [0, 0.5, 0, 1]]).T).T[:, :3]
        np.testing.assert_allclose(ends, joints[i : i + 2], atol=1e-12)
        # radius directions stay unscaled (the backbone keeps its drawn radius)
        np.testing.assert_allclose(np.linalg.norm(M[:3, [0, 2]], axis=0), 1.0, atol=1e-12)
    for j in range(21):
        np.testing.assert_allclose(T[f"/meshcat/robot/discs/{j:03d}"][:3, 3], joints[j], atol=1e-12)
    np.testing.assert_allclose(T["/meshcat/robot/discs/020"][:3, 3], model.tip_position(x) * 1e-3, atol=1e-12)


def _interp_keys(times, values, t):
    """The page's straight-line interpolation of key values (K, ...) at times t (N,)."""
    flat = values.reshape(len(times), -1)
    return np.stack([np.interp(t, times, flat[:, j]) for j in range(flat.shape[1])], -1).reshape(len(t), -1)


def test_animation_keys_follow_the_run_within_half_a_millimetre(shown, result, model):
    """Keys sit at waypoint times (first and last included); between them the page's interpolation stays
    within 0.5 mm of every disc the model puts at every waypoint; obstacles, their D_sf shells and the
    closest-approach line follow the run at every key."""
    tracks, cmd = _animation(shown)
    wps = result["waypoints"]
    t = np.array([w["t"] for w in wps]) - wps[0]["t"]
    assert cmd["options"] == {"play": False, "repetitions": 1}
    times, _ = _keys(tracks["/meshcat/robot/discs/000"][".position"])
    k = np.searchsorted(t, times - 1e-6)
    np.testing.assert_allclose(times, t[k], atol=1e-6)  # float32 key times
    assert k[0] == 0 and k[-1] == len(wps) - 1 and 2 <= len(k) <= len(wps)
    for tr in tracks.values():  # every moving node is keyed at the same times
        for track in tr.values():
            np.testing.assert_array_equal(_keys(track)[0], times)
    X = np.array([w["x"] for w in wps])
    joints = np.asarray(model.points(X, 21)).reshape(len(wps), 21, 3) * 1e-3  # the model's discs, metres
    for j in range(21):
        _, pos = _keys(tracks[f"/meshcat/robot/discs/{j:03d}"][".position"])
        np.testing.assert_allclose(pos, joints[k, j], atol=2e-6)
        assert np.abs(_interp_keys(times, pos, t) - joints[:, j]).max() <= 0.5e-3 + 2e-6, j
    _, tip = _keys(tracks["/meshcat/robot/tip"][".position"])
    np.testing.assert_allclose(tip * 1e3, np.array([w["tip"] for w in wps])[k], atol=2e-3)
    dsf = result["scene"]["safety_distance"]
    for i in range(2):
        _, pos = _keys(tracks[f"/meshcat/obstacles/{i}"][".position"])
        _, scale = _keys(tracks[f"/meshcat/obstacles/{i}"][".scale"])
        _, shell = _keys(tracks[f"/meshcat/shells/{i}"][".scale"])
        np.testing.assert_allclose(pos * 1e3, [wps[j]["obstacles"]["centers"][i] for j in k], atol=2e-3)
        radii = np.array([wps[j]["obstacles"]["radii"][i] for j in k])
        np.testing.assert_allclose(scale * 1e3, np.repeat(radii[:, None], 3, axis=1), atol=2e-3)
        np.testing.assert_allclose(shell * 1e3, np.repeat(radii[:, None] + dsf, 3, axis=1), atol=2e-3)
    # the closest-approach line runs from the body's surface to the nearest sphere's surface
    _, a = _keys(tracks["/meshcat/closest/body"][".position"])
    _, b = _keys(tracks["/meshcat/closest/obstacle"][".position"])
    dense = np.asarray(model.points(X[k], 401)).reshape(len(k), 401, 3)
    C = np.array([wps[j]["obstacles"]["centers"] for j in k])
    R = np.array([wps[j]["obstacles"]["radii"] for j in k])
    gap = np.linalg.norm(dense[:, :, None] - C[:, None], axis=-1).min(axis=1) - R - model.robot.body_radius
    # (measured at 4 mm spacing: within 0.1 mm outside the spheres; a backbone through a sphere's centre is
    # within half the spacing, where the distance has a kink)
    g = gap.min(axis=1)
    assert np.all(np.abs(np.linalg.norm(b - a, axis=1) * 1e3 - np.abs(g)) <= np.where(g > 0, 0.1, 2.0))
    on_sphere = np.linalg.norm(b[:, None] * 1e3 - C, axis=-1) - R
    np.testing.assert_allclose(np.abs(on_sphere).min(axis=1), 0.0, atol=2e-3)
    body = np.linalg.norm(dense - a[:, None] * 1e3, axis=-1).min(axis=1)
    np.testing.assert_allclose(body, model.robot.body_radius, atol=0.05)


def test_show_waypoint_moves_robot_and_obstacles(result, model):
    with Visualizer.for_result(result, play=False) as vis:
        vis.show_waypoint(7)
        T = _last_transforms(vis)
        with pytest.raises(InputError, match="show_waypoint: k must be in"):
            vis.show_waypoint(len(result["waypoints"]))
    w = result["waypoints"][7]
    for i in range(2):
        M = T[f"/meshcat/obstacles/{i}"]
        np.testing.assert_allclose(M[:3, 3], np.array(w["obstacles"]["centers"][i]) * 1e-3, atol=1e-12)
        np.testing.assert_allclose(M[:3, :3], np.eye(3) * w["obstacles"]["radii"][i] * 1e-3, atol=1e-12)
    np.testing.assert_allclose(T["/meshcat/robot/discs/020"][:3, 3], np.array(w["tip"]) * 1e-3, atol=1e-12)


def test_plan_result_draws_its_tips_as_the_planned_path(model):
    res = make_result(model, n=5, kind="plan")
    del res["reference"], res["tree"]
    for w in res["waypoints"]:
        del w["tip"]  # optional: computed from x
    with Visualizer.for_result(res) as vis:
        objs = _objects(vis)
    assert "/meshcat/path/executed/line" not in objs and "/meshcat/tree" not in objs
    pos = objs["/meshcat/path/planned/line"]["object"]["geometries"][0]["data"]["attributes"]["position"]
    pts = np.frombuffer(pos["array"].data, dtype=np.float32).reshape(-1, 3)
    X = np.array([w["x"] for w in res["waypoints"]])
    np.testing.assert_allclose(pts, model.tip_position(X) * 1e-3, atol=1e-6)


# --------------------------------------------------------------- export
def test_static_html_is_standalone_and_replays_the_scene(shown, tmp_path):
    out = shown.save_html(tmp_path / "sub" / "view.html")
    assert out == tmp_path / "sub" / "view.html"
    assert sorted(p.name for p in out.parent.iterdir()) == ["view.html"]  # atomic: no temp file left
    html = out.read_text(encoding="utf-8")
    assert "new MeshCat.Viewer" in html and "viewer.connect" not in html  # no websocket, no server
    assert not re.search(r"<script[^>]+src=", html)  # the viewer's JavaScript is inlined
    assert _html_commands(html) == shown.scene_commands()
    assert shown.jupyter_cell().data.count("srcdoc=") == 1  # notebook cell: the same page inline


def test_fast_packer_gives_meshcats_exact_bytes(shown):
    """crtraj packs commands with the C msgpack when present; meshcat's umsgpack must agree byte for byte."""
    from crtraj.viz.export import packb

    cmds = shown.scene_commands()
    assert {c["type"] for c in cmds} >= {"set_object", "set_transform", "set_property", "set_animation"}
    for c in cmds:
        assert packb(c) == umsgpack.packb(c)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: r.pop("waypoints"), r"^waypoints: missing"),
        (lambda r: r.update(waypoints=[]), r"^waypoints: expected a non-empty list"),
        (lambda r: r["waypoints"][2].update(x=[0.0] * 4), r"^waypoints\[2\]\.x: expected shape \(5\)"),
        (lambda r: r["waypoints"][3].update(t=-1.0), r"^waypoints\[3\]\.t: time goes backwards"),
        (lambda r: r["waypoints"][1]["obstacles"]["radii"].pop(), r"^waypoints\[1\]\.obstacles\.radii: expected"),
        (lambda r: r["waypoints"][4].pop("obstacles"), r"^waypoints\[4\]\.obstacles: 0 obstacles, but"),
        (lambda r: r["tree"].update(edges=[[1, 2, 3]]), r"^tree\.edges: expected shape"),
        (lambda r: r.update(kind="fly"), r"^kind: must be plan or replan"),
        (lambda r: r["robot"].update(cable_radius=-1), r"^robot\.cable_radius: must be >= 0.001"),
        (lambda r: r["waypoints"][1].update(t=1e300), r"^waypoints\[1\]\.t: must be within \+-1e\+06"),
        (
            lambda r: r["waypoints"][1]["obstacles"]["centers"][0].__setitem__(0, 1e308),
            r"^waypoints\[1\]\.obstacles\.centers: values must be within",
        ),
        (lambda r: r["waypoints"][1].update(x=["1", 0, 0, 0, 0]), r"^waypoints\[1\]\.x: expected numbers"),
    ],
)
def test_bad_result_names_the_field(result, edit, message):
    bad = json.loads(json.dumps(result))
    edit(bad)
    with pytest.raises(InputError, match=message):
        Visualizer.for_result(bad)


def test_result_of_another_robot_is_refused(result, model):
    other = json.loads(json.dumps(result))
    other["robot"]["segment"][1]["length"] = 150.0
    with Visualizer(model, server=False) as vis, pytest.raises(InputError, match=r"^robot: the result was made for"):
        vis.show_result(other)


# ---------------------------------------------------------------- server
def _gone(pid, wait=10.0):
    """True once process `pid` has exited (a zombie counts as exited)."""
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        try:
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                return True
        except FileNotFoundError:
            return True
        time.sleep(0.05)
    return False


def _server_children(pid):
    """Pids of the crtraj.viz.server processes started by process `pid` (Linux /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
                cmd = (d / "cmdline").read_bytes().split(b"\0")
            except (FileNotFoundError, ProcessLookupError, IndexError):
                continue
            if ppid == pid and b"crtraj.viz.server" in cmd:
                out.append(int(d.name))
    return out


def _listening(pid):
    """(ip, port) of every listening TCP socket of process `pid` (Linux /proc)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        m = re.match(r"socket:\[(\d+)\]", os.readlink(fd))
        if m:
            inodes.add(m.group(1))
    out = []
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        if not os.path.exists(table):
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] != "0A" or f[9] not in inodes:  # 0A: LISTEN
                continue
            addr, port = f[1].split(":")
            ip = "v6:" + addr if v6 else ".".join(str(b) for b in reversed(bytes.fromhex(addr)))
            out.append((ip, int(port, 16)))
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads listening sockets from /proc (Linux)")
def test_server_listens_on_loopback_only_and_serves_the_same_scene(result):
    import meshcat

    vis = Visualizer.for_result(result, server=True)
    try:
        assert vis.url.startswith("http://127.0.0.1:") and vis.zmq_url.startswith("tcp://127.0.0.1:")
        socks = _listening(vis.server_pid)
        web_port = int(vis.url.split(":")[2].split("/")[0])
        assert sorted(p for _, p in socks) == sorted([web_port, int(vis.zmq_url.rsplit(":", 1)[1])])
        assert all(ip == "127.0.0.1" for ip, _ in socks), socks
        page = urllib.request.urlopen(vis.url, timeout=20).read().decode()
        assert "MeshCat" in page and 'id="crtraj-hud"' in page  # the full page: meshcat's scene inside crtraj's
        assert "MeshCat" in urllib.request.urlopen(vis.scene_url, timeout=20).read().decode()
        # meshcat's own client asks the server for its static export: ours is exactly that inside crtraj's page
        from crtraj.viz.page import wrap_page

        other = meshcat.Visualizer(zmq_url=vis.zmq_url)
        assert wrap_page(other.static_html(), vis.page_data()) == vis.static_html()
        assert f'src="{vis.url}"' in vis.jupyter_cell().data
    finally:
        pid = vis.server_pid
        vis.close()
    assert _gone(pid)  # (its port may be taken by another server right away: check the process)
    vis.close()  # a second close is harmless


def _segment_distance(p, a, b):
    """Distance from points p (..., 3) to the nearest of the segments a[i]-b[i] (S, 3)."""
    ab = b - a
    s = np.clip(np.einsum("...sk,sk->...s", p[..., None, :] - a, ab) / np.einsum("sk,sk->s", ab, ab), 0.0, 1.0)
    return np.linalg.norm(p[..., None, :] - (a + s[..., None] * ab), axis=-1).min(axis=-1)


def test_real_replan_run_is_drawn_on_its_recorded_backbone(tmp_path, capsys):
    """`crtraj replan` on the paper's simulation 2: at every key frame the recorded backbone points (computed
    by the replanner) lie on the drawn chain of cylinders, and the obstacles have the recorded radii."""
    assert main(["replan", str(PROBLEMS / "paper_dynamic.toml"), "--out", str(tmp_path), "--quiet", "--no-html"]) in (
        0,
        1,
    )
    capsys.readouterr()
    result = json.loads((tmp_path / "run.json").read_text())
    wps = result["waypoints"]
    t = np.array([w["t"] for w in wps]) - wps[0]["t"]
    with Visualizer.for_result(result, play=False) as vis:
        tracks, _ = _animation(vis)
    n_discs = len([p for p in tracks if p.startswith("/meshcat/robot/discs/")])
    times = _keys(tracks["/meshcat/robot/discs/000"][".position"])[0]
    # the key times are float32 (about 2e-6 s apart near 30 s): take the nearest waypoint, the steps are 0.1 s apart
    k = np.argmin(np.abs(t[None, :] - times[:, None]), axis=1)
    np.testing.assert_allclose(times, t[k], atol=1e-5)
    joints = np.stack([_keys(tracks[f"/meshcat/robot/discs/{j:03d}"][".position"])[1] for j in range(n_discs)], 1)
    assert joints.shape[:2] == (len(k), n_discs) and len(k) >= 10
    # PCC arcs between discs 20 mm apart bow at most R (1 - cos(10 mm / R)) < 0.8 mm away from the chord
    for i, w in enumerate(wps[j] for j in k):
        d = _segment_distance(np.array(w["backbone"]) * 1e-3, joints[i, :-1], joints[i, 1:])
        assert d.max() < 1.0e-3, (i, d.max())
    m = len(wps[0]["obstacles"]["radii"])
    for i in range(m):
        _, scale = _keys(tracks[f"/meshcat/obstacles/{i}"][".scale"])
        np.testing.assert_allclose(scale[:, 0] * 1e3, [wps[j]["obstacles"]["radii"][i] for j in k], atol=2e-3)


# ------------------------------------------------------------------- CLI
def test_cli_view_html_writes_file_and_prints_path(result, tmp_path, capsys):
    src = atomic_write_json(tmp_path / "run.json", result)
    out = tmp_path / "view.html"
    assert main(["view", str(src), "--html", str(out), "--no-play"]) == 0
    printed = capsys.readouterr().out
    assert str(out) in printed
    html = out.read_text()
    assert "new MeshCat.Viewer" in html
    anims = [c for c in _html_commands(html) if c["type"] == "set_animation"]
    assert anims[0]["options"]["play"] is False


def test_cli_view_errors_are_one_line(tmp_path, capsys):
    assert main(["view", str(tmp_path / "missing.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("crtraj: error:") and "missing.json: no such file" in err and "\n" not in err
    (tmp_path / "bad.json").write_text('{"kind": "plan", "robot": {}}')
    assert main(["view", str(tmp_path / "bad.json")]) == 2
    assert "robot.segment: missing" in capsys.readouterr().err


class _Lines:
    """Reads a process's stdout on a thread, so waiting for a line can time out."""

    def __init__(self, stream):
        self.queue = queue.Queue()
        self.seen = []
        threading.Thread(target=lambda: [self.queue.put(line) for line in stream], daemon=True).start()

    def wait_for(self, pattern, timeout):
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.queue.get(timeout=left)
            except queue.Empty:
                break
            self.seen.append(line)
            m = re.search(pattern, line)
            if m:
                return m
        raise AssertionError(f"no line matching {pattern!r} within {timeout} s: {self.seen}")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sends SIGINT, reads processes from /proc (Linux)")
def test_cli_view_serves_until_ctrl_c(result, tmp_path):
    src = atomic_write_json(tmp_path / "run.json", result)
    proc = subprocess.Popen(
        [sys.executable, "-m", "crtraj.cli", "view", str(src), "--no-browser"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
    )
    try:
        lines = _Lines(proc.stdout)
        url = lines.wait_for(r"at (http://127\.0\.0\.1:\d+/crtraj/)", 60).group(1)
        lines.wait_for("Ctrl-C", 10)
        page = urllib.request.urlopen(url, timeout=20).read().decode()
        assert "MeshCat" in page and 'id="crtraj-hud"' in page  # the full page
        servers = _server_children(proc.pid)
        assert len(servers) == 1
        proc.send_signal(signal.SIGINT)
        lines.wait_for("stopped", 300)  # hang bounds only: a loaded machine may take long to shut down
        proc.wait(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, proc.stderr.read()
    assert _gone(servers[0])  # the server went with it


# --------------------------------------------------------------- browser
# Headless Chromium is driven over the DevTools protocol on a pipe: a page is captured once a condition
# holds in it (every scene command handled, the animation loaded and, if it plays, finished), never after
# a fixed or virtual-time window, so a slow machine only takes longer. BROWSER_HANG_S bounds a hang only.
BROWSER_HANG_S = 600.0
# the library's flags (crtraj.viz.chromium), at this module's window size
CHROMIUM_FLAGS = (*chromium.FLAGS, "--window-size=1024,768", "--remote-debugging-pipe")

# Runs in every page before its own scripts: counts the meshcat commands the viewer has handled (meshcat's
# bundle assigns self.MeshCat once; the setter wraps Viewer.handle_command then) and records page errors.
_PAGE_HOOK = """
(() => {
  const state = (window.__crtraj = { handled: 0, errors: [] });
  addEventListener("error", (e) => state.errors.push(String(e.message)));
  addEventListener("unhandledrejection", (e) => state.errors.push(String(e.reason)));
  let lib;
  Object.defineProperty(window, "MeshCat", {
    configurable: true,
    get: () => lib,
    set(value) {
      lib = value;
      const handle = value.Viewer.prototype.handle_command;
      value.Viewer.prototype.handle_command = function (cmd) {
        handle.call(this, cmd);
        state.handled += 1;
      };
    },
  });
})();
"""

# Resolves once N commands are handled and the animation is loaded and not playing (paused, or played to
# its end: meshcat stops playing when every action has finished), after two more frames so the final pose
# is on screen; rejects at the first page error.
_PAGE_READY = """
new Promise((resolve, reject) => {
  const s = window.__crtraj;
  const check = () => {
    if (s.errors.length) return reject(new Error(s.errors.join("; ")));
    const v = window.viewer;
    if (v && s.handled >= %d && v.animator.actions.length > 0 && !v.animator.playing) {
      v.set_dirty();
      requestAnimationFrame(() => requestAnimationFrame(() => resolve({ handled: s.handled, time: v.animator.time })));
    } else {
      requestAnimationFrame(check);
    }
  };
  check();
})
"""


class _Browser:
    """One headless Chromium; `capture` opens a page in a new tab and returns its picture."""

    def __init__(self, exe: str, profile: Path):
        profile.mkdir(parents=True, exist_ok=True)
        # the DevTools pipe: Chromium reads commands on its fd 3 and writes replies on its fd 4; a Python
        # trampoline moves the pipe ends there and execs Chromium (subprocess can only keep fd numbers)
        to_r, to_w = os.pipe()
        from_r, from_w = os.pipe()
        self._log = (profile / "chromium.log").open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", chromium.TRAMPOLINE, str(to_r), str(from_w), exe,
             *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT, pass_fds=(to_r, from_w),
        )  # fmt: skip
        self._log_path = profile / "chromium.log"
        os.close(to_r)
        os.close(from_w)
        self._out = os.fdopen(to_w, "wb", buffering=0)
        self._replies: queue.Queue = queue.Queue()
        self._next_id = 0
        self._events: list[dict] = []
        threading.Thread(target=self._read, args=(from_r,), daemon=True).start()

    def _read(self, fd: int) -> None:
        buf = b""
        with os.fdopen(fd, "rb", buffering=0) as f:
            while chunk := f.read(1 << 20):
                *msgs, buf = (buf + chunk).split(b"\0")
                for m in msgs:
                    self._replies.put(json.loads(m))
        self._replies.put(None)  # Chromium closed the pipe

    def _fail(self, what: str) -> AssertionError:
        tail = self._log_path.read_text(errors="replace")[-3000:]
        return AssertionError(f"chromium: {what}; exit code {self.proc.poll()}; log tail:\n{tail}")

    def _next(self, what: str, deadline: float) -> dict:
        """The next message from Chromium; fails at the hang bound or when the pipe closes."""
        try:
            msg = self._replies.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise self._fail(f"no {what} within {BROWSER_HANG_S:.0f} s (hung)") from None
        if msg is None:
            self._replies.put(None)
            raise self._fail(f"pipe closed while waiting for {what}")
        return msg

    def call(self, method: str, session: str | None = None, **params):
        """Send one DevTools command and wait for its reply (events meanwhile are kept for `wait_event`)."""
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        self._out.write(json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + BROWSER_HANG_S  # a hang bound, never a window a slow page could miss
        while True:
            reply = self._next(f"reply to {method}", deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise self._fail(f"{method}: {reply['error']}")
                return reply["result"]
            if "method" in reply:
                self._events.append(reply)

    def wait_event(self, method: str, session: str) -> dict:
        """Wait for the event `method` of `session` (one already received counts)."""
        deadline = time.monotonic() + BROWSER_HANG_S
        while True:
            for i, ev in enumerate(self._events):
                if ev["method"] == method and ev.get("sessionId") == session:
                    return self._events.pop(i)
            ev = self._next(f"event {method}", deadline)
            if "method" in ev:
                self._events.append(ev)

    def capture(self, page: Path | str, n_commands: int, png: Path, probe: str = "null") -> tuple[np.ndarray, dict]:
        """Open `page` (an HTML file or a URL), wait until its viewer has handled `n_commands` meshcat
        commands and its animation is at rest, and return the picture, RGB (768, 1024, 3) in [0, 1],
        and the page's state ({"handled": commands, "time": animation time in s, "probe": the value of the
        JavaScript expression `probe` evaluated just before the picture})."""
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        try:
            self.call("Emulation.setDeviceMetricsOverride", session, width=1024, height=768,
                      deviceScaleFactor=1, mobile=False)  # fmt: skip
            self.call("Page.addScriptToEvaluateOnNewDocument", session, source=_PAGE_HOOK)
            self.call("Page.enable", session)
            self.call("Page.navigate", session, url=page.resolve().as_uri() if isinstance(page, Path) else page)
            self.wait_event("Page.loadEventFired", session)  # the page's own document (and hook) is in place
            ready = self.call("Runtime.evaluate", session, expression=_PAGE_READY % n_commands,
                              awaitPromise=True, returnByValue=True)  # fmt: skip
            if "exceptionDetails" in ready:
                raise self._fail(f"page {page}: {ready['exceptionDetails']}")
            probed = self.call("Runtime.evaluate", session, expression=probe, returnByValue=True)
            if "exceptionDetails" in probed:
                raise self._fail(f"page {page}: probe: {probed['exceptionDetails']}")
            ready["result"]["value"]["probe"] = probed["result"].get("value")
            shot = self.call("Page.captureScreenshot", session, format="png")
        finally:
            self.call("Target.closeTarget", targetId=target)
            self._events = [ev for ev in self._events if ev.get("sessionId") != session]
        png.write_bytes(base64.b64decode(shot["data"]))
        return mpimg.imread(png)[..., :3], ready["result"]["value"]

    def close(self) -> None:
        try:
            if self.proc.poll() is None:
                self.call("Browser.close")
            self.proc.wait(timeout=BROWSER_HANG_S)
        except (AssertionError, OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        finally:
            self._out.close()
            self._log.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    """A headless Chromium for this module's browser tests; skips locally (fails under CI=true) without one."""
    exe = require_tool("chromium", "chromium-browser", "google-chrome", hint="Debian: apt-get install chromium")
    b = _Browser(exe, tmp_path_factory.mktemp("chromium") / "profile")
    yield b
    b.close()


def _mask(img, hue_lo, hue_hi, min_sat):
    """Pixels whose hue (deg) is in [hue_lo, hue_hi) (wrapping past 360) with saturation >= min_sat."""
    hsv = rgb_to_hsv(img)
    h = hsv[..., 0] * 360
    inside = (h >= hue_lo) & (h < hue_hi) if hue_lo < hue_hi else (h >= hue_lo) | (h < hue_hi)
    return inside & (hsv[..., 1] >= min_sat) & (hsv[..., 2] >= 0.15)


# hue windows of the default colours: segment 1 #1f77b4, segment 2 #2ca02c, obstacles #d62728
# (translucent, so less saturated), goal marker #e000e0, start marker #ffb000
BLUE, GREEN, RED = (190, 222, 0.3), (105, 140, 0.3), (340, 10, 0.2)
MAGENTA, AMBER = (290, 310, 0.5), (36, 48, 0.5)


def _scene_px(img):
    """The scene pane of a 1024 x 768 page: the page's panels take 300 px on the right, 210 px at the bottom."""
    return img[: 768 - 210, : 1024 - 300]


def _centroid(mask):
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean(), ys.mean()])


def _n_commands(vis: Visualizer) -> int:
    return len(vis.scene_commands())


def test_browser_renders_robot_and_obstacles(browser, model, result, tmp_path):
    vis = Visualizer.for_result(result, play=False)
    img, _ = browser.capture(vis.save_html(tmp_path / "sim1.html"), _n_commands(vis), tmp_path / "sim1.png")
    assert img.shape == (768, 1024, 3)
    img = _scene_px(img)
    # not blank: a failed WebGL context leaves one flat colour
    assert img.reshape(-1, 3).std(axis=0).max() > 0.05
    assert len(np.unique((img * 255).astype(np.uint8).reshape(-1, 3), axis=0)) > 200
    n_blue, n_green, n_red = (int(_mask(img, *c).sum()) for c in (BLUE, GREEN, RED))
    assert n_blue > 80 and n_green > 80, (n_blue, n_green)
    assert n_red > 3000, n_red
    # control: the same run without obstacles has no obstacle colour, robot colours stay
    bare = Visualizer.for_result(make_result(model, obstacles=False), play=False)
    img2, _ = browser.capture(bare.save_html(tmp_path / "bare.html"), _n_commands(bare), tmp_path / "bare.png")
    img2 = _scene_px(img2)
    assert int(_mask(img2, *RED).sum()) < 50
    assert int(_mask(img2, *BLUE).sum()) > 80 and int(_mask(img2, *GREEN).sum()) > 80


def test_browser_animation_carries_robot_from_start_to_goal(browser, model, tmp_path):
    """Paused, the tip segment is at the start marker; played (a 2 s run, in real time) until meshcat
    reports the animation finished, it is at the goal marker (both projected with the page's camera)."""
    result = make_result(model, duration=2.0)
    probe = f"[crtrajView.project({START.tolist()}), crtrajView.project({GOAL.tolist()})]"
    still = Visualizer.for_result(result, play=False)
    paused, state0 = browser.capture(
        still.save_html(tmp_path / "a.html"), _n_commands(still), tmp_path / "a.png", probe
    )
    moving = Visualizer.for_result(result, play=True)
    played, state1 = browser.capture(
        moving.save_html(tmp_path / "b.html"), _n_commands(moving), tmp_path / "b.png", probe
    )
    paused, played = _scene_px(paused), _scene_px(played)
    # the page's own animation clock: at the start when paused, at the end (2 s) once played through
    assert state0["time"] == 0.0 and state1["time"] == pytest.approx(2.0, abs=1e-6), (state0, state1)
    start_px, goal_px = (np.array(p) for p in state0["probe"])
    assert np.linalg.norm(start_px - goal_px) > 100
    for img, near, far in ((paused, start_px, goal_px), (played, goal_px, start_px)):
        # the tip: the segment-2 pixel farthest from segment 1
        ys, xs = np.nonzero(_mask(img, *GREEN))
        green = np.stack([xs, ys], axis=1)
        tip = green[np.argmax(np.linalg.norm(green - _centroid(_mask(img, *BLUE)), axis=1))]
        d_near, d_far = np.linalg.norm(tip - near), np.linalg.norm(tip - far)
        assert d_near < 15 and d_far > 100, (d_near, d_far)


def test_browser_live_server_page_matches_standalone_page(browser, result, tmp_path):
    """The page served over the websocket renders the same picture as meshcat's standalone scene file."""
    vis = Visualizer.for_result(result, server=True, play=False)
    try:
        n = _n_commands(vis)
        live, _ = browser.capture(vis.scene_url, n, tmp_path / "live.png")
        scene = tmp_path / "static.html"
        scene.write_text(vis.scene_html(), encoding="utf-8")
        static, _ = browser.capture(scene, n, tmp_path / "static.png")
    finally:
        vis.close()
    assert int(_mask(live, *GREEN).sum()) > 80 and int(_mask(live, *RED).sum()) > 3000
    assert np.abs(live - static).mean() < 0.01
