"""A git revision's source tree in a temporary folder, for the benchmarks that run old and new code side by side
(`plan.py --baseline`, `replan.py --baseline`): each side runs in its own process with PYTHONPATH on its tree."""

from __future__ import annotations

import io
import subprocess
import tarfile
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@contextmanager
def revision_tree(rev: str) -> Iterator[str]:
    """The tree of git revision `rev` of this repository, extracted into a temporary folder (removed afterwards)."""
    with tempfile.TemporaryDirectory(prefix="crtraj-baseline-") as tmp:
        tar = subprocess.run(["git", "-C", str(ROOT), "archive", rev], capture_output=True, check=True).stdout
        with tarfile.open(fileobj=io.BytesIO(tar)) as t:
            t.extractall(tmp, filter="data")
        yield tmp
