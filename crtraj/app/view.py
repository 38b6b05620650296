"""Use case: look at a result: one standalone HTML page, or the live view served on 127.0.0.1 (`crtraj view`)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping
from typing import Any

from crtraj.core.fileio import check_output_file, check_outputs_not_inputs
from crtraj.io.results import Result, read_result
from crtraj.viz.view import Visualizer

# How long the serving loop sleeps between checks for Ctrl-C (s); any value works, Ctrl-C interrupts the sleep.
_IDLE_S = 3600.0


def static_html(result: Mapping[str, Any] | Result, play: bool | None = None) -> str:
    """The result's 3-D replay as one self-contained HTML page (no server involved)."""
    vis = Visualizer.for_result(result, play=play)
    try:
        return vis.static_html()
    finally:
        vis.close()


def serve(result: Mapping[str, Any] | Result, label: str, open_browser: bool, play: bool | None = None) -> int:
    """Serve a result in the meshcat view on 127.0.0.1 until Ctrl-C; returns 0."""
    res = read_result(result)
    try:  # Ctrl-C is the normal way out, whenever it comes; leaving the block stops the server
        with Visualizer.for_result(res, server=True, play=play) as vis:
            print(f"serving {label} ({res.kind}, {len(res.t)} waypoints) at {vis.url}", flush=True)
            if open_browser:
                vis.open()
            print("press Ctrl-C to stop", flush=True)
            while True:
                time.sleep(_IDLE_S)
    except KeyboardInterrupt:
        print("stopped", flush=True)
    return 0


def view_command(args: argparse.Namespace) -> int:
    """`crtraj view RESULT [--html FILE]` (arguments from `crtraj.cli`); returns the exit code."""
    if args.html is not None:  # before the result is read: an --html that is the result would destroy it
        check_outputs_not_inputs({"--html": args.html}, {"RESULT": args.result})
        check_output_file(args.html, "--html")
    result = read_result(args.result)
    play = False if args.no_play else None
    if args.html is not None:
        vis = Visualizer.for_result(result, play=play)
        try:
            path = vis.save_html(args.html)
        finally:
            vis.close()
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); open it in any browser, no server needed")
        return 0
    return serve(result, str(args.result), not args.no_browser, play)
