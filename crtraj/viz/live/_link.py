"""The view's link to a live meshcat server: meshcat's ViewerWindow interface over ZMQ, plus the in-process copy.

`MeshcatWindow` is what `meshcat.Visualizer(window=...)` talks to (meshcat's public hook for a custom window):
every command goes to the in-process `SceneRecorder` (so the standalone page works offline) and, when connected,
to a meshcat server, either one this window starts (`crtraj.viz.server`, bound to 127.0.0.1, stopped with the
window) or a running one at a ZMQ address. Every reply is awaited at most `timeout` s.
"""

from __future__ import annotations

import subprocess
import weakref
import webbrowser
from typing import Any

import msgpack
import numpy as np
import zmq

from crtraj.viz import server as meshcat_server
from crtraj.viz.export import SceneRecorder, packb


class ServerLateError(RuntimeError):
    """The meshcat server did not answer one command within the window's timeout (the link stays usable)."""


class MeshcatWindow:
    """meshcat's ViewerWindow interface: every command goes to the in-process scene recorder and, when
    connected, to a meshcat server.

    zmq_url: a running server's ZMQ address (None: none); start_server: start one as a child process (at
    niceness `nice`, 0-19); timeout: s for the server's start-up and for every reply.
    """

    def __init__(self, zmq_url: str | None, start_server: bool, timeout: float, nice: int = 0) -> None:
        self.recorder = SceneRecorder()
        self._timeout_ms = int(timeout * 1000)
        self.server_proc: subprocess.Popen[bytes] | None = None
        self._log = None
        self._sock = None
        self.zmq_url: str | None = None
        self.web_url: str | None = None
        if start_server:
            self.server_proc, self._log, self.zmq_url, self.web_url = meshcat_server.start_server(timeout, nice)
            self._connect()
        elif zmq_url is not None:
            self.zmq_url = zmq_url
            self._connect()
            self.web_url = self._request(b"url").decode("utf-8")
            # meshcat's client does the same: a url request before any browser
            # connects leaves the server's receive callback stuck until a reconnect.
            self._sock.close(linger=0)
            self._connect()
        self._finalizer = weakref.finalize(self, meshcat_server.stop_server, self.server_proc, self._sock, self._log)

    def _connect(self) -> None:
        sock = zmq.Context.instance().socket(zmq.REQ)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.RCVTIMEO, self._timeout_ms)
        sock.setsockopt(zmq.SNDTIMEO, self._timeout_ms)
        sock.connect(self.zmq_url)
        self._sock = sock

    def _request(self, *frames: bytes) -> bytes:
        try:
            self._sock.send_multipart(list(frames))
            return self._sock.recv()
        except zmq.Again:
            # a REQ socket that missed its reply can send no more: a new one keeps the link usable, so a server
            # that was only slow (starved on a busy machine) takes the next command
            self._sock.close(linger=0)
            self._connect()
            raise ServerLateError(
                f"meshcat server at {self.zmq_url} did not answer within {self._timeout_ms / 1000:g} s"
            ) from None

    def send(self, command: Any) -> None:
        """Record a meshcat command and send it to the server, if any."""
        data = command.lower()
        # an animation is nearly all floats: float32 halves the page (key times and positions stay within 1 um)
        packed = packb(data, single_float=data["type"] == "set_animation")
        self.recorder.apply(data["type"], data["path"], packed)
        if self._sock is not None:
            self._request(data["type"].encode("utf-8"), data["path"].encode("utf-8"), packed)

    def _checked(self, reply: bytes) -> None:
        if reply != b"ok":
            raise RuntimeError(f"meshcat server at {self.zmq_url}: {reply.decode('utf-8', errors='replace')[:200]}")

    @property
    def connected(self) -> bool:
        """Whether commands go to a meshcat server."""
        return self._sock is not None

    def send_frame(self, paths: list[str], matrices: np.ndarray, rows: Any = None) -> None:
        """One frame of a live run in one request: the 4x4 transforms matrices (K, 4, 4) of the K nodes `paths`
        (meshcat paths) and, if given, the page's new numbers `rows` (`crtraj.viz.page.append_rows`). The server
        forwards it to every page as one message (`crtraj.viz.server.FRAME_COMMAND`; the page's script applies
        it). Not recorded: a frame is a moment of a live run, whose page is built from its result afterwards."""
        if self._sock is None:
            return
        # three.js reads a matrix column by column; one float32 typed array (msgpack extension 0x17, which
        # meshcat's page decodes to a Float32Array) for all of them
        cols = np.ascontiguousarray(np.asarray(matrices, dtype=np.float32).transpose(0, 2, 1))
        msg = {"type": meshcat_server.FRAME_TYPE, "paths": paths, "matrices": msgpack.ExtType(0x17, cols.tobytes())}
        if rows is not None:
            msg["rows"] = rows
        self._checked(self._request(meshcat_server.FRAME_COMMAND, b"", packb(msg)))

    def send_page(self, data_json: str) -> None:
        """Replace the data of the server's full page (`crtraj.viz.server.PAGE_PATH`); no-op without a server."""
        if self._sock is not None:
            self._checked(self._request(meshcat_server.PAGE_COMMAND, b"", data_json.encode("utf-8")))

    @property
    def page_url(self) -> str | None:
        """The server's full page (scene, panel, plots, legend), None without a server."""
        if not self.web_url:
            return None
        return self.web_url.removesuffix("/static/").rstrip("/") + meshcat_server.PAGE_PATH

    def get_scene(self) -> str:
        """The standalone page of everything recorded (meshcat's name for it)."""
        return self.recorder.static_html()

    def open(self) -> MeshcatWindow:
        """Open the live page in the default browser (no-op without a server)."""
        if self.page_url:
            webbrowser.open(self.page_url, new=2)
        return self

    def close(self) -> None:
        """Close the link and stop the server this window started (idempotent)."""
        self._finalizer()
        self._sock = None
