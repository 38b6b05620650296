"""The live view's drawing process: a `LivePage` on the live server, fed one JSON line per draw.

A thread in the loop's process draws only through the same interpreter lock as the loop: every millisecond of
Python it runs (posing the robot, packing meshcat's commands, the page's numbers) is a millisecond the loop may
wait. So `crtraj.viz.live_view.LiveView` draws here, in a child process (``python -m crtraj.viz.live_child``): its
feed thread (`crtraj.viz.live_feed.LiveFeed`) sends each draw's newest state and the steps since the last draw
as one JSON line on the child's stdin and waits (without the lock) for the child's "ok" line. The first line is
the set-up (robot, the server's ZMQ address, D_sf, deadline, obstacle names, goal). Plain JSON both ways, no
pickles. The child ends at EOF on its stdin. Lengths in mm, times in s.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from crtraj.core.fields import Table
from crtraj.core.fileio import to_jsonable
from crtraj.model.kinematics import Model
from crtraj.model.robot import Robot
from crtraj.viz.live_page import LivePage
from crtraj.viz.view import Visualizer


def _state_msg(state: Any) -> list[Any]:
    return [float(state.t), state.x.tolist(), np.asarray(state.centers).tolist(), np.asarray(state.radii).tolist(),
            np.asarray(getattr(state, "planned", state.x)).tolist()]  # fmt: skip


def _step_msg(step: Any) -> list[Any] | None:
    return None if step is None else [str(step.step_status), float(step.iter_time), bool(step.replanned)]


class ChildDrawer:
    """The feed's drawer in the loop's process: hands each draw to the child process and waits for it.

    setup: the child's first line (see the module doc); timeout: s for the child's start-up (its "ready" line).
    """

    def __init__(self, setup: dict[str, Any]) -> None:
        # the child's diagnostics go to a temp file: an unread pipe could fill and stall it
        self._log = tempfile.TemporaryFile(mode="w+b")  # noqa: SIM115 - closed by close()
        env = dict(os.environ)  # the child imports this crtraj, wherever it is
        pkg_parent = str(Path(__file__).resolve().parent.parent.parent)
        env["PYTHONPATH"] = pkg_parent + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "crtraj.viz.live_child"],
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
            start_new_session=True,  # a Ctrl-C meant for the loop does not kill the view
        )
        self._send(to_jsonable(setup))
        if self._line() != "ready":
            self.close()
            raise RuntimeError(f"live view: its drawing process did not start: {self._tail()}")

    def _send(self, msg: dict[str, Any]) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(msg).encode("utf-8") + b"\n")  # NaN as Python's json reads it back
        self.proc.stdin.flush()

    def _line(self) -> str:
        assert self.proc.stdout is not None
        return self.proc.stdout.readline().decode("utf-8").strip()

    def _tail(self) -> str:
        self._log.seek(0)
        lines = self._log.read().decode("utf-8", errors="replace").strip().splitlines()
        return lines[-1] if lines else f"exit code {self.proc.poll()}"

    def draw(self, state: Any, new: list[tuple[Any, Any]]) -> None:
        """Draw `state` and add the steps `new` to the page (the child's work); raises when the child failed."""
        self._send({"x": _state_msg(state), "new": [[_state_msg(s), _step_msg(k)] for s, k in new]})
        if self._line() != "ok":
            raise RuntimeError(f"live view: the drawing process failed: {self._tail()}")

    def close(self) -> None:
        """End the child (EOF on its stdin) and wait for it (idempotent)."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._log.close()


def setup_message(model: Model, zmq_url: str, scene: Any, deadline: float, goal: Any) -> dict[str, Any]:
    """The child's first line: the robot, the live server's ZMQ address, D_sf (mm), the step deadline (s), the
    obstacles' names and the goal (3,) mm."""
    return {
        "robot": model.robot.to_dict(),
        "zmq_url": zmq_url,
        "safety": float(scene.safety_distance),
        "deadline": float(deadline),
        "names": [o.name for o in scene.obstacles],
        "goal": np.asarray(goal, dtype=float).tolist(),
    }


def _state(m: list[Any]) -> SimpleNamespace:
    t, x, c, r, p = m
    return SimpleNamespace(t=t, x=np.asarray(x, float), centers=np.asarray(c, float).reshape(-1, 3),
                           radii=np.asarray(r, float).reshape(-1), planned=np.asarray(p, float))  # fmt: skip


def _step(m: list[Any] | None) -> SimpleNamespace | None:
    return None if m is None else SimpleNamespace(step_status=m[0], iter_time=m[1], replanned=m[2])


def main() -> None:
    """Entry point of the drawing process."""
    setup = json.loads(sys.stdin.readline())
    model = Model(Robot.from_table(Table(setup["robot"], "robot")))
    vis = Visualizer(model, zmq_url=setup["zmq_url"])
    try:
        page = LivePage(vis, model, safety_distance=setup["safety"], deadline=setup["deadline"],
                        names=setup["names"], goal=setup["goal"])  # fmt: skip
        page.push()
        print("ready", flush=True)
        for line in sys.stdin:
            msg = json.loads(line)
            entries = [(_state(s), _step(k)) for s, k in msg["new"]]
            if entries:
                page.extend(entries)
            state = _state(msg["x"])
            page.display(state.x)
            page.set_obstacles(state.centers, state.radii)
            print("ok", flush=True)
    finally:
        vis.close()


if __name__ == "__main__":
    main()
