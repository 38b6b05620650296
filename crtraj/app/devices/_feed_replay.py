"""Use case: replay a problem's obstacles over UDP as a motion-capture bridge would (`crtraj feed-replay`).

The scene's obstacles are sampled from their own time functions (`crtraj.world.replay.FeedReplay`), with
noise, latency, jitter and dropped messages, and sent to a `crtraj replan --feed` listener on 127.0.0.1.
Units: mm, s, Hz.

Inputs: the problem file (`crtraj.io.problem.Problem.load`: every number of its scene through the bounded
field reader, `crtraj.core.fields`) and the flags (`ReplayOptions`: finite, within each option's bounds).
A bad value is one error line naming it, before anything is sent. The command writes no files.
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import time

from crtraj.core import interrupt
from crtraj.core.errors import InputError
from crtraj.hardware.transport import parse_hostport
from crtraj.io.problem import Problem
from crtraj.world.replay import FeedReplay, ReplayOptions
from crtraj.world.scene import Scene


def feed_replay_command(args: argparse.Namespace) -> int:
    """`crtraj feed-replay PROBLEM --udp 127.0.0.1:PORT ...` (arguments from `crtraj.cli`); the exit code."""
    host, port = parse_hostport(args.udp.removeprefix("udp://"), "--udp")
    if host not in ("127.0.0.1", "localhost"):
        raise InputError(f"--udp: the replay sends to a feed on 127.0.0.1 only, got host {host!r}")
    if port == 0:
        raise InputError("--udp: port must be the feed's port (1..65535), got 0")
    options = ReplayOptions(
        rate=args.rate,
        noise=args.noise,
        latency=args.latency,
        jitter=args.jitter,
        dropout=args.dropout,
        duration=args.duration,
        seed=args.seed,
    )
    problem = Problem.load(args.problem)
    replay = FeedReplay(Scene.from_table(problem.section("scene")), options)
    o = options
    print(
        f"replaying {len(replay.ids)} obstacles of '{problem.name}' ({', '.join(replay.ids)}) to udp://{host}:{port} "
        f"at {o.rate:g} Hz for {o.duration:g} s: noise {o.noise:g} mm, latency {o.latency:g} s, jitter "
        f"{o.jitter:g} s, dropout {o.dropout:g}",
        flush=True,
    )
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        target = ("127.0.0.1", port)

        def send(datagram: bytes) -> None:
            # nobody listening yet (ICMP port unreachable): a bridge keeps sending regardless
            with contextlib.suppress(OSError):
                sock.sendto(datagram, target)

        try:
            counts = replay.run(send, time.perf_counter, time.sleep)
            ended = "finished"
        except KeyboardInterrupt:
            interrupt.acknowledge()  # Ctrl-C is a replay's normal end: exit 0
            counts, ended = replay.counts(), "interrupted"
    print(
        f"feed-replay {ended}: {counts.measured} states measured, {counts.sent} sent in {counts.datagrams} "
        f"datagrams, {counts.dropped} dropped",
        flush=True,
    )
    return 0
