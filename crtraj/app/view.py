"""Use case: look at a result (`crtraj view`): one standalone HTML page, a PNG or MP4 of it, or the live view
served on 127.0.0.1; a second result is drawn beside the first as a ghost."""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from crtraj.core import interrupt
from crtraj.core.errors import InputError
from crtraj.core.fileio import check_output_file, check_outputs_not_inputs
from crtraj.io.results import Result, read_result
from crtraj.viz.live import LiveView
from crtraj.viz.render import Picture, parse_size, render_mp4, render_png
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


def serve(
    result: Mapping[str, Any] | Result,
    label: str,
    open_browser: bool,
    play: bool | None = None,
    vis: Visualizer | None = None,
) -> int:
    """Serve a result in the full page on 127.0.0.1 until Ctrl-C; returns 0. vis: a served Visualizer to show it
    on (a live view's, whose page is open already and reloads to the result); None: a new one."""
    res = read_result(result)
    try:  # Ctrl-C is the normal way out, whenever it comes; leaving the block stops the server
        if vis is not None:
            vis.show_result(res, play=play)
        with vis if vis is not None else Visualizer.for_result(res, server=True, play=play) as shown:
            print(f"serving {label} ({res.kind}, {len(res.t)} waypoints) at {shown.url}", flush=True)
            if open_browser:
                shown.open()
            print("press Ctrl-C to stop", flush=True)
            while True:
                time.sleep(_IDLE_S)
    except KeyboardInterrupt:
        interrupt.acknowledge()  # Ctrl-C is a server's normal end: exit 0
        print("stopped", flush=True)
    return 0


class LiveSession:
    """`crtraj replan --view`: the loop feeds a served full page while it runs (`crtraj.viz.live.LiveView`);
    afterwards the same page shows the finished run until Ctrl-C. open_browser: open the page at the start."""

    def __init__(self, open_browser: bool) -> None:
        self.open_browser = open_browser
        self.view: LiveView | None = None

    def start(self, loop: Any) -> Any:
        """Serve the live page of `loop` (a `ClosedLoop`); returns its observer (the feed)."""
        self.view = LiveView.for_loop(loop)
        print(f"live view of the run at {self.view.url}", flush=True)
        if self.open_browser:
            self.view.vis.open()
        return self.view.feed

    def stop(self) -> None:
        """Stop feeding the page (the loop has ended) and print the feed's counts."""
        if self.view is None:
            return
        c = self.view.stop_feed()
        print(
            f"  live view: {c['published']} states, {c['drawn']} drawn, {c['dropped']} dropped frames (a newer state "
            f"came before the view drew it; the run's files have every state), {c['failed']} failed draws",
            flush=True,
        )

    def serve(self, result: Mapping[str, Any] | Result) -> int:
        """Show the finished run on the live page until Ctrl-C (a new server when the loop never started)."""
        if self.view is None:
            return serve(result, "the run", self.open_browser)
        return serve(result, "the run", False, vis=self.view.vis)

    def close(self) -> None:
        """Stop the feed and the server (idempotent)."""
        if self.view is not None:
            self.view.close()


def _outputs(args: argparse.Namespace) -> dict[str, Any]:
    return {"--html": args.html, "--png": getattr(args, "png", None), "--mp4": getattr(args, "mp4", None)}


def _pictures(vis: Visualizer, args: argparse.Namespace) -> None:
    """Write --png and --mp4 of the page drawn by `vis` (the page goes through a temporary file)."""
    size = parse_size(args.size)
    tl = vis.timeline
    duration = float(tl.t[-1]) if tl is not None and len(tl.t) else 0.0
    at = args.at if args.at is not None else (float(tl.t[tl.closest_index]) if tl is not None else 0.0)
    if not (math.isfinite(at) and 0.0 <= at <= duration):
        raise InputError(f"--at: expected a time in [0, {duration:g}] s, got {args.at}")
    if not (math.isfinite(args.fps) and 0.5 <= args.fps <= 60.0):
        raise InputError(f"--fps: expected 0.5 to 60 frames per second, got {args.fps}")
    with tempfile.TemporaryDirectory(prefix="crtraj-view-") as tmp:
        page = vis.save_html(Path(tmp) / "view.html")
        pic = Picture(page=page, size=size, at=at, fps=args.fps)
        for flag, path in (("--png", args.png), ("--mp4", args.mp4)):
            if path is None:
                continue
            try:
                out = render_png(pic, Path(path)) if flag == "--png" else render_mp4(pic, Path(path), duration)
            except RuntimeError as exc:  # the browser failed: one line, what was written stays
                raise InputError(f"{flag}: {exc}") from None
            what = (
                f"{size[0]}x{size[1]} px at t = {at:.2f} s"
                if flag == "--png"
                else f"{duration:.1f} s at {args.fps:g} fps"
            )
            print(f"wrote {out} ({what})")


def view_command(args: argparse.Namespace) -> int:
    """`crtraj view RESULT [COMPARE] [--html FILE] [--png FILE] [--mp4 FILE]` (arguments from `crtraj.cli`);
    returns the exit code."""
    outputs = {k: v for k, v in _outputs(args).items() if v is not None}
    compare = getattr(args, "compare", None)
    if outputs:  # before the result is read: an output that is the result would destroy it
        check_outputs_not_inputs(outputs, {"RESULT": args.result, "COMPARE": compare})
        for name, path in outputs.items():
            check_output_file(path, name)
    if "--png" in outputs or "--mp4" in outputs:
        parse_size(args.size)  # a bad size is refused before any work
    result = read_result(args.result)
    play = False if args.no_play else None
    if not outputs and compare is None:
        return serve(result, str(args.result), not args.no_browser, play)
    vis = Visualizer.for_result(result, play=play)
    try:
        if compare is not None:
            vis.compare(read_result(compare))
        if args.html is not None:
            path = vis.save_html(args.html)
            print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB); open it in any browser, no server needed")
        if "--png" in outputs or "--mp4" in outputs:
            _pictures(vis, args)
        if not outputs:
            raise InputError("COMPARE: a comparison is written, not served: add --html FILE (or --png/--mp4)")
    finally:
        vis.close()
    return 0
