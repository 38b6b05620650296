"""Motion-capture marker files and their join with a stream log, by timestamp.

A marker file holds one row per marker and capture frame: timestamp (s), marker name, x, y, z (mm, in the
capture system's frame). Two formats:

- CSV with a header row naming the columns ``timestamp`` (or ``t``, ``time``), ``marker`` (or ``name``),
  ``x``, ``y``, ``z``; ``#`` lines are comments;
- JSON lines, one object per row: ``{"t": 1.25, "marker": "tip", "x": .., "y": .., "z": ..}`` (or
  ``"position": [x, y, z]``).

Rows with the same timestamp form one capture frame. The stream log is the JSON-lines record of
`crtraj.hardware.stream.Streamer` (``crtraj stream --log``, ``crtraj replan --stream``): its ``rx``
lines carry the device's measured actuator values, its ``tx`` lines the values sent, both with ``wall``
(s since the stream started). `join` puts the marker times on the log's clock (log time = marker time -
time_offset), interpolates the actuator values linearly at each capture frame and refuses files whose
times do not overlap. Every line of both files is treated as hostile: one-line `InputError` naming the
file, line and field.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_STAMP, read_number
from crtraj.core.fileio import read_text
from crtraj.model.calibration import MAX_SAMPLES, MarkerSite

MAX_FILE_BYTES = 512 * 1024 * 1024
MAX_ROWS = 4_000_000
# Largest gap (s) between two log samples a capture frame may fall in: beyond it the device's position
# between them is unknown (telemetry lost), and the frame is dropped.
MAX_GAP = 0.25


@dataclass(frozen=True)
class MarkerFrames:
    """Capture frames: times (F,) s and positions (F, M, 3) mm of the sites' markers (NaN: not seen)."""

    t: np.ndarray
    positions: np.ndarray


def _float(v: Any, where: str) -> float:
    # the one bounded number reader: huge integers, 1e300, NaN, inf and non-ASCII digits are refused
    return read_number(v, where, limit=MAX_STAMP)


def _rows_csv(text: str, path: Path) -> list[tuple[int, Any, Any, Any]]:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    reader = csv.reader(io.StringIO("\n".join(lines)))
    try:
        header = [h.strip().lower() for h in next(reader)]
    except StopIteration:
        raise InputError(f"{path}: empty marker file") from None

    def col(*names: str) -> int:
        for n in names:
            if n in header:
                return header.index(n)
        raise InputError(f"{path}: header: no column {names[0]!r} (columns: {', '.join(header)})")

    it, im, ix, iy, iz = col("timestamp", "t", "time"), col("marker", "name"), col("x"), col("y"), col("z")
    rows = []
    for ln, r in enumerate(reader, start=2):
        if len(r) != len(header):
            raise InputError(f"{path} row {ln}: {len(r)} columns, the header has {len(header)}")
        rows.append((ln, r[it], r[im].strip(), (r[ix], r[iy], r[iz])))
        if len(rows) > MAX_ROWS:
            raise InputError(f"{path}: more than {MAX_ROWS} rows")
    return rows


def _json_objects(text: str, path: Path, hint: str, expected: str) -> Iterator[tuple[int, dict[str, Any]]]:
    """(line number, object) of each non-empty line of a JSON-lines file; `InputError` naming the line
    when one is not JSON (hint: what the file should be) or not an object (expected: which)."""
    for ln, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            d = json.loads(line)
        except (ValueError, RecursionError):
            raise InputError(f"{path} line {ln}: not valid JSON{hint}") from None
        if not isinstance(d, dict):
            raise InputError(f"{path} line {ln}: expected {expected}")
        yield ln, d


def _rows_jsonl(text: str, path: Path) -> list[tuple[int, Any, Any, Any]]:
    rows = []
    for ln, d in _json_objects(text, path, "", "an object {t, marker, x, y, z}"):
        t = d.get("t", d.get("timestamp", d.get("time")))
        name = d.get("marker", d.get("name"))
        xyz = d.get("position", (d.get("x"), d.get("y"), d.get("z")))
        if not isinstance(xyz, (list, tuple)) or len(xyz) != 3:
            raise InputError(f"{path} line {ln}: position: expected [x, y, z]")
        rows.append((ln, t, name, tuple(xyz)))
        if len(rows) > MAX_ROWS:
            raise InputError(f"{path}: more than {MAX_ROWS} rows")
    return rows


def read_markers(path: str | Path, sites: Sequence[MarkerSite]) -> MarkerFrames:
    """Read a marker file (CSV or JSON lines, by content) into capture frames of the given sites."""
    p = Path(path)
    text = read_text(p, max_bytes=MAX_FILE_BYTES, kind="marker (CSV or JSON lines)")
    rows = _rows_jsonl(text, p) if text.lstrip().startswith("{") else _rows_csv(text, p)
    if not rows:
        raise InputError(f"{p}: no marker rows")
    index = {s.name: j for j, s in enumerate(sites)}
    frames: dict[float, np.ndarray] = {}
    for ln, t_raw, name, xyz in rows:
        where = f"{p} line {ln}"
        if not isinstance(name, str) or name not in index:
            raise InputError(
                f"{where}: marker {name!r} unknown (configured: {', '.join(index)}; add --marker NAME=SEGMENT:ARC)"
            )
        t = _float(t_raw, f"{where}: timestamp")
        pos = [_float(v, f"{where}: {ax}") for v, ax in zip(xyz, "xyz", strict=True)]
        f = frames.get(t)
        if f is None:
            if len(frames) >= MAX_SAMPLES:
                raise InputError(f"{p}: more than {MAX_SAMPLES} capture frames")
            f = frames[t] = np.full((len(sites), 3), np.nan)
        f[index[name]] = pos
    times = np.array(sorted(frames))
    return MarkerFrames(times, np.stack([frames[t] for t in times]))


@dataclass(frozen=True)
class LogSeries:
    """Actuator values from a stream log: times (K,) s on the log's clock, values (K, n), and which kind
    ('measured': the device's telemetry, 'commanded': the set-points sent)."""

    names: tuple[str, ...]
    t: np.ndarray
    values: np.ndarray
    kind: str


def read_stream_log(path: str | Path, prefer: str = "measured") -> LogSeries:
    """The actuator values of a stream log: its telemetry (``rx`` positions) when it has any and
    prefer is "measured", else the set-points sent (``tx`` values)."""
    p = Path(path)
    text = read_text(p, max_bytes=MAX_FILE_BYTES, kind="stream log (JSON lines)")
    names: tuple[str, ...] | None = None
    rx: list[tuple[float, list[float]]] = []
    tx: list[tuple[float, list[float]]] = []
    for ln, d in _json_objects(text, p, " (is it a crtraj stream log?)", "a JSON object"):
        kind = d.get("type")
        if kind == "header":
            nm = d.get("names")
            if not isinstance(nm, list) or not all(isinstance(x, str) for x in nm) or not nm:
                raise InputError(f"{p} line {ln}: names: expected the actuator names")
            names = tuple(nm)
        elif kind in ("rx", "tx"):
            key = "positions" if kind == "rx" else "values"
            if key not in d:  # a PING carries no values
                continue
            wall = _float(d.get("wall"), f"{p} line {ln}: wall")
            vals = d[key]
            if not isinstance(vals, list) or names is None or len(vals) != len(names):
                raise InputError(f"{p} line {ln}: {key}: expected {len(names or ())} actuator values")
            row = [_float(v, f"{p} line {ln}: {key}") for v in vals]
            (rx if kind == "rx" else tx).append((wall, row))
        if len(rx) + len(tx) > MAX_ROWS:
            raise InputError(f"{p}: more than {MAX_ROWS} frames")
    if names is None:
        raise InputError(f"{p}: no header line (is it a crtraj stream log?)")
    use, kind = (rx, "measured") if rx and prefer == "measured" else (tx, "commanded")
    if len(use) < 2:
        raise InputError(f"{p}: fewer than two {kind} actuator frames; nothing to interpolate")
    use.sort(key=lambda r: r[0])
    return LogSeries(names, np.array([r[0] for r in use]), np.array([r[1] for r in use]), kind)


def join(
    log: LogSeries, frames: MarkerFrames, time_offset: float = 0.0, max_gap: float = MAX_GAP
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(times (F',) s on the log clock, values (F', n) interpolated, positions (F', M, 3), frames dropped).

    A capture frame at marker time tau is at log time tau - time_offset; frames outside the log's span or
    in a gap longer than max_gap are dropped; none left: `InputError` (the times do not overlap).
    """
    tl = frames.t - time_offset
    inside = (tl >= log.t[0]) & (tl <= log.t[-1])
    j = np.clip(np.searchsorted(log.t, tl), 1, log.t.size - 1)
    gap = log.t[j] - log.t[j - 1]
    keep = inside & (gap <= max_gap)
    if not keep.any():
        raise InputError(
            f"timestamps: the markers cover {tl[0]:.3f}..{tl[-1]:.3f} s and the log {log.t[0]:.3f}..{log.t[-1]:.3f} s "
            f"(log clock, time offset {time_offset:g} s): they do not overlap; set --time-offset"
        )
    tl, j = tl[keep], j[keep]
    t0, t1 = log.t[j - 1], log.t[j]
    w = np.where(t1 > t0, (tl - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)[:, None]
    values = (1 - w) * log.values[j - 1] + w * log.values[j]
    return tl, values, frames.positions[keep], int((~keep).sum())
