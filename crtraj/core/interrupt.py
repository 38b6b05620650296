"""One interrupt policy for every command: Ctrl-C (SIGINT) and SIGTERM stop it at the next safe point.

`policy` installs one handler for both signals while a command runs. The handler records the request in a
flag that nothing can clear by accident and raises `Interrupted` (a KeyboardInterrupt, so the places that
hold a device on Ctrl-C still do). Native code may swallow that exception: CasADi calls Python signal checks
inside its solvers and turns the exception into a stopped solve or a SystemError. The flag survives that:
`check` raises again at the next safe point (between rod solves, after a solve, before any output is
committed), and every commit of `crtraj.core.fileio` calls `check` first, so an interrupted command replaces
nothing the user had. A second signal raises again (a harder stop), still through the same clean unwinding.

Exit codes (`exit_code`): 130 after SIGINT, 143 after SIGTERM (128 + the signal number, as a shell reports a
process the signal killed). Commands whose normal end is Ctrl-C (the servers: view, sim-device, ...) call
`acknowledge` and exit 0.

Children die with their parent (`die_with_parent`, `popen_child`): Linux delivers a signal to a child whose
parent thread ends, even when the parent is SIGKILLed and no cleanup code of it runs; a program that starts
children of its own (a C compiler) runs under `run_guarded`, which ends its whole process group.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

SIGNALS = (signal.SIGINT, signal.SIGTERM)
_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_NAMES = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}


class Interrupted(KeyboardInterrupt):
    """A stop was requested by signal `signum` (SIGINT or SIGTERM)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


class _State:
    """The request of the running command: the first signal's number (0: none) and the signals seen."""

    signum = 0
    count = 0
    shield = 0  # > 0: cleanup is running, a signal is recorded but raises nothing


_state = _State()


def requested() -> int:
    """The number of the signal that asked this command to stop (0: none)."""
    return _state.signum


def check() -> None:
    """Raise `Interrupted` when a stop was requested (a safe point: call it between solves, before commits)."""
    if _state.signum and not _state.shield:
        raise Interrupted(_state.signum)


def acknowledge() -> None:
    """A SIGINT was this command's normal end (a server's Ctrl-C): forget it, so the command exits 0."""
    if _state.signum == signal.SIGINT:
        _state.signum = 0


def exit_code(signum: int) -> int:
    """The exit status of a command stopped by `signum`: 130 for SIGINT, 143 for SIGTERM."""
    return 128 + int(signum)


def message(signum: int) -> str:
    """The one stderr line of a command stopped by `signum`."""
    return f"crtraj: {_NAMES.get(signum, 'interrupted')}"


def _handle(signum: int, frame: Any) -> None:
    if not _state.signum:
        _state.signum = signum
    _state.count += 1
    if not _state.shield:
        raise Interrupted(_state.signum)


@contextlib.contextmanager
def shielded() -> Iterator[None]:
    """A step that a signal must not cut short (a folder swap, a cleanup): a signal inside is recorded and,
    when the block ends without an error, raised after it."""
    seen = _state.count
    _state.shield += 1
    try:
        yield
    finally:
        _state.shield -= 1
    if _state.count != seen:
        check()


def hold() -> None:
    """The command is stopping: from now on a signal is recorded, never raised (its last cleanup runs whole)."""
    _state.shield += 1


class _CasadiStopFilter:
    """sys.stderr while a command runs, without CasADi's line about the stop it caught (written in pieces:
    ``CasADi - <time> WARNING("KeyboardInterruptException") [...]``): a stop is reported once, by the command.
    Every other line passes unchanged."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self._held = ""

    def write(self, text: str) -> int:
        if not (self._held or text.startswith("CasADi - ")):
            return self._stream.write(text)
        self._held += text
        if "\n" in text:
            line, self._held = self._held, ""
            if "KeyboardInterruptException" not in line:
                self._stream.write(line)
        return len(text)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


@contextlib.contextmanager
def _quiet_casadi_stops() -> Iterator[None]:
    stderr = sys.stderr
    sys.stderr = _CasadiStopFilter(stderr)
    try:
        yield
    finally:
        if isinstance(sys.stderr, _CasadiStopFilter):
            sys.stderr = stderr


@contextlib.contextmanager
def policy(last: bool = False) -> Iterator[None]:
    """Install the handler of SIGINT and SIGTERM for the command run inside the block; restore the previous
    handlers after it, or, when the block is the `last` thing this process does, ignore both signals (the
    command is over; Python's own exit would otherwise let a late signal kill it without a word). A SIGINT
    ignored by the caller (a background job of a non-interactive shell) stays ignored, as Python does. Off the
    main thread (signals cannot be handled there) it only resets the flag."""
    _state.signum, _state.count, _state.shield = 0, 0, 0
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in SIGNALS}
    for s in SIGNALS:
        if old[s] is not signal.SIG_IGN or s == signal.SIGTERM:
            signal.signal(s, _handle)
    try:
        with _quiet_casadi_stops():
            yield
    finally:
        for s, h in old.items():
            signal.signal(s, signal.SIG_IGN if last else h if h is not None else signal.SIG_DFL)


# ------------------------------------------------------- temporary files
# the temporary files and folders of this process's writes not yet renamed into place or removed
# (crtraj.core.fileio adds and drops them); an interrupted command's end removes what is left
temporaries: set[Path] = set()


def remove_temporaries() -> None:
    """Remove every temporary file and folder of this process's unfinished writes (an interrupted command's)."""
    with shielded():
        for p in list(temporaries):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            temporaries.discard(p)


# ---------------------------------------------------------------- children
def _libc_prctl() -> Any:
    """libc's prctl, looked up once in the parent (a preexec hook must not search for libraries)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _libc_prctl()


def _prctl_deathsig(signum: int) -> bool:
    """Ask Linux to send `signum` to this process when its parent (thread) ends; False where unsupported."""
    return _PRCTL is not None and _PRCTL(_PR_SET_PDEATHSIG, int(signum), 0, 0, 0) == 0


def die_with_parent(parent_pid: int, signum: int = signal.SIGKILL) -> None:
    """In a child: die by `signum` when the parent `parent_pid` ends (also by SIGKILL). The child that lost its
    parent before the request took effect ends at once. Ctrl-C in a terminal reaches the whole process group:
    the child ignores SIGINT and leaves the stop to its parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the parent's handler a fork copied: SIGTERM just ends it
    _prctl_deathsig(signum)
    if os.getppid() != parent_pid:
        os._exit(1)


def popen_child(signum: int = signal.SIGKILL) -> dict[str, Any]:
    """Keyword arguments of `subprocess.Popen` for a child that must die with this process: a preexec hook
    that requests `signum` on the parent's death (the child is exec'd after it; the request survives exec)."""
    parent = os.getpid()

    def preexec() -> None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is the parent's to handle
        _prctl_deathsig(signum)
        if os.getppid() != parent:
            os._exit(1)

    return {"preexec_fn": preexec} if sys.platform.startswith("linux") else {}


# A guard between this process and a program that starts children of its own (a C compiler driver runs cc1
# and as): the program runs in a process group of its own, and the guard kills that whole group when it gets
# SIGTERM, which Linux sends it when this process dies (popen_child). SIGTERM stays blocked until the group
# exists, so no signal can come between the start and the handler.
_GUARD = """
import os, signal, subprocess, sys
signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
child = subprocess.Popen(sys.argv[1:], start_new_session=True,
                         preexec_fn=lambda: signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM}))
def stop(signum, frame):
    try:
        os.killpg(child.pid, signal.SIGKILL)
    except OSError:
        pass
    os._exit(128 + signum)
signal.signal(signal.SIGTERM, stop)
signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
sys.exit(child.wait())
"""


def run_guarded(cmd: list[str], timeout: float | None = None) -> subprocess.CompletedProcess[str]:
    """Run the program `cmd` to its end (text output captured), with every process it starts dying with this
    one: on this process's death (even by SIGKILL), on an exception here (Ctrl-C) and after `timeout` s
    (`subprocess.TimeoutExpired`, as `subprocess.run` raises it)."""
    guard = [sys.executable, "-I", "-c", _GUARD, *cmd]
    proc = subprocess.Popen(
        guard, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen_child(signal.SIGTERM)
    )
    try:
        out, err = proc.communicate(timeout=timeout)
    except BaseException:
        with shielded():
            proc.terminate()  # the guard kills the program's process group
            proc.communicate()
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)
