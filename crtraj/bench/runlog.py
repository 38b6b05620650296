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
from crtraj.core.fileio import read_text

# Most rows and bytes read back (a full table is 100 scenarios x 4 counts x 7 planners = 2800 rows, ~1 MB).
MAX_ROWS = 200_000
MAX_BYTES = 256 * 1024 * 1024


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


class RunLog:
    """Appends records to a CSV file, one flushed line each (the header first when the file is new)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
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
    if kind is bool or kind == "bool":
        if text not in ("True", "False"):
            raise InputError(f"{where}: expected True or False, got {text!r:.40}")
        return text == "True"
    if kind is int or kind == "int":
        try:
            return int(text)
        except ValueError:
            raise InputError(f"{where}: expected an integer, got {text!r:.40}") from None
    if kind is float or kind == "float":
        try:
            return float(text) if text else float("nan")
        except ValueError:
            raise InputError(f"{where}: expected a number, got {text!r:.40}") from None
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
