"""The meshcat server process behind a live `crtraj.viz.view.Visualizer`, bound to 127.0.0.1 only.

meshcat 0.3.2's own server listens on every interface; here its web and ZMQ
sockets bind to the loopback interface. The server runs as a child process
(``python -m crtraj.viz.server``) that exits when its parent closes its stdin
or dies, so a crashed notebook never leaves a server behind.

Beside meshcat's own page (``/static/``) the server serves crtraj's full page (``/crtraj/``: the scene with the
heads-up panel, plots, events and legend of `crtraj.viz.page`) and the page's data (``/crtraj/data.json``), which a
client replaces with the ZMQ command ``crtraj_page`` (frames: command, "", the JSON); a live page polls it.
"""

from __future__ import annotations

import functools
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

from crtraj.viz.page import wrap_page_json

with warnings.catch_warnings():
    # meshcat's server module installs a pyzmq < 17 event-loop shim and pyzmq warns about it
    warnings.filterwarnings("ignore", category=DeprecationWarning, message=r"zmq\.eventloop\.ioloop")
    import tornado.web
    from meshcat.servers.zmqserver import VIEWER_HTML, VIEWER_ROOT, ZMQWebSocketBridge

HOST = "127.0.0.1"  # the only interface a crtraj server listens on
PAGE_COMMAND = b"crtraj_page"  # the ZMQ command that replaces the full page's data
PAGE_PATH = "/crtraj/"  # where the full page is served
_EMPTY_PAGE = b'{"runs":[],"legend":[]}'
_POLL_S = 0.05  # how often the parent looks for the child's start-up lines


def _read_log(fh: Any) -> str:
    return os.pread(fh.fileno(), 1 << 20, 0).decode("utf-8", errors="replace")


def start_server(timeout: float) -> tuple[subprocess.Popen[bytes], Any, str, str]:
    """Start meshcat's server (bound to 127.0.0.1) as a child; return (proc, log, zmq_url, web_url).

    timeout: s to wait for the server's start-up lines.
    """
    # The child's output goes to an append-only temp file: an unread pipe could fill and stall it.
    log = tempfile.TemporaryFile(mode="a+b")  # noqa: SIM115 - lives as long as the server; closed by stop_server
    env = dict(os.environ)
    pkg_parent = str(Path(__file__).resolve().parent.parent.parent)
    env["PYTHONPATH"] = pkg_parent + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "crtraj.viz.server"],
        stdin=subprocess.PIPE,  # closing it stops the server, also when this process dies
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,  # a Ctrl-C meant for a notebook cell does not kill the viewer
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

    page_json = _EMPTY_PAGE

    def handle_zmq(self, frames: list[bytes]) -> None:
        if frames and frames[0] == PAGE_COMMAND:
            if len(frames) == 3:
                self.page_json = bytes(frames[2])
                self.zmq_socket.send(b"ok")
            else:
                self.zmq_socket.send(b"error: expected 3 frames")
            return
        super().handle_zmq(frames)

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
    """Entry point of the server child: meshcat's bridge, every socket on 127.0.0.1."""
    bridge = _LoopbackBridge(host=HOST)
    # the start-up lines on stdout are the child's answer to `start_server`, which parses them (not diagnostics)
    print(f"zmq_url={bridge.zmq_url}")
    print(f"web_url={bridge.web_url}")
    threading.Thread(target=_exit_when_parent_goes, daemon=True).start()
    bridge.run()


if __name__ == "__main__":
    serve()
