"""The meshcat server process behind a live `crtraj.viz.view.Visualizer`, bound to 127.0.0.1 only.

meshcat 0.3.2's own server listens on every interface; here its web and ZMQ
sockets bind to the loopback interface. The server runs as a child process
(``python -m crtraj.viz.server``) that exits when its parent closes its stdin
or dies, so a crashed notebook never leaves a server behind.

Beside meshcat's own page (``/static/``) the server serves crtraj's full page (``/crtraj/``: the scene with the
heads-up panel, plots, events and legend of `crtraj.viz.page`) and the page's data (``/crtraj/data.json``), which a
client replaces with the ZMQ command ``crtraj_page`` (frames: command, "", the JSON); every page is then told to
fetch it again. A live run's frames come as the ZMQ command ``crtraj_frame`` (frames: command, "", one msgpack map:
the transforms of every moving node and the page's new numbers, `crtraj.viz.live.MeshcatWindow.send_frame`): the
server adds the numbers to its page data and forwards the frame to every page as one web-socket message, which the
page's script applies (one message per frame, not one per object). A page that connects later gets the scene, the
newest frame and the notice to fetch the data.
"""

from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import msgpack

from crtraj.core.interrupt import popen_child
from crtraj.viz.page import append_rows, wrap_page_json
from crtraj.viz.page import page_json as dump_page

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    import tornado.web
    from meshcat.servers.zmqserver import VIEWER_HTML, VIEWER_ROOT, ZMQWebSocketBridge

HOST = "127.0.0.1"  # the only interface a crtraj server listens on
PAGE_COMMAND = b"crtraj_page"  # the ZMQ command that replaces the full page's data
FRAME_COMMAND = b"crtraj_frame"  # the ZMQ command of one live frame
FRAME_TYPE = "crtraj_frame"  # its message type on the page's web socket
PAGE_PATH = "/crtraj/"  # where the full page is served
# the web-socket message that tells a page to fetch its data again (the page's script knows the type)
_PAGE_NOTICE = msgpack.packb({"type": "crtraj_page"})
_EMPTY_PAGE = b'{"runs":[],"legend":[]}'
_POLL_S = 0.05  # how often the parent looks for the child's start-up lines


def _read_log(fh: Any) -> str:
    return os.pread(fh.fileno(), 1 << 20, 0).decode("utf-8", errors="replace")


def start_server(timeout: float, nice: int = 0) -> tuple[subprocess.Popen[bytes], Any, str, str]:
    """Start meshcat's server (bound to 127.0.0.1) as a child; return (proc, log, zmq_url, web_url).

    timeout: s to wait for the server's start-up lines; nice: the server's niceness (0-19; a live view's server
    runs below the loop it shows).
    """
    if not 0 <= nice <= 19:
        raise ValueError(f"nice: expected 0 to 19, got {nice}")
    # The child's output goes to an append-only temp file: an unread pipe could fill and stall it.
    log = tempfile.TemporaryFile(mode="a+b")  # noqa: SIM115 - lives as long as the server; closed by stop_server
    env = dict(os.environ)
    pkg_parent = str(Path(__file__).resolve().parent.parent.parent)
    env["PYTHONPATH"] = pkg_parent + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "crtraj.viz.server", str(int(nice))],
        stdin=subprocess.PIPE,  # closing it stops the server, also when this process dies
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,  # a Ctrl-C meant for a notebook cell does not kill the viewer
        **popen_child(),  # but the viewer dies with this process, even a SIGKILLed one
    )
    deadline = time.monotonic() + timeout
    while True:
        text = _read_log(log)
        zmq_url = re.search(r"^zmq_url=(\S+)$", text, re.MULTILINE)
        web_url = re.search(r"^web_url=(\S+)$", text, re.MULTILINE)
        if zmq_url and web_url:
            return proc, log, zmq_url.group(1), web_url.group(1)
        if proc.poll() is not None or time.monotonic() > deadline:
            stop_server(proc, None, log)
            last = text.strip().splitlines()[-1:] or ["no output"]
            raise RuntimeError(f"meshcat server did not start (exit code {proc.returncode}): {last[0]}")
        time.sleep(_POLL_S)


def stop_server(proc: subprocess.Popen[bytes] | None, sock: Any, log: Any) -> None:
    """Close the ZMQ socket and stop the server child (idempotent; used by weakref.finalize)."""
    if sock is not None:
        sock.close(linger=0)
    if proc is not None and proc.poll() is None:
        if proc.stdin is not None:
            proc.stdin.close()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if log is not None:
        log.close()


def _exit_when_parent_goes() -> None:
    """EOF on stdin means the parent closed it or died: stop serving."""
    sys.stdin.buffer.read()
    os._exit(0)


class _PageHandler(tornado.web.RequestHandler):
    """The full page: meshcat's served page (websocket scene) inside crtraj's page, with the newest data."""

    def initialize(self, bridge: _LoopbackBridge) -> None:
        self.bridge = bridge

    def get(self) -> None:
        shell = Path(VIEWER_ROOT, VIEWER_HTML).read_text(encoding="utf-8")
        shell = shell.replace('src="main.min.js"', 'src="/static/main.min.js"')
        self.set_header("Cache-Control", "no-store")
        self.set_header("Content-Type", "text/html; charset=utf-8")
        self.write(wrap_page_json(shell, self.bridge.page_json.decode("utf-8")))


class _DataHandler(tornado.web.RequestHandler):
    """The full page's data (JSON), polled by a live page."""

    def initialize(self, bridge: _LoopbackBridge) -> None:
        self.bridge = bridge

    def get(self) -> None:
        self.set_header("Cache-Control", "no-store")
        self.set_header("Content-Type", "application/json")
        self.write(self.bridge.page_json)


class _LoopbackBridge(ZMQWebSocketBridge):
    """meshcat's bridge with its web socket on 127.0.0.1 too, and crtraj's full page beside meshcat's."""

    page: dict[str, Any] | None = None  # the full page's data
    _page_json: bytes | None = _EMPTY_PAGE  # ... as JSON (None: to be made again from `page`)
    last_frame: bytes | None = None  # the newest live frame, for a page that connects later

    @property
    def page_json(self) -> bytes:
        """The full page's data as JSON."""
        if self._page_json is None:
            self._page_json = dump_page(self.page or {}).encode("utf-8")
        return self._page_json

    def handle_zmq(self, frames: list[bytes]) -> None:
        if frames and frames[0] in (PAGE_COMMAND, FRAME_COMMAND):
            if len(frames) != 3:
                self.zmq_socket.send(b"error: expected 3 frames")
                return
            try:
                (self._set_page if frames[0] == PAGE_COMMAND else self._frame)(bytes(frames[2]))
            except Exception as exc:  # a bad message is answered, never the end of the server
                self.zmq_socket.send(f"error: {type(exc).__name__}: {exc}".encode())
                return
            self.zmq_socket.send(b"ok")
            return
        super().handle_zmq(frames)

    def _set_page(self, data: bytes) -> None:
        self.page, self._page_json = json.loads(data), data
        self.last_frame = None  # a frame of the run before does not belong to the new page
        self._broadcast(_PAGE_NOTICE)

    def _frame(self, data: bytes) -> None:
        rows = msgpack.unpackb(data).get("rows")
        if rows is not None and self.page and self.page.get("runs"):
            append_rows(self.page["runs"][0], rows)
            self._page_json = None
        self.last_frame = data
        self._broadcast(data)

    def _broadcast(self, data: bytes) -> None:
        for websocket in self.websocket_pool:
            websocket.write_message(data, binary=True)

    def send_scene(self, websocket: Any) -> None:
        super().send_scene(websocket)
        if self.last_frame is not None:
            websocket.write_message(self.last_frame, binary=True)
        # the page was served before its web socket opened: it may have missed numbers, or the run's end
        websocket.write_message(_PAGE_NOTICE, binary=True)

    # meshcat 0.3.x has no option for the web socket's bind address: its `host` binds the ZMQ socket and names the
    # page's address, but the tornado app its `make_app` builds is listened on without one. Overriding `make_app`
    # (a method of the bridge's class, called once from its constructor) is the narrowest hook; pyproject pins
    # meshcat to >=0.3.2,<0.4, the versions with that constructor.
    def make_app(self) -> Any:
        app = super().make_app()
        app.add_handlers(
            r".*",
            [
                (PAGE_PATH, _PageHandler, {"bridge": self}),
                (PAGE_PATH + "data.json", _DataHandler, {"bridge": self}),
            ],
        )
        # tornado's listen() binds every interface unless given an address
        app.listen = functools.partial(app.listen, address=HOST)
        return app


def serve() -> None:
    """Entry point of the server child: meshcat's bridge, every socket on 127.0.0.1; the argument, if any, is the
    niceness to run at (before any thread starts: Linux sets it per thread, and threads inherit it)."""
    if len(sys.argv) > 1 and int(sys.argv[1]) > 0:
        os.nice(int(sys.argv[1]))
    bridge = _LoopbackBridge(host=HOST)
    # the start-up lines on stdout are the child's answer to `start_server`, which parses them (not diagnostics)
    print(f"zmq_url={bridge.zmq_url}")
    print(f"web_url={bridge.web_url}")
    threading.Thread(target=_exit_when_parent_goes, daemon=True).start()
    bridge.run()


if __name__ == "__main__":
    serve()
