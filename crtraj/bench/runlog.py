"""runs.csv as a log: one row per finished run, appended as it finishes, read back into `RunRecord`s.

A long benchmark appends each record the moment it arrives (`RunLog.append`),
so a run cut short keeps every finished row and can be resumed
(`Table1Bench.run(done=...)`) or reported (`read_runs`). The columns are
`RunRecord.fields()`; floats are written with 6 significant digits, NaN as
an empty cell. Units s, mm.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

from crtraj.bench.records import RunRecord
from crtraj.core.errors import InputError
from crtraj.core.fields import read_int, read_number
from crtraj.core.fileio import read_text

# Most rows and bytes read back (a full table is 100 scenarios x 4 counts x 7 planners = 2800 rows, ~1 MB).
MAX_ROWS = 200_000
MAX_BYTES = 256 * 1024 * 1024
# Largest integer cell (counts, indices, seeds, graph sizes): every value an exact float holds.
MAX_INT = 2**53


def record_row(r: RunRecord) -> dict[str, Any]:
    """One record as CSV cells."""
    row = asdict(r)
    for k, v in row.items():
        if isinstance(v, float):
            row[k] = "" if not math.isfinite(v) else f"{v:.6g}"
    return row


def csv_text(records: list[RunRecord]) -> str:
    """The records as runs.csv text, sorted by (obstacle count, index, planner)."""
    buf = io.StringIO()
    wr = csv.DictWriter(buf, fieldnames=RunRecord.fields(), lineterminator="\n")
    wr.writeheader()
    for r in sorted(records, key=lambda r: (r.n_obstacles, r.index, r.planner)):
        wr.writerow(record_row(r))
    return buf.getvalue()


def _check_ours(path: Path) -> None:
    """An existing log is appended to only when it is one crtraj wrote: a regular file that is empty or
    starts with this version's runs.csv header; anything else is one `InputError` line, left untouched."""
    if not os.path.lexists(path):
        return
    if path.is_symlink() or not path.is_file():
        raise InputError(f"{path}: not a regular file; give a runs log crtraj wrote, or a new name")
    with open(path, "rb") as fh:
        first = fh.readline(64 * 1024)
    if first and first.rstrip(b"\r\n") != ",".join(RunRecord.fields()).encode("ascii"):
        raise InputError(f"{path}: its first line is not the runs.csv header of this crtraj; not appended to")


def _drop_torn_row(path: Path) -> None:
    """Cut a log that does not end in a newline back to its last complete line: the process writing it was
    killed in the middle of a row, and a resumed log must read back (`read_runs`)."""
    if not path.is_file() or path.stat().st_size == 0:
        return
    with open(path, "rb+") as fh:
        fh.seek(-1, os.SEEK_END)
        if fh.read(1) == b"\n":
            return
        fh.seek(0)
        data = fh.read()
        fh.truncate(data.rfind(b"\n") + 1)


class RunLog:
    """Appends records to a CSV file, one flushed line each (the header first when the file is new).

    An existing file must be a runs log crtraj wrote (`InputError` otherwise, the file untouched); one left
    with a torn last row by a killed run is first cut back to its last complete row.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        _check_ours(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        _drop_torn_row(self.path)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._f = open(self.path, "a", newline="", encoding="utf-8")  # noqa: SIM115 (held open for the run)
        self._w = csv.DictWriter(self._f, fieldnames=RunRecord.fields(), lineterminator="\n")
        if new:
            self._w.writeheader()
            self._f.flush()

    def append(self, r: RunRecord) -> None:
        self._w.writerow(record_row(r))
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def _cell(kind: Any, text: str, where: str) -> Any:
    """One cell as its field's type, through the bounded readers (`read_int`, `read_number`): a 400-digit
    integer, 1e300, NaN or other scripts' digits are one `InputError` line naming `where` (row and column).
    An empty float cell is NaN: the writer's spelling of a value that was not measured (`record_row`)."""
    if kind is bool or kind == "bool":
        if text not in ("True", "False"):
            raise InputError(f"{where}: expected True or False, got {text!r:.40}")
        return text == "True"
    if kind is int or kind == "int":
        return read_int(text, where, ge=0, le=MAX_INT)
    if kind is float or kind == "float":
        return read_number(text, where) if text else float("nan")
    return text


def read_runs(path: str | os.PathLike[str]) -> list[RunRecord]:
    """The records of a runs.csv (a later row for the same planner, count and index replaces an earlier one)."""
    text = read_text(path, max_bytes=MAX_BYTES, kind="runs CSV")
    reader = csv.DictReader(io.StringIO(text))
    kinds = {f.name: f.type for f in fields(RunRecord)}
    missing = [k for k in kinds if k not in (reader.fieldnames or [])]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}")
    out: dict[tuple[str, int, int], RunRecord] = {}
    for i, row in enumerate(reader, start=2):
        if i > MAX_ROWS + 1:
            raise InputError(f"{path}: more than {MAX_ROWS} rows")
        vals = {k: _cell(kinds[k], row[k] or "", f"{path}:{i}: {k}") for k in kinds}
        r = RunRecord(**vals)
        out[(r.planner, r.n_obstacles, r.index)] = r
    return list(out.values())
