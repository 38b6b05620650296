"""The standalone page: meshcat's scene tree kept in process, so the HTML export needs no server.

Every command the view sends is also applied here (`SceneRecorder.apply`), to a meshcat `SceneTree` (the tree
meshcat's own server keeps), so `static_html` gives exactly the page meshcat's server would give, with or without
a server. `packb` encodes a command as meshcat does, faster.
"""

from __future__ import annotations

import warnings
from typing import Any

import msgpack
import umsgpack

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    from meshcat.servers.tree import SceneTree, find_node, walk
    from meshcat.servers.zmqserver import ZMQWebSocketBridge


# The commands that change meshcat's scene tree (meshcat.servers.zmqserver.MESHCAT_COMMANDS in 0.3.x).
_SCENE_COMMANDS = ("set_transform", "set_object", "delete", "set_property", "set_animation")


def _ext(obj: Any) -> Any:
    if isinstance(obj, umsgpack.Ext):
        return msgpack.ExtType(obj.type, obj.data)
    raise TypeError(f"cannot pack {type(obj).__name__}")


def packb(data: Any, single_float: bool = False) -> bytes:
    """msgpack bytes of a lowered meshcat command: the C msgpack packs a long animation ~20x faster than
    meshcat's pure-Python umsgpack, with the same bytes. single_float: floats as float32 (5 bytes, not 9;
    7 significant digits, 1 um in a metre-sized scene), which the page's msgpack reads alike."""
    return msgpack.packb(data, default=_ext, use_bin_type=True, use_single_float=single_float)


class _PageReply:
    """Receives the page meshcat's scene export answers with (its reply-socket role)."""

    __slots__ = ("data",)

    def __init__(self) -> None:
        self.data = b""

    def send(self, data: bytes) -> None:
        self.data = data


class SceneRecorder:
    """meshcat's scene tree, kept in process: what a page replays, and the standalone page of it."""

    def __init__(self) -> None:
        self.tree = SceneTree()

    def apply(self, kind: str, path: str, data: bytes) -> None:
        """Apply one packed command (`kind`: set_object, set_transform, set_property, set_animation or
        delete) at the meshcat path `path` (``/a/b``), as meshcat's server does to its tree."""
        parts = [p for p in path.split("/") if p]
        if kind not in _SCENE_COMMANDS:
            return  # meshcat's server records nothing for any other command either
        if kind == "delete":
            if not parts:
                self.tree = SceneTree()
                return
            parent = find_node(self.tree, parts[:-1])
            if parts[-1] in parent:
                del parent[parts[-1]]
            return
        node = find_node(self.tree, parts)
        if kind == "set_object":
            node.object = data
            node.properties = []  # a new object starts without the old one's properties
        elif kind == "set_transform":
            node.transform = data
        elif kind == "set_property":
            node.properties.append(data)
        else:
            node.animation = data

    def commands(self) -> list[dict[str, Any]]:
        """The decoded commands that make up the scene, in the order a page replays them."""
        out = []
        for node in walk(self.tree):
            blobs = [node.object, *node.properties, node.transform, node.animation]
            out.extend(umsgpack.unpackb(b) for b in blobs if b is not None)
        return out

    def static_html(self) -> str:
        """The scene as one self-contained HTML page, meshcat's own export of it."""
        # meshcat (0.3.x) builds its standalone page only inside its server's request handler (the "get_scene"
        # branch of ZMQWebSocketBridge.handle_zmq); there is no public function for it. That branch reads only
        # `tree` and answers through `zmq_socket.send`, so it is called with a stand-in holding exactly those two;
        # pyproject pins meshcat to >=0.3.2,<0.4, the versions whose handler has that shape.
        holder = _PageSource(self.tree)
        ZMQWebSocketBridge.handle_zmq(holder, [b"get_scene"])
        return holder.zmq_socket.data.decode("utf-8")


class _PageSource:
    """The two fields meshcat's scene export reads: the tree and where the page goes."""

    __slots__ = ("tree", "zmq_socket")

    def __init__(self, tree: Any) -> None:
        self.tree = tree
        self.zmq_socket = _PageReply()
