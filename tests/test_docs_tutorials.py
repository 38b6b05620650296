"""Every shell block of docs/tutorials/ runs as written, against the simulators (issue 36).

Each tutorial page is followed as a reader follows it: its ```bash blocks in order, in one folder holding copies
of problems/ and examples/, with the simulated devices (`crtraj sim-device`, `crtraj sim-dynamixel`) where the
page starts them. A block that needs what a test machine does not have (real servos on /dev/ttyUSB0, a motion
capture's marker file, a robot's ROS driver, the network) carries the marker
``<!-- docs-test: skip (what it needs) -->`` on the line before its fence (docs/contributing.md); every other
block runs.

How a block is read: each command line (``\\`` continues it) runs with bash; `.venv/bin/` is the test's
interpreter's, a bare `crtraj` is found on PATH there too, /dev/pts/N is the pseudo-terminal the simulator
printed, and every 127.0.0.1:PORT of the page is a free port of this machine (the same one wherever the page
names it). ``CMD &`` starts in the background and runs on once it printed its first line (a simulator serving,
a feed sending); ``kill %N`` stops the block's Nth such job, and the block's end stops the rest. A command whose
comment says ``until Ctrl-C`` serves until it prints ``press Ctrl-C to stop``; then it gets its Ctrl-C and must
exit 0. Every other command exits 0, or with the ``(exit N)`` the tutorial shows under it, and prints every line
shown under it (``#   ...`` lines; ``...`` in them stands for any text); a command whose simulator answered
too late (a starved machine: the stream's telemetry watchdog, a Dynamixel read without reply, a servo's bus
watchdog, a loop that missed its wall-clock step deadline until it timed out) makes its block run again from its
start, with fresh simulators, at most three times in all. BROWSER is a program that opens nothing.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, default_sigint

TUTORIALS = ROOT / "docs" / "tutorials"
SKIP_MARKER = "<!-- docs-test: skip ("
_BLOCK = re.compile(r"^(?:<!-- docs-test: skip \((?P<why>[^)]+)\) -->\n)?```bash\n(?P<text>.*?)^```", re.S | re.M)
_READY_PTY = re.compile(r"sim-dynamixel on (/dev/pts/\d+)")
_EXIT = re.compile(r"^\(exit (\d+)\) ")
_PORT = re.compile(r"127\.0\.0\.1:(\d{4,5})\b")
SERVES = "until Ctrl-C"
SERVING = "press Ctrl-C to stop"
HANG_S = 800.0  # a hang bound only
# what a starved machine makes of a simulator's replies: the stream's telemetry watchdog (0.1 s), a Dynamixel read
# the simulated chain did not answer within the SDK's reply timeout (34 ms, tried 3 times), a simulated servo's
# Bus Watchdog (no instruction for 100 ms; the stream says "check the host's load")
STARVED = ("telemetry lost: nothing valid for", "cannot read register", "its bus watchdog stopped it")
# and a loop whose steps missed the problem's wall-clock step deadline (paper_dynamic.toml: 4 ms) so often that it
# held until its time ran out
_LATE_LOOP = re.compile(r"\b[1-9]\d* deadline misses(.|\n)*goal not reached")


class StarvedError(Exception):
    """A command of the block was starved (`starved`): the block runs again from its start."""


def starved(output: str) -> bool:
    """The output says the machine was too loaded for the simulator or the loop's step deadline."""
    return any(s in output for s in STARVED) or _LATE_LOOP.search(output) is not None


STARVED_RUNS = 3


def blocks(page: Path) -> list[tuple[str | None, str]]:
    """The page's ```bash blocks in order: (the skip marker's reason or None, the block's text)."""
    return [(m.group("why"), m.group("text")) for m in _BLOCK.finditer(page.read_text(encoding="utf-8"))]


def _runs(page: Path) -> str:
    """The text of the page's blocks that run."""
    return "".join(text for why, text in blocks(page) if why is None)


def _tools(page: Path) -> bool:
    """The page's blocks need a tool or extra beyond crtraj: Chromium and ffmpeg (view --png/--mp4) or the
    Dynamixel SDK (--dynamixel)."""
    return any(flag in _runs(page) for flag in ("--png", "--mp4", "--dynamixel"))


def _pages(tools: bool) -> list:
    """One pytest param per tutorial page with a block to run, those with or without tools."""
    pages = sorted(TUTORIALS.glob("*.md"))
    return [pytest.param(p.name, id=p.name) for p in pages if _runs(p) and _tools(p) == tools]


def steps(text: str) -> list[tuple[str, list[str]]]:
    """The block's commands (continued lines joined), each with the output lines shown under it (``#   ...``)."""
    out: list[tuple[str, list[str]]] = []
    for line in text.replace("\\\n", " ").splitlines():
        if line.startswith("#   ") and out:
            out[-1][1].append(line[4:].strip())
        elif line.strip() and not line.startswith("#"):
            out.append((line, []))
    return out


def _shown(expected: str) -> re.Pattern:
    """The tutorial's shown output line as a pattern: ``...`` stands for any text, /dev/pts/N for a pty."""
    parts = [re.escape(p).replace("/dev/pts/N", r"/dev/pts/\d+") for p in expected.split("...")]
    return re.compile(".*".join(parts))


def check_step(command: str, shown: list[str], proc: subprocess.CompletedProcess) -> None:
    """Exit code 0 (or the ``(exit N)`` shown) and every shown line somewhere in the output."""
    output = proc.stdout + proc.stderr
    want = next((int(m.group(1)) for m in map(_EXIT.match, shown) if m), 0)
    assert proc.returncode == want, f"{command}\nexit {proc.returncode}, expected {want}\n{output[-3000:]}"
    for line in shown:
        pattern = _shown(_EXIT.sub("", line))
        assert any(pattern.fullmatch(out) for out in output.splitlines()), f"{command}\nno line {line!r}\n{output}"


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Reader:
    """The reader's terminal for one page: its folder, environment, ports and background jobs."""

    def __init__(self, folder: Path, page_text: str) -> None:
        self.folder = folder
        bin_dir = Path(sys.executable).parent
        self.env = {**os.environ, "PYTHONPATH": str(ROOT), "BROWSER": "true"}
        self.env["PATH"] = f"{bin_dir}{os.pathsep}{self.env.get('PATH', '')}"
        self.bin = f"{bin_dir}/"
        self.ports = {p: _free_port() for p in sorted(set(_PORT.findall(page_text)))}
        self.pty: str | None = None
        self.jobs: list[subprocess.Popen] = []

    def shell(self, command: str) -> str:
        """The command as this machine runs it (its comment dropped)."""
        command = command.replace(".venv/bin/", self.bin)
        command = _PORT.sub(lambda m: f"127.0.0.1:{self.ports[m.group(1)]}", command)
        if self.pty is not None:
            command = command.replace("/dev/pts/N", self.pty)
        return re.sub(r"\s+#.*$", "", command).strip()

    def _popen(self, shell: str) -> subprocess.Popen:
        out = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True}
        return subprocess.Popen(
            ["bash", "-c", shell],
            cwd=self.folder,
            env=self.env,
            start_new_session=True,
            preexec_fn=_reader_child(shell),
            **out,
        )

    def background(self, shell: str) -> str:
        """Start `shell` (without its ``&``); its output up to its first line (a pty it names is kept)."""
        job = self._popen(shell)
        self.jobs.append(job)
        line = job.stdout.readline()
        assert line, f"{shell}\nexited {job.wait()} without a word"
        while _READY_PTY.search(line) is None and "sim-dynamixel" in shell and "--pty" in shell:
            more = job.stdout.readline()  # with --at it homes first, then prints its path
            assert more, f"{shell}\nprinted no pseudo-terminal:\n{line}"
            line += more
        found = _READY_PTY.search(line)
        self.pty = found.group(1) if found else self.pty
        return line

    def serve(self, shell: str) -> subprocess.CompletedProcess:
        """Run a server until it says it serves, then press Ctrl-C (to its process group, as a terminal does)."""
        proc = self._popen(shell)
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if SERVING in line:
                os.killpg(proc.pid, signal.SIGINT)
                break
        seen.append(proc.stdout.read())
        proc.stdout.close()
        return subprocess.CompletedProcess(shell, proc.wait(timeout=HANG_S), "".join(seen), "")

    def run(self, shell: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["bash", "-c", shell],
            cwd=self.folder,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=HANG_S,
            preexec_fn=_reader_child(shell),
        )

    def run_fed(self, shell: str, last: bool = True) -> subprocess.CompletedProcess:
        """Run `shell`; `StarvedError` when the simulator's replies came too late (`STARVED`: only a machine too loaded
        to run both processes on time starves a simulator on 127.0.0.1 or a pty; the command then stops safely, as
        it must, and says so) and this is not the `last` try of its block."""
        proc = self.run(shell)
        if not last and starved(proc.stdout + proc.stderr):
            raise StarvedError(shell)
        return proc

    def stop(self, job: subprocess.Popen) -> None:
        """SIGTERM to the job's process group (the shell and the program), then wait for it."""
        if job.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(job.pid, signal.SIGTERM)
            job.wait(timeout=60)
        job.stdout.close()

    def block(self, text: str) -> None:
        """Run one block, and again from its start (its simulators started afresh: a stopped stream left the
        device elsewhere) when a command was starved, at most `STARVED_RUNS` times in all."""
        for attempt in range(1, STARVED_RUNS + 1):
            try:
                self._block_once(text, last=attempt == STARVED_RUNS)
                return
            except StarvedError:
                continue

    def _block_once(self, text: str, last: bool) -> None:
        """Run one block, step by step, and stop its jobs at its end."""
        try:
            for command, shown in steps(text):
                shell = self.shell(command)
                if shell.endswith("&"):
                    check_step(command, shown, subprocess.CompletedProcess(shell, 0, self.background(shell[:-1]), ""))
                elif (m := re.fullmatch(r"kill %(\d+)", shell)) is not None:
                    self.stop(self.jobs[int(m.group(1)) - 1])
                elif SERVES in command:
                    check_step(command, shown, self.serve(shell))
                else:
                    check_step(command, shown, self.run_fed(shell, last))
        finally:
            for job in self.jobs:
                self.stop(job)
            self.jobs = []
            self.pty = None


# The simulated devices and the commands that stream to them or feed them run ahead of the suite's other work
# (nice -10, where the user may raise priority): a simulator stands in for separate hardware with its own processor,
# and a page's stream is the only real-time work of a reader's machine. The suite's other workers and the budget's
# CPU hog would otherwise starve a 100 Hz stream past its 100 ms watchdogs. Only those: a page's planning, rendering
# and encoding at that priority would starve the other workers' real-time tests (a headless Chromium went silent).
READER_NICE = -10
_REAL_TIME = re.compile(r"sim-device|sim-dynamixel|feed-replay|--udp\b|--dynamixel\b|--stream\b|--feed\b|\bhome\b")


def _reader_child(shell: str):
    """Popen preexec_fn of a reader's command `shell`: a terminal's job takes Ctrl-C (a suite run in the background
    hands SIGINT on ignored, conftest's `default_sigint`); a real-time one at `READER_NICE` when allowed."""
    real_time = _REAL_TIME.search(shell) is not None

    def child() -> None:
        default_sigint()
        if real_time:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, 0, READER_NICE)

    return child


def _follow(page: str, folder: Path) -> None:
    """The page's blocks, in order, in one folder (a later block reads what an earlier one wrote)."""
    for name in ("problems", "examples"):
        shutil.copytree(ROOT / name, folder / name)
    path = TUTORIALS / page
    reader = Reader(folder, path.read_text(encoding="utf-8"))
    for why, text in blocks(path):
        if why is None:
            reader.block(text)


@pytest.mark.slow
@pytest.mark.parametrize("page", _pages(tools=False))
def test_tutorial_shell_blocks_run_as_written(page, tmp_path):
    _follow(page, tmp_path)


def test_every_tutorial_block_runs_or_says_what_it_needs():
    """Every ```bash block of the tutorials is run by the test above, or its marker names what it needs; a
    marker is read only right before a fence (a misplaced one would silently run nothing or skip nothing)."""
    found = skipped = 0
    for page in sorted(TUTORIALS.glob("*.md")):
        text = page.read_text(encoding="utf-8")
        assert text.count(SKIP_MARKER) == sum(why is not None for why, _ in blocks(page)), page.name
        assert text.count("```bash\n") == len(blocks(page)), page.name
        for why, _ in blocks(page):
            found += 1
            skipped += why is not None
            assert why is None or len(why.split()) >= 2, f"{page.name}: say what the block needs: {why!r}"
    assert found > skipped > 0
    assert _pages(tools=False) and _pages(tools=True), "the tutorials have blocks to run"


def test_tutorial_step_check_sees_a_wrong_exit_code_and_a_missing_line():
    """The checks above fail on a command that exits otherwise than shown, or does not print a shown line."""
    got = steps("a --x \\\n  --y\n#   (exit 2) crtraj: error: servo id 7 (z): not homed ... run crtraj home ...\nb\n")
    assert got == [
        ("a --x    --y", ["(exit 2) crtraj: error: servo id 7 (z): not homed ... run crtraj home ..."]),
        ("b", []),
    ]
    line = "crtraj: error: servo id 7 (z): not homed since its power-up; run crtraj home --dynamixel /dev/pts/3\n"
    check_step("a", got[0][1], subprocess.CompletedProcess("a", 2, "", line))
    with pytest.raises(AssertionError, match="exit 1, expected 2"):
        check_step("a", got[0][1], subprocess.CompletedProcess("a", 1, "", line))
    with pytest.raises(AssertionError, match="no line"):
        check_step("a", got[0][1], subprocess.CompletedProcess("a", 2, "", line.replace("not homed", "homed")))


def test_a_reader_maps_the_pages_ports_and_the_tools(tmp_path):
    """One page port is one free port wherever it appears; .venv/bin/ is this interpreter's; comments go."""
    reader = Reader(tmp_path, "x --udp 127.0.0.1:9870 y udp://127.0.0.1:9871 z 127.0.0.1:9870")
    assert len(set(reader.ports.values())) == 2
    shell = reader.shell(".venv/bin/crtraj a --udp 127.0.0.1:9870 --to udp://127.0.0.1:9870   # a note")
    assert shell == f"{Path(sys.executable).parent}/crtraj a --udp 127.0.0.1:{reader.ports['9870']} --to " + (
        f"udp://127.0.0.1:{reader.ports['9870']}"
    )


def test_a_starved_simulator_reruns_the_block_and_nothing_else_does(tmp_path):
    """A block with a starved command runs again from its start (at most 3 runs); any other failure is final."""
    reader = Reader(tmp_path, "")
    count = "n=$(cat {0} 2>/dev/null || echo 0); echo $((n+1)) > {0}; "
    flaky = "echo start >> log\n" + count.format("a")
    flaky += "[ $n -ge 1 ] || { echo 'telemetry lost: nothing valid for 428 ms'; exit 1; }\n"
    reader.block(flaky)
    assert (tmp_path / "a").read_text() == "2\n" and (tmp_path / "log").read_text() == "start\nstart\n"
    with pytest.raises(AssertionError, match="exit 1, expected 0"):
        reader.block(count.format("b") + "echo 'servo id 7 (z): cannot read register 126'; exit 1\n")
    assert (tmp_path / "b").read_text() == "3\n"
    with pytest.raises(AssertionError, match="exit 2, expected 0"):
        reader.block(count.format("c") + "echo 'not homed'; exit 2\n")
    assert (tmp_path / "c").read_text() == "1\n"
    late = "reached goal no, 542 deadline misses (deadline 4 ms)\ncrtraj: replan failed: timeout: goal not reached"
    assert (
        starved(late) and not starved(late.replace("542", "0")) and not starved("reached goal yes, 3 deadline misses")
    )
