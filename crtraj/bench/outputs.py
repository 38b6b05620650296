"""The files of one bench command, written together at the end or not at all.

A bench command (`crtraj bench table1|suite|modes`) runs for minutes to hours and then writes several
files (tables, runs.csv, JSON, plots, a folder of OMPL logs). `OutputSet` holds them in memory until the
run is over; `commit` first checks every target (a folder is replaced only when it carries crtraj's
marker or holds only files crtraj writes there), then stages every file beside its target and only then
renames them into place one after the other, so a refused or failed write leaves every existing file as
it was. Nothing is written before `commit`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from crtraj.core.fileio import StagedDir, StagedFile, atomic_write_bytes, check_output_dir, check_output_file


@dataclass(frozen=True)
class _Folder:
    """A folder that is replaced as a whole: its files (relative name: bytes), the names an unmarked
    existing folder may hold, crtraj's marker kind, and the flag named in errors."""

    path: Path
    files: Mapping[str, bytes]
    replaceable: frozenset[str]
    marker: str
    what: str


def _bytes(data: bytes | str) -> bytes:
    return data.encode("utf-8") if isinstance(data, str) else data


class OutputSet:
    """Files and folders of one command, written on `commit` (see the module docstring).

    what: the flag that names the outputs in error lines (e.g. ``--out``).
    """

    def __init__(self, what: str = "--out") -> None:
        self.what = what
        self._files: dict[Path, bytes] = {}
        self._folders: list[_Folder] = []

    def file(self, path: str | os.PathLike[str], data: bytes | str) -> None:
        """Add one file (UTF-8 text or bytes) to write at `path`."""
        self._files[Path(path)] = _bytes(data)

    def folder(
        self,
        path: str | os.PathLike[str],
        files: Mapping[str, bytes | str],
        *,
        marker: str,
        replaceable: frozenset[str] = frozenset(),
    ) -> None:
        """Add a folder that replaces `path` as a whole, holding `files` and crtraj's `marker`.

        An existing folder at `path` is replaced only when it carries the marker or holds nothing but
        `replaceable` names; anything else refuses the whole set (nothing is written)."""
        data = {name: _bytes(v) for name, v in files.items()}
        self._folders.append(_Folder(Path(path), data, replaceable, marker, f"{self.what} ({Path(path).name})"))

    def check(self) -> None:
        """Refuse, in one `InputError` line, a target that cannot be written or replaced (nothing written)."""
        for f in self._folders:
            check_output_dir(f.path, f.what, f.replaceable, f.marker)
        for p in self._files:
            check_output_file(p, f"{self.what} ({p.name})")

    def commit(self) -> list[Path]:
        """Check every target, stage every file and folder, then move them all into place; the paths written
        (files first, then each folder's files). On any error the staged copies are removed and every
        existing file is left as it was."""
        self.check()
        staged_files: list[StagedFile] = []
        staged_dirs: list[StagedDir] = []
        try:
            for path, data in self._files.items():
                staged_files.append(StagedFile(path))
                staged_files[-1].write(data)
            for f in self._folders:
                staged_dirs.append(StagedDir(f.path, f.replaceable, f.marker))
                for name, data in f.files.items():
                    atomic_write_bytes(staged_dirs[-1].path / name, data)
            written = [s.commit() for s in staged_files]
            for d, f in zip(staged_dirs, self._folders, strict=True):
                d.commit()
                written += [f.path / name for name in f.files]
            return written
        finally:
            for s in staged_files:
                s.discard()
            for d in staged_dirs:
                d.discard()
