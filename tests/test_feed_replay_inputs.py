"""`crtraj feed-replay` and issue 27: every number of the problem it replays and of its flags goes through
the bounded reader; a bad one is one stderr line naming the field, no traceback, nothing sent, and the
problem's folder byte-identical (the command writes no files)."""

from __future__ import annotations

import hashlib
import socket
from pathlib import Path

import pytest
from conftest import paper_copy

from crtraj.cli import main

BIG = "1" + "0" * 400


def _snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*")}


def _received(sock: socket.socket) -> list[bytes]:
    """Every datagram already queued on `sock` (localhost delivery is done by the time sendto returns)."""
    got = []
    sock.setblocking(False)
    while True:
        try:
            got.append(sock.recv(65536))
        except BlockingIOError:
            return got


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("center = [0.0, 90.0, 330.0]", "center = [0.0, 90.0, 1e300]", "scene.obstacle[0].center[2]"),
        ("mean = 60.0", f"mean = {BIG}", "scene.obstacle[0].radius.mean"),
        ("omega = 0.5", "omega = nan", "scene.obstacle[0].radius.omega"),
        ("amplitude = 15.0", "amplitude = inf", "scene.obstacle[1].radius.amplitude"),
        ("phase = 0.0 }", "phase = 1e308 }", "scene.obstacle[0].radius.phase"),
        ('name = "upper"', "name = 7", "scene.obstacle[0].name"),
    ],
)
def test_a_bad_number_in_the_replayed_problem_is_one_line_and_nothing_is_sent(tmp_path, capsys, old, new, field):
    problem = paper_copy(tmp_path)
    text = problem.read_text()
    assert old in text
    problem.write_text(text.replace(old, new, 1))
    before = _snapshot(tmp_path)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        rc = main(["feed-replay", str(problem), "--udp", f"127.0.0.1:{port}", "--duration", "0.01"])
        sent = _received(sock)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and err.startswith(f"crtraj: error: {field}") and "Traceback" not in err
    assert sent == [] and _snapshot(tmp_path) == before


@pytest.mark.parametrize(
    ("flag", "value"),
    [
        ("--rate", "nan"),
        ("--rate", "1e400"),
        ("--noise", "\u0661"),
        ("--duration", "1_0"),
        ("--seed", BIG),
        ("--seed", "\u00b2"),
        ("--latency", "-1"),
    ],
)
def test_a_bad_flag_number_is_one_line_and_nothing_is_sent(tmp_path, capsys, flag, value):
    problem = paper_copy(tmp_path)
    before = _snapshot(tmp_path)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
        argv = ["feed-replay", str(problem), "--udp", f"127.0.0.1:{port}", "--duration", "0.01", flag, value]
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse refuses a flag it cannot convert
            rc = int(exc.code)
        sent = _received(sock)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and err.startswith("crtraj: error: ") and "Traceback" not in err
    assert flag.lstrip("-") in err
    assert sent == [] and _snapshot(tmp_path) == before


def test_the_problem_path_must_be_a_readable_file(tmp_path, capsys):
    (tmp_path / "p.toml").mkdir()
    rc = main(["feed-replay", str(tmp_path / "p.toml"), "--udp", "127.0.0.1:9", "--duration", "0.01"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "p.toml" in err and "Traceback" not in err
