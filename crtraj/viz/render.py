"""Pictures of the view's page: one frame as PNG, or the whole run as an MP4 video (ffmpeg), by headless Chromium.

The page is the standalone HTML (`crtraj.viz.view.Visualizer.static_html`) written to a file; Chromium opens it
offline at a fixed size in pixels, the page's clock is paused and seeked to each time (s), and the picture taken.
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
from pathlib import Path

from crtraj.core.errors import InputError
from crtraj.core.interrupt import popen_child
from crtraj.viz.chromium import Chromium

DEFAULT_SIZE = (1280, 800)
MAX_FRAMES = 3000  # a video's frame count is bounded (fps x duration)


@dataclasses.dataclass(frozen=True)
class Picture:
    """What to render: page (an HTML file), size (width, height) px; at: time (s) of a still; fps of a video."""

    page: Path
    size: tuple[int, int] = DEFAULT_SIZE
    at: float = 0.0
    fps: float = 10.0


def parse_size(text: str, name: str = "--size") -> tuple[int, int]:
    """'WxH' -> (W, H) px, each in [64, 4096]; a one-line error naming `name` otherwise."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise InputError(f"{name}: expected WIDTHxHEIGHT in pixels such as 1280x800, got {text!r}")
    w, h = (int(p) for p in parts)
    if not (64 <= w <= 4096 and 64 <= h <= 4096):
        raise InputError(f"{name}: width and height must be in [64, 4096] px, got {w}x{h}")
    return w, h


def render_png(pic: Picture, out: Path) -> Path:
    """Write the page at time pic.at (s) as a PNG of pic.size px to `out`; returns out."""
    with Chromium() as browser:
        tab = browser.open(pic.page.resolve().as_uri(), *pic.size, offline=True)
        tab.seek(pic.at)
        data = tab.screenshot()
        tab.close()
    out.write_bytes(data)
    return out


def render_mp4(pic: Picture, out: Path, duration: float) -> Path:
    """Write the page played from 0 to duration (s) at pic.fps as an H.264 MP4 to `out`; returns out.

    Raises InputError (one line) when ffmpeg is not installed.
    """
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        raise InputError("--mp4: ffmpeg is not installed (Debian: apt-get install ffmpeg); --png still works")
    n = min(MAX_FRAMES, int(duration * pic.fps) + 1)
    cmd = [ffmpeg, "-loglevel", "error", "-y", "-f", "image2pipe", "-framerate", f"{pic.fps:g}", "-i", "-",
           "-c:v", "libx264", "-pix_fmt", "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", str(out)]  # fmt: skip
    with Chromium() as browser:
        tab = browser.open(pic.page.resolve().as_uri(), *pic.size, offline=True)
        enc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE, **popen_child())
        try:
            for k in range(n):
                tab.seek(min(duration, k / pic.fps))
                enc.stdin.write(tab.screenshot())
        finally:
            enc.stdin.close()
            err = enc.stderr.read().decode(errors="replace").strip()
            enc.wait()
            tab.close()
    if enc.returncode != 0:
        raise InputError(f"--mp4: ffmpeg failed: {err.splitlines()[-1] if err else enc.returncode}")
    return out
