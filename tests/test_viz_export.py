"""The in-process scene recorder behind the standalone page: what it keeps of meshcat commands, and the page."""

from __future__ import annotations

import base64
import re

import umsgpack

from crtraj.viz.export import SceneRecorder, packb


def _cmd(kind: str, path: str, **fields) -> tuple[str, str, bytes]:
    return kind, path, packb({"type": kind, "path": path, **fields})


def _apply(rec: SceneRecorder, *cmds: tuple[str, str, bytes]) -> None:
    for c in cmds:
        rec.apply(*c)


def test_new_object_drops_the_old_objects_properties():
    """set_object replaces a node's object and starts it without properties; its transform stays."""
    rec = SceneRecorder()
    _apply(
        rec,
        _cmd("set_object", "/meshcat/a", object={"n": 1}),
        _cmd("set_property", "/meshcat/a", property="visible", value=False),
        _cmd("set_transform", "/meshcat/a", matrix=[1.0, 2.0]),
        _cmd("set_object", "/meshcat/a", object={"n": 2}),
    )
    assert [(c["type"], c.get("object")) for c in rec.commands()] == [("set_object", {"n": 2}), ("set_transform", None)]


def test_delete_removes_a_subtree_and_the_root_clears_everything():
    """delete of a path drops it and its children only; delete of '' empties the tree."""
    rec = SceneRecorder()
    _apply(
        rec,
        _cmd("set_object", "/meshcat/robot/a", object=1),
        _cmd("set_object", "/meshcat/robot/a/b", object=2),
        _cmd("set_object", "/meshcat/obstacles/0", object=3),
        _cmd("delete", "/meshcat/robot"),
        _cmd("delete", "/meshcat/not-there"),
    )
    assert [c["path"] for c in rec.commands()] == ["/meshcat/obstacles/0"]
    _apply(rec, _cmd("delete", ""))
    assert rec.commands() == []


def test_other_commands_leave_the_tree_alone():
    """Commands that are not scene commands (meshcat's server keeps none of them) record nothing."""
    rec = SceneRecorder()
    _apply(rec, _cmd("capture_image", "/meshcat/a"))
    assert rec.commands() == []


def test_standalone_page_replays_the_recorded_commands_in_order():
    """The page carries every recorded command, in tree order, as base64 msgpack, and no server link."""
    rec = SceneRecorder()
    _apply(
        rec,
        _cmd("set_object", "/meshcat/b", object="B"),
        _cmd("set_object", "/meshcat/a", object="A"),
        _cmd("set_animation", "/meshcat/a", animations=[]),
    )
    html = rec.static_html()
    blobs = re.findall(r"data:application/octet-binary;base64,([A-Za-z0-9+/=]+)", html)
    assert [umsgpack.unpackb(base64.b64decode(b)) for b in blobs] == rec.commands()
    assert [c["path"] for c in rec.commands()] == ["/meshcat/b", "/meshcat/a", "/meshcat/a"]
    assert "new MeshCat.Viewer" in html and "viewer.connect" not in html
