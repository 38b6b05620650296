"""The live view's drawing process: a `LivePage` on the live server, fed one small message per draw.

A thread in the loop's process draws only through the same interpreter lock as the loop: every millisecond of
Python it runs (posing the robot, packing meshcat's commands, the page's numbers) is a millisecond the loop may
wait. So `crtraj.viz.live.LiveView` draws here, in a child process (``python -m crtraj.viz.live._child NICE``,
at niceness NICE: below the loop, so on a busy machine the loop keeps the CPU). Its feed thread
(`crtraj.viz.live._feed.LiveFeed`) does as little as it can per draw: it packs the newest state and the records
since the last draw into one buffer of float64 (`pack`) and sends it, with a one-line JSON header (each record's
step status, obstacle count and executed samples), on the child's stdin, then waits (without the lock) for the
child's "ok" line. The first line is the set-up (robot, the server's ZMQ address, D_sf, deadline, obstacle names,
goal). Plain JSON and raw floats, no pickles. The child ends at EOF on its stdin. Lengths in mm, times in s.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import struct
import subprocess
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from crtraj.core.fields import Table
from crtraj.core.fileio import to_jsonable
from crtraj.core.interrupt import popen_child
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.viz.live._link import ServerLateError
from crtraj.viz.live._page import LivePage
from crtraj.viz.view import Visualizer

_TIMES = struct.Struct("3d")  # t, iteration time, replanned


def pack(state: Any, new: list[tuple[Any, Any]]) -> tuple[bytes, bytes]:
    """The message of one draw: (header line, float64 buffer). The buffer holds, for the newest state and then for
    each record (StateRecord, StepRecord or None) of `new`: t, iteration time, replanned, x, planned x, centres,
    radii, executed actuation (the first record: its actuation, which starts the samples; the newest state: none).
    The header lists per part [step status or null, obstacles, executed numbers]. Runs on the feed thread, holding
    the interpreter lock the loop needs: a few attribute reads and the arrays' bytes per record, one join."""
    f64 = np.asarray
    parts: list[bytes] = []
    meta: list[list[Any]] = []
    for s, k, motion in [(state, None, False), *((s, k, True) for s, k in new)]:
        c = f64(s.centers, float)
        ex = f64(s.q if k is None else k.executed, float).tobytes() if motion else b""
        times = _TIMES.pack(s.t, math.nan, 0.0) if k is None else _TIMES.pack(s.t, k.iter_time, k.replanned)
        parts += (times, f64(s.x, float).tobytes(), f64(getattr(s, "planned", s.x), float).tobytes(), c.tobytes(),
                  f64(s.radii, float).tobytes(), ex)  # fmt: skip
        meta.append([None if k is None else str(k.step_status), c.size // 3, len(ex) // 8])
    buf = b"".join(parts)
    return json.dumps({"e": meta, "b": len(buf)}).encode("utf-8") + b"\n", buf


def unpack(header: dict[str, Any], buf: bytes, nx: int) -> tuple[SimpleNamespace, list[tuple[Any, Any]]]:
    """`pack`'s message read back: (the newest state, [(state, step or None), ...]) as namespaces with the
    records' field names."""
    v = np.frombuffer(buf, dtype=float)
    out, i = [], 0
    for status, m, n_ex in header["e"]:
        t, it, rep = v[i : i + 3]
        i += 3
        x, planned = v[i : i + nx], v[i + nx : i + 2 * nx]
        i += 2 * nx
        c, r, ex = v[i : i + 3 * m].reshape(m, 3), v[i + 3 * m : i + 4 * m], v[i + 4 * m : i + 4 * m + n_ex]
        i += 4 * m + n_ex
        state = SimpleNamespace(t=float(t), x=x, planned=planned, centers=c, radii=r, q=ex)
        step = None if status is None else SimpleNamespace(step_status=status, iter_time=float(it),
                                                           replanned=bool(rep), executed=ex)  # fmt: skip
        out.append((state, step))
    if i != len(v):
        raise ValueError(f"live view message: {len(v)} numbers, the header describes {i}")
    return out[0][0], out[1:]


class ChildDrawer:
    """The feed's drawer in the loop's process: hands each draw to the child process and waits for it.

    setup: the child's first line (see the module doc); nice: the child's niceness (0-19).
    """

    def __init__(self, setup: dict[str, Any], nice: int = 0) -> None:
        if not 0 <= nice <= 19:
            raise ValueError(f"nice: expected 0 to 19, got {nice}")
        # the child's diagnostics go to a temp file: an unread pipe could fill and stall it
        self._log = tempfile.TemporaryFile(mode="w+b")  # noqa: SIM115 - closed by close()
        env = dict(os.environ)  # the child imports this crtraj, wherever it is
        pkg_parent = str(Path(__file__).resolve().parents[3])
        env["PYTHONPATH"] = pkg_parent + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "crtraj.viz.live._child", str(int(nice))],
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
            start_new_session=True,  # a Ctrl-C meant for the loop does not kill the view
            **popen_child(),  # but the view dies with the loop's process, even a SIGKILLed one
        )
        self._send(json.dumps(to_jsonable(setup)).encode("utf-8") + b"\n")
        if self._line() != "ready":
            self.close()
            raise RuntimeError(f"live view: its drawing process did not start: {self._tail()}")

    def _send(self, *chunks: bytes) -> None:
        # one write system call for the whole message: every call the feed thread makes into the system lets the
        # loop's thread take the interpreter lock, and taking it back makes the loop wait for this thread
        assert self.proc.stdin is not None
        view = memoryview(b"".join(chunks))
        fd = self.proc.stdin.fileno()
        while view:
            view = view[os.write(fd, view) :]

    def _line(self) -> str:
        assert self.proc.stdout is not None
        return self.proc.stdout.readline().decode("utf-8").strip()

    def _tail(self) -> str:
        self._log.seek(0)
        lines = self._log.read().decode("utf-8", errors="replace").strip().splitlines()
        return lines[-1] if lines else f"exit code {self.proc.poll()}"

    def draw(self, state: Any, new: list[tuple[Any, Any]]) -> None:
        """Draw `state` and add the records `new` to the page (the child's work); raises when the child failed,
        or when the server was too slow to take this frame (the child then goes on; the next draw is whole)."""
        self._send(*pack(state, new))
        line = self._line()
        if line == "late":
            raise ServerLateError(f"live view: the server missed the frame at t = {state.t:.3f} s; the view goes on")
        if line != "ok":
            raise RuntimeError(f"live view: the drawing process failed: {self._tail()}")

    def close(self) -> None:
        """End the child (EOF on its stdin) and wait for it (idempotent)."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            with contextlib.suppress(BrokenPipeError):  # the child is gone already
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()


def setup_message(
    model: Model, zmq_url: str, scene: Any, deadline: float, goal: Any, timeout: float = 60.0
) -> dict[str, Any]:
    """The child's first line: the robot, the live server's ZMQ address, D_sf (mm), the step deadline (s), the
    obstacles' names, the goal (3,) mm and the bound (s) on each of the server's replies."""
    return {
        "robot": model.robot.to_dict(),
        "zmq_url": zmq_url,
        "timeout": float(timeout),
        "safety": float(scene.safety_distance),
        "deadline": float(deadline),
        "names": [o.name for o in scene.obstacles],
        "goal": np.asarray(goal, dtype=float).tolist(),
    }


def main() -> None:
    """Entry point of the drawing process; the argument, if any, is its niceness (set before any thread starts:
    Linux keeps it per thread, and threads inherit it)."""
    if len(sys.argv) > 1 and int(sys.argv[1]) > 0:
        os.nice(int(sys.argv[1]))
    stdin = sys.stdin.buffer
    setup = json.loads(stdin.readline())
    model = Model(Robot.from_table(Table(setup["robot"], "robot")))
    vis = Visualizer(model, zmq_url=setup["zmq_url"], timeout=setup.get("timeout", 60.0))
    try:
        page = LivePage(vis, model, safety_distance=setup["safety"], deadline=setup["deadline"],
                        names=setup["names"], goal=setup["goal"])  # fmt: skip
        page.warm_up()
        page.push()
        print("ready", flush=True)
        for line in stdin:
            header = json.loads(line)
            state, entries = unpack(header, stdin.read(header["b"]), model.robot.nx)
            print("ok" if _draw(page, state, entries) else "late", flush=True)
    finally:
        vis.close()


def _draw(page: LivePage, state: Any, entries: list[tuple[Any, Any]]) -> bool:
    """Draw one frame; False when the server was too slow to answer (starved at its low priority on a busy
    machine). The frame's new rows may then be lost on the server's side, so the page's whole data is sent again
    at the next chance: the live page never keeps a gap, and one slow moment never ends the view."""
    try:
        if page.resync:
            page.push()
            page.resync = False
        page.draw(state, entries)
    except ServerLateError as exc:
        page.resync = True
        print(f"live view: {exc}", file=sys.stderr, flush=True)
        return False
    return True


if __name__ == "__main__":
    main()
