"""Headless Chromium driven over its DevTools pipe: open the view's page, seek it, take pictures.

`Chromium` starts one browser with a new empty profile (deleted on `close`) and no background networking;
`Chromium.open` gives a `Tab` of a fixed size in pixels. The DevTools pipe is Chromium's fd 3 (commands in) and
fd 4 (replies out); a small Python trampoline puts the pipe ends there before it execs Chromium. Every wait is
bounded by `timeout` s (a hang bound, not a timing window).
"""

from __future__ import annotations

import base64
import json
import logging
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from crtraj.core.errors import InputError
from crtraj.core.interrupt import popen_child

log = logging.getLogger(__name__)


EXECUTABLES = ("chromium", "chromium-browser", "google-chrome")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-quic",
    "--no-first-run",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--hide-scrollbars",
    "--mute-audio",
    # WebGL with --disable-gpu runs on SwiftShader; newer Chromium wants it allowed explicitly
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
)

TRAMPOLINE = """
import fcntl, os, sys
r, w = (int(a) for a in sys.argv[1:3])
moved = [fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 5) for fd in (r, w)]  # off 3 and 4 first
for fd in (r, w):
    os.close(fd)
os.dup2(moved[0], 3)
os.dup2(moved[1], 4)
for fd in moved:
    os.close(fd)
os.execv(sys.argv[3], sys.argv[3:])
"""

# Resolves once the page's script has found meshcat's scene and clock (crtraj.viz.page), after two more frames.
_READY = """
new Promise((resolve, reject) => {
  const t0 = performance.now();
  const check = () => {
    const v = window.crtrajView;
    if (v && v.isReady()) {
      window.viewer.set_dirty();
      requestAnimationFrame(() => requestAnimationFrame(() => resolve(v.time())));
    } else if (performance.now() - t0 > %d) {
      reject(new Error("the page did not become ready"));
    } else {
      requestAnimationFrame(check);
    }
  };
  check();
})
"""


def find_chromium() -> str | None:
    """The path of a Chromium on PATH (or /usr/bin/chromium), None when there is none."""
    for name in EXECUTABLES:
        path = shutil.which(name)
        if path:
            return path
    return "/usr/bin/chromium" if os.access("/usr/bin/chromium", os.X_OK) else None


class Chromium:
    """One headless Chromium over the DevTools pipe. exe: its path (None: `find_chromium`); timeout: s per wait."""

    def __init__(self, exe: str | None = None, timeout: float = 120.0) -> None:
        exe = exe or find_chromium()
        if exe is None:
            raise InputError("chromium: no Chromium found on PATH (install chromium for --png/--mp4)")
        self.timeout = timeout
        self._profile = tempfile.mkdtemp(prefix="crtraj-chromium-")
        to_r, to_w = os.pipe()
        from_r, from_w = os.pipe()
        self._log = open(Path(self._profile) / "chromium.log", "wb")  # noqa: SIM115 - closed by close()
        self.proc = subprocess.Popen(
            [sys.executable, "-c", TRAMPOLINE, str(to_r), str(from_w), exe, *FLAGS, "--remote-debugging-pipe",
             f"--user-data-dir={self._profile}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT, pass_fds=(to_r, from_w),
            **popen_child(),
        )  # fmt: skip
        os.close(to_r)
        os.close(from_w)
        self._out = os.fdopen(to_w, "wb", buffering=0)
        self._in = from_r
        self._buf = b""
        self._next_id = 0
        self.events: list[dict[str, Any]] = []

    def _fail(self, what: str) -> RuntimeError:
        """One line for the user; Chromium's own output goes to the debug log."""
        log.debug("chromium log tail: %s", (Path(self._profile) / "chromium.log").read_text(errors="replace")[-4000:])
        return RuntimeError(f"chromium: {what} (exit code {self.proc.poll()})")

    def _message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._in], [], [], left)[0]:
                raise self._fail(f"no answer within {self.timeout:g} s")
            chunk = os.read(self._in, 1 << 20)
            if not chunk:
                raise self._fail("the DevTools pipe closed")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, session: str | None = None, **params: Any) -> dict[str, Any]:
        """Send one DevTools command and return its result (events meanwhile go to `events`)."""
        self._next_id += 1
        msg: dict[str, Any] = {"id": self._next_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        self._out.write(json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._message(deadline)
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise self._fail(f"{method}: {reply['error'].get('message', reply['error'])}")
                return reply.get("result", {})
            if "method" in reply:
                self.events.append(reply)

    def open(self, url: str, width: int, height: int, offline: bool = False) -> Tab:
        """A new tab of width x height px showing `url`, once its page is ready; offline: no network at all."""
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        tab = Tab(self, target, session)
        self.call("Emulation.setDeviceMetricsOverride", session, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)  # fmt: skip
        if offline:
            self.call("Network.enable", session)
            self.call("Network.emulateNetworkConditions", session, offline=True, latency=0,
                      downloadThroughput=-1, uploadThroughput=-1)  # fmt: skip
        self.call("Page.enable", session)
        self.call("Page.navigate", session, url=url)
        tab.wait_event("Page.loadEventFired")
        tab.evaluate(_READY % int(self.timeout * 1000), await_promise=True)
        return tab

    def close(self) -> None:
        """Stop the browser and delete its profile (idempotent)."""
        try:
            if self.proc.poll() is None:
                self.call("Browser.close")
            self.proc.wait(timeout=self.timeout)
        except (RuntimeError, OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        finally:
            self._out.close()
            os.close(self._in)
            self._log.close()
            shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Tab:
    """One page of a `Chromium`."""

    def __init__(self, browser: Chromium, target: str, session: str) -> None:
        self.browser = browser
        self.target = target
        self.session = session

    def wait_event(self, method: str) -> dict[str, Any]:
        """Wait for the event `method` of this tab (one already received counts)."""
        b = self.browser
        deadline = time.monotonic() + b.timeout
        while True:
            for i, ev in enumerate(b.events):
                if ev["method"] == method and ev.get("sessionId") == self.session:
                    return b.events.pop(i)
            ev = b._message(deadline)
            if "method" in ev:
                b.events.append(ev)

    def evaluate(self, expression: str, await_promise: bool = False) -> Any:
        """The value of a JavaScript expression in the page (a rejected promise or a throw raises)."""
        r = self.browser.call("Runtime.evaluate", self.session, expression=expression,
                              awaitPromise=await_promise, returnByValue=True)  # fmt: skip
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise self.browser._fail(f"page script: {d.get('exception', {}).get('description', d.get('text'))}")
        return r["result"].get("value")

    def seek(self, t: float) -> None:
        """Pause the page's clock at t (s) and wait two frames so the scene shows it."""
        self.evaluate(
            f"new Promise((res) => {{ crtrajView.pause(); crtrajView.seek({float(t)!r}); window.viewer.set_dirty();"
            " requestAnimationFrame(() => requestAnimationFrame(res)); })",
            await_promise=True,
        )

    def screenshot(self) -> bytes:
        """The tab's picture as PNG bytes."""
        return base64.b64decode(self.browser.call("Page.captureScreenshot", self.session, format="png")["data"])

    def close(self) -> None:
        self.browser.call("Target.closeTarget", targetId=self.target)
        self.browser.events = [ev for ev in self.browser.events if ev.get("sessionId") != self.session]
