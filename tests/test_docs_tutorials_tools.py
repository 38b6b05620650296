"""The tutorial pages that need Chromium and ffmpeg (crtraj view renders in headless Chromium and encodes with
ffmpeg) or the Dynamixel SDK, run as written by `test_docs_tutorials`'s reader. A file of their own: the suite's
workers (pytest-xdist, one file per worker) then run these pages beside the others, not after them."""

from __future__ import annotations

import pytest
from conftest import require_module, require_tool
from test_docs_tutorials import TUTORIALS, _follow, _pages, _runs


@pytest.mark.slow
@pytest.mark.parametrize("page", _pages(tools=True))
def test_tutorial_shell_blocks_with_tools_run_as_written(page, tmp_path):
    runs = _runs(TUTORIALS / page)
    if "--png" in runs or "--mp4" in runs:
        require_tool("chromium", "chromium-browser", "google-chrome", hint="Debian: apt-get install chromium")
    if "--mp4" in runs:
        require_tool("ffmpeg", hint="Debian: apt-get install ffmpeg")
    if "--dynamixel" in runs:
        require_module("dynamixel_sdk", "pip install 'crtraj[dynamixel]'")
    _follow(page, tmp_path)
