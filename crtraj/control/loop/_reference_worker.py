"""Reference planning beside the control loop: a worker process that runs the reference source.

A reference plan (the configuration-space planner, tens of milliseconds) is far longer than a control
step's budget (a few milliseconds), so with ``[loop] reference_delay > 0`` the closed loop hands each
request to this worker (after the step's move is chosen: whether a new path is needed is decided
there too) and keeps stepping on the reference it has; the finished path is taken over at the first
step at least ``reference_delay`` seconds after the request.

The worker is a forked copy of the loop's process, so it holds the same planner, robot model and compiled
kernels without rebuilding them. Requests and replies cross a pipe as JSON headers and raw float64 arrays
(never pickles): the request carries the configuration, the time, the tip goal and the obstacles (the
scene in its ``[scene]`` schema, sent only when it changed); the reply carries the path, the planner's
status and message, its wall time and the tree edges for drawing. Units: mm, rad, s.
"""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing
import os
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from crtraj.control.loop._reference import ReferencePlan, ReferenceSource
from crtraj.core.fields import Table
from crtraj.core.interrupt import die_with_parent
from crtraj.planning.result import PlanStatus
from crtraj.world.scene import Scene

# Largest reply the parent accepts (bytes per message): a path or tree of a million numbers.
MAX_REPLY_BYTES = 8 * 1_000_000
# Seconds the parent waits for the worker to end after closing its pipe, before terminating it.
JOIN_TIMEOUT = 2.0


@dataclass(frozen=True)
class PendingPlan:
    """A request in the worker: the step it was made at, the first step its path may be used at, why, and
    the version of the tip goal it plans for (the loop's count of retargets)."""

    step: int
    due: int
    reason: str
    goal_version: int = 0


class ReferenceWorker:
    """A child process that plans references for the closed loop (see the module docstring).

    source: the loop's `ReferenceSource` (the child uses its forked copy; a source with a ``goal``
    attribute and a ``retarget`` method is retargeted to the parent's goal before every plan).
    Start it with `start` (where `can_fork()`), then `submit`, `ready`, `take` and, at the end, `close`.
    reply_timeout: s `take` waits for a reply at most (a hang bound: the planner's own time limit ends a plan
    long before); a worker that does not reply by then is reported as failed and terminated.
    """

    def __init__(self, source: ReferenceSource, nx: int, reply_timeout: float = 600.0) -> None:
        self.source = source
        self.nx = int(nx)
        self.reply_timeout = float(reply_timeout)
        self.pending: PendingPlan | None = None
        self.plans = 0
        self.wait_time = 0.0  # s the loop spent waiting for due paths (simulated runs only)
        self._conn: Connection | None = None
        self._proc: Any = None
        self._sent_scene: Any = None
        self.failure = ""  # why the worker stopped serving ('' while it serves)

    @staticmethod
    def can_fork() -> bool:
        """This platform has the fork start method (the worker shares the loop's loaded planner)."""
        return "fork" in multiprocessing.get_all_start_methods()

    def start(self) -> None:
        """Fork the worker. Call before the loop's first step (a fork copies the process: milliseconds)."""
        ctx = multiprocessing.get_context("fork")
        parent, child = ctx.Pipe(duplex=True)
        args = (self.source, child, self.nx, os.getpid())
        proc = ctx.Process(target=_serve, args=args, name="crtraj-reference", daemon=True)
        proc.start()
        child.close()
        self._conn, self._proc = parent, proc

    @property
    def alive(self) -> bool:
        """The worker serves requests (started and not failed)."""
        return self._conn is not None and not self.failure

    @property
    def pid(self) -> int | None:
        """The worker process's id while it runs (its scheduling class is visible to the OS), else None."""
        return None if self._proc is None else self._proc.pid

    def submit(self, x: np.ndarray, t: float, scene: Any, pending: PendingPlan) -> None:
        """Ask for a path from configuration x (nx,) at loop time t (s) among `scene` (a `Scene`). A worker
        that has failed is not asked: `take` then gives the failed plan that says why."""
        if self.pending is not None:
            raise RuntimeError("reference worker: a request is already pending")
        self.pending = pending
        if not self.alive:
            return
        head: dict[str, Any] = {"t": float(t)}
        goal = getattr(self.source, "goal", None)
        if goal is not None and hasattr(self.source, "retarget"):
            head["goal"] = [float(v) for v in np.asarray(goal, dtype=float)]
        if scene is not self._sent_scene:
            head["scene"] = None if scene is None else scene.to_dict()
        try:
            assert self._conn is not None
            self._conn.send_bytes(json.dumps(head).encode("utf-8"))
            self._conn.send_bytes(np.ascontiguousarray(x, dtype=float).tobytes())
        except (OSError, ValueError) as exc:
            self._fail(f"reference worker: request not sent ({exc})")
            return
        self._sent_scene = scene

    def ready(self) -> bool:
        """The pending request's reply has arrived (or the worker failed: `take` then says so)."""
        if self.pending is None:
            return False
        if not self.alive:
            return True
        try:
            assert self._conn is not None
            return bool(self._conn.poll(0))
        except (OSError, ValueError) as exc:
            self._fail(f"reference worker: {exc}")
            return True

    def take(self, wait: bool, clock: Any) -> ReferencePlan | None:
        """The pending request's plan, or None when it has not arrived and `wait` is false. With `wait`, block
        until it arrives (the time, by `clock`, adds to `wait_time`). A worker that failed gives a failed plan
        whose message says why, and the loop plans inline from then on."""
        if self.pending is None:
            return None
        if not wait and not self.ready():
            return None
        t0 = clock()
        plan = self._receive()
        if wait:
            self.wait_time += clock() - t0
        self.pending = None
        self.plans += 1
        return plan

    def record(self) -> dict[str, Any]:
        """What a run records of its worker: plans taken over, seconds waited for due paths, why it failed."""
        return {"plans": self.plans, "wait_s": self.wait_time, "failure": self.failure}

    def close(self) -> None:
        """End the worker (closing its pipe ends it; one still planning is terminated, then killed): no
        process outlives this call."""
        conn, proc = self._conn, self._proc
        self._conn, self._proc = None, None
        if conn is not None:
            conn.close()
        if proc is not None:
            proc.join(JOIN_TIMEOUT if self.pending is None else 0.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(JOIN_TIMEOUT)
            if proc.is_alive():
                # a heavily loaded machine can leave a terminated child unscheduled past the timeout; SIGKILL
                # cannot be ignored, so the join returns and no process outlives close()
                proc.kill()
                proc.join()
        self.pending = None

    # ----------------------------------------------------------------- internals
    def _fail(self, why: str) -> None:
        if not self.failure:
            self.failure = why

    def _receive(self) -> ReferencePlan:
        """Read one reply; a failed plan naming the problem when the worker is gone or the reply is malformed."""
        if not self.alive:
            return _failed(self.failure)
        try:
            assert self._conn is not None
            if not self._conn.poll(self.reply_timeout):
                self._fail(f"reference worker: no reply in {self.reply_timeout:g} s")
                self._proc.terminate()
                return _failed(self.failure)
            head = json.loads(self._conn.recv_bytes(MAX_REPLY_BYTES).decode("utf-8"))
            configs = _array(self._conn.recv_bytes(MAX_REPLY_BYTES), head["configs"], self.nx)
            edges = _array(self._conn.recv_bytes(MAX_REPLY_BYTES), head["edges"], 6).reshape(-1, 2, 3)
            status = PlanStatus(head["status"])
            return ReferencePlan(configs, status, str(head["message"]), float(head["wall_time"]), edges)
        except (EOFError, OSError, ValueError, KeyError, TypeError) as exc:
            code = None
            if self._proc is not None:
                self._proc.join(JOIN_TIMEOUT)  # a worker that died is reaped, so its exit code is known
                code = self._proc.exitcode
            self._fail(f"reference worker stopped (exit code {code}): {type(exc).__name__} {exc}".strip())
            return _failed(self.failure)


def _failed(why: str) -> ReferencePlan:
    return ReferencePlan(np.zeros((0, 0)), PlanStatus.ERROR, why, 0.0)


def _array(data: bytes, rows: Any, cols: int) -> np.ndarray:
    """(rows, cols) float64 from raw bytes; ValueError when the sizes disagree or a value is not finite."""
    rows = int(rows)
    if rows < 0 or len(data) != rows * cols * 8:
        raise ValueError(f"reply of {len(data)} bytes is not {rows} x {cols} numbers")
    a = np.frombuffer(data, dtype=float).reshape(rows, cols).copy()
    if not np.isfinite(a).all():
        raise ValueError("reply has a non-finite number")
    return a


def _yield_to_the_loop() -> None:
    """Run this process only when a CPU would otherwise idle (Linux SCHED_IDLE; elsewhere the lowest nice
    level): a request wakes the worker, and a woken worker on the loop's CPU would otherwise preempt the
    control step for milliseconds. The loop never starves it: the loop waits (simulated) or sleeps between
    steps (real time), and the worker runs then."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # type: ignore[attr-defined]
    except (AttributeError, OSError):
        with contextlib.suppress(OSError):
            os.nice(19)


def _serve(source: ReferenceSource, conn: Connection, nx: int, parent: int) -> None:
    """The worker's loop: read a request, plan, reply; end when the parent closes the pipe or dies."""
    # Ctrl-C is the parent's to handle: the worker ends when the parent closes the pipe, or with the parent
    die_with_parent(parent)
    _yield_to_the_loop()
    scene: Scene | None = None
    while True:
        try:
            head = json.loads(conn.recv_bytes().decode("utf-8"))
            x = np.frombuffer(conn.recv_bytes(), dtype=float).copy()
        except (EOFError, OSError):
            break
        if "scene" in head:
            scene = None if head["scene"] is None else Scene.from_table(Table(head["scene"], "scene"))
        if "goal" in head:
            source.retarget(np.asarray(head["goal"], dtype=float))  # type: ignore[attr-defined]
        if len(x) != nx or not math.isfinite(head["t"]):
            break
        try:
            plan = source(x, float(head["t"]), scene)
        except Exception as exc:  # any planner error is the parent's to report, as a failed plan
            why = f"planner raised {type(exc).__name__}: {exc}"
            plan = ReferencePlan(np.zeros((0, nx)), PlanStatus.ERROR, why, 0.0)
        configs = np.ascontiguousarray(plan.configs, dtype=float).reshape(-1, nx)
        edges = np.ascontiguousarray(plan.tree_edges, dtype=float).reshape(-1, 6)
        reply = {
            "status": plan.status.value,
            "message": plan.message,
            "wall_time": plan.wall_time,
            "configs": len(configs),
            "edges": len(edges),
        }
        try:
            conn.send_bytes(json.dumps(reply).encode("utf-8"))
            conn.send_bytes(configs.tobytes())
            conn.send_bytes(edges.tobytes())
        except OSError:
            break
    conn.close()
