"""The calibration dataset: actuator values and motion-capture marker positions, one JSON document.

``crtraj record`` writes it, ``crtraj calibrate`` reads it. Schema (version 1)::

    {"kind": "calibration-dataset", "schema": 1, "created": ISO time, "crtraj_version": ...,
     "source": {...how it was made...},
     "actuators": ["s1c1", ..., "z"],                 actuator names, in the robot's order
     "markers": {"base": {"segment": 1, "arc": 0.0},   where each marker sits: segment (1-based),
                 "tip1": {"segment": 1, "arc": "tip"},  arc length from the segment's start (mm) or "tip"
                 "tip": {"segment": 2, "arc": "tip"}},
     "t": [s, ...],                                     sample times (s)
     "values": [[...], ...],                            actuator values per sample (rad; the stage in mm)
     "positions": {"base": [[x, y, z] or null, ...]}}   capture-frame positions (mm); null: not seen

Every number must be finite and within its physical range (`crtraj.io.calibration_numbers`: times within
1e10 s, actuator values within 1e5, positions within 1 km; a NaN, 1e300 or a 400-digit integer is refused,
naming its place; a marker that was not seen is null).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from crtraj import __version__
from crtraj.core.errors import InputError
from crtraj.core.fields import MAX_LENGTH, Table
from crtraj.core.fileio import atomic_write_json, read_json, read_toml
from crtraj.io.calibration_numbers import POSITION_LIMIT, TIME_LIMIT, VALUE_LIMIT, display_path, number_array
from crtraj.model.calibration import MAX_MARKERS, MAX_SAMPLES, MIN_SAMPLES, MarkerSite

KIND = "calibration-dataset"
SCHEMA = 1
MAX_DATASET_BYTES = 512 * 1024 * 1024


@dataclass(frozen=True)
class Dataset:
    """A calibration dataset in memory. t (N,) s; values (N, nq); positions (N, M, 3) mm (NaN: not seen)."""

    actuators: tuple[str, ...]
    sites: tuple[MarkerSite, ...]
    t: np.ndarray
    values: np.ndarray
    positions: np.ndarray
    source: dict[str, Any] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.t.size)

    def to_dict(self) -> dict[str, Any]:
        pos = {
            s.name: [None if np.isnan(p).any() else [float(x) for x in p] for p in self.positions[:, j]]
            for j, s in enumerate(self.sites)
        }
        return {
            "kind": KIND,
            "schema": SCHEMA,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "crtraj_version": __version__,
            "source": self.source,
            "actuators": list(self.actuators),
            "markers": {s.name: s.to_dict() for s in self.sites},
            "t": [float(x) for x in self.t],
            "values": self.values.tolist(),
            "positions": pos,
        }

    def write(self, path: str | Path) -> Path:
        """Write the dataset atomically (JSON)."""
        return atomic_write_json(path, self.to_dict())


def parse_site(name: str, spec: Any, n_segments: int, where: str) -> MarkerSite:
    """A marker site from ``{"segment": k (1-based), "arc": mm or "tip"}``."""
    if not isinstance(spec, dict):
        raise InputError(f"{where}: expected a table {{segment, arc}}, got {type(spec).__name__}")
    unknown = sorted(set(spec) - {"segment", "arc"})
    if unknown:
        raise InputError(f"{where}.{unknown[0]}: unknown key (known: segment, arc)")
    seg = spec.get("segment")
    if isinstance(seg, bool) or not isinstance(seg, int) or not 1 <= seg <= n_segments:
        raise InputError(f"{where}.segment: must be an integer in [1, {n_segments}], got {seg!r}")
    arc = spec.get("arc", "tip")
    if arc != "tip" and (isinstance(arc, bool) or not isinstance(arc, (int, float)) or not 0 <= arc <= MAX_LENGTH):
        raise InputError(f'{where}.arc: must be "tip" or an arc length >= 0 mm, got {arc!r}')
    return MarkerSite(name, seg - 1, None if arc == "tip" else float(arc))


def parse_marker_option(text: str, n_segments: int) -> MarkerSite:
    """A ``--marker NAME=SEGMENT:ARC`` option (ARC in mm from the segment's start, or "tip")."""
    name, eq, rest = text.partition("=")
    seg, colon, arc = rest.partition(":")
    if not eq or not colon or not name.strip():
        raise InputError(f"--marker: expected NAME=SEGMENT:ARC (e.g. tip1=1:tip, mid=2:100), got {text!r}")
    try:
        seg_i = int(seg)
        arc_v: Any = "tip" if arc.strip() == "tip" else float(arc)
    except ValueError:
        raise InputError(f"--marker {text}: SEGMENT must be an integer and ARC a number (mm) or tip") from None
    return parse_site(name.strip(), {"segment": seg_i, "arc": arc_v}, n_segments, f"--marker {name.strip()}")


def dataset_from_dict(doc: Any, actuator_names: tuple[str, ...], n_segments: int, where: str = "") -> Dataset:
    """Validate a dataset document against the robot (its actuator names and segments)."""
    p = f"{where}: " if where else ""
    if not isinstance(doc, dict):
        raise InputError(f"{p}expected a JSON object (a calibration dataset)")
    if doc.get("kind") != KIND:
        raise InputError(f"{p}kind: expected {KIND!r}, got {doc.get('kind')!r} (write one with crtraj record)")
    if doc.get("schema") != SCHEMA:
        raise InputError(f"{p}schema: unsupported version {doc.get('schema')!r} (this crtraj reads {SCHEMA})")
    names = doc.get("actuators")
    if names != list(actuator_names):
        raise InputError(f"{p}actuators: {names!r} are not the robot's actuators {list(actuator_names)}")
    marks = doc.get("markers")
    if not isinstance(marks, dict) or not marks:
        raise InputError(f"{p}markers: expected a table of marker sites")
    if len(marks) > MAX_MARKERS:
        raise InputError(f"{p}markers: at most {MAX_MARKERS}, got {len(marks)}")
    sites = tuple(parse_site(str(k), v, n_segments, f"{p}markers.{k}") for k, v in marks.items())
    t_raw = doc.get("t")
    if not isinstance(t_raw, list):
        raise InputError(f"{p}t: expected a list of sample times (s)")
    n = len(t_raw)
    if n > MAX_SAMPLES:
        raise InputError(f"{p}t: at most {MAX_SAMPLES} samples, got {n}")
    if n < MIN_SAMPLES:
        raise InputError(f"{p}t: {n} samples, need at least {MIN_SAMPLES} (record more motion)")
    t = number_array(t_raw, f"{p}t", (n,), TIME_LIMIT)
    values = number_array(doc.get("values"), f"{p}values", (n, len(actuator_names)), VALUE_LIMIT)
    pos_doc = doc.get("positions")
    if not isinstance(pos_doc, dict):
        raise InputError(f"{p}positions: expected a table marker -> list of [x, y, z] or null")
    known = [s.name for s in sites]
    for k in pos_doc:
        if k not in known:
            raise InputError(f"{p}positions.{k}: unknown marker (known: {', '.join(known)})")
    positions = np.full((n, len(sites), 3), np.nan)
    for j, s in enumerate(sites):
        col = pos_doc.get(s.name)
        if not isinstance(col, list) or len(col) != n:
            raise InputError(f"{p}positions.{s.name}: expected {n} entries ([x, y, z] mm or null)")
        for i, row in enumerate(col):
            if row is not None:
                positions[i, j] = number_array(row, f"{p}positions.{s.name}[{i}]", (3,), POSITION_LIMIT)
    if not np.isfinite(positions).all(axis=2).any():
        raise InputError(f"{p}positions: no marker was seen in any sample")
    src = doc.get("source", {})
    return Dataset(tuple(actuator_names), sites, t, values, positions, src if isinstance(src, dict) else {})


def read_dataset(path: str | Path, actuator_names: tuple[str, ...], n_segments: int) -> Dataset:
    """Read and validate a dataset file (one-line `InputError` naming the file and field)."""
    doc = read_json(path, max_bytes=MAX_DATASET_BYTES)
    return dataset_from_dict(doc, actuator_names, n_segments, display_path(path))


@dataclass(frozen=True)
class CalibrationRecord:
    """The ``[calibration]`` table `crtraj calibrate` adds to a robot file: the dataset and date it was
    fitted from and when, the parameters fitted and held, those confounded at the fit (their values depend on
    the held ones' priors; no standard error), the capture frame (rotation vector, rad, and
    translation, mm: capture -> robot, p_robot = R p_capture + t), the held-out residual RMS with and without
    the outliers (mm) and their count, and the marker noise per axis (mm) the fit was judged against."""

    dataset: str = ""
    date: str = ""
    fitted: tuple[str, ...] = ()
    held: tuple[str, ...] = ()
    capture_rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    capture_translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    confounded: tuple[str, ...] = ()
    heldout_rms_mm: float | None = None
    heldout_rms_inliers_mm: float | None = None
    heldout_outliers: int | None = None
    noise_mm: float | None = None

    @property
    def capture(self) -> np.ndarray:
        """(6,) rotation vector (rad) and translation (mm)."""
        return np.array([*self.capture_rotation, *self.capture_translation])

    @classmethod
    def from_table(cls, t: Table) -> CalibrationRecord:
        def names(key: str) -> tuple[str, ...]:
            v = t.raw(key, [])
            if not isinstance(v, list) or len(v) > 1000 or not all(isinstance(x, str) and len(x) < 100 for x in v):
                raise t.error(key, "expected a list of parameter names")
            return tuple(v)

        rec = cls(
            dataset=t.str("dataset", "", max_len=4096),
            date=t.str("date", "", max_len=100),
            fitted=names("fitted"),
            held=names("held"),
            confounded=names("confounded"),
            capture_rotation=t.vec("capture_rotation", 3, (0.0, 0.0, 0.0), limit=4 * math.pi),  # type: ignore[arg-type]
            capture_translation=t.vec("capture_translation", 3, (0.0, 0.0, 0.0), limit=MAX_LENGTH),  # type: ignore[arg-type]
            heldout_rms_mm=t.float("heldout_rms_mm", None, ge=0.0, limit=MAX_LENGTH),
            heldout_rms_inliers_mm=t.float("heldout_rms_inliers_mm", None, ge=0.0, limit=MAX_LENGTH),
            heldout_outliers=t.int("heldout_outliers", None, ge=0, le=MAX_SAMPLES * MAX_MARKERS),
            noise_mm=t.float("noise_mm", None, ge=0.0, limit=MAX_LENGTH),
        )
        t.finish()
        return rec


def read_calibration(path: str | Path) -> CalibrationRecord | None:
    """The ``[calibration]`` table of a robot file, or None when it has none."""
    top = Table(read_toml(path), "")
    return CalibrationRecord.from_table(top.table("calibration")) if top.has("calibration") else None
