"""Marker sites and the parameter groups of a calibration (units: mm)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from crtraj.core.errors import InputError
from crtraj.model.robot import Robot

# The parameter groups a user may fit (`--fit`), in file order.
GROUPS = ("lengths", "coupling", "cable_radius", "zero_offsets", "base_z", "capture_frame")
# Identifiability priority: earlier groups keep a shared direction, later ones are held at their prior.
PRIORITY = ("capture_frame", "lengths", "cable_radius", "coupling", "zero_offsets", "base_z")
# Most samples and markers of one dataset (the NLP grows linearly with them).
MAX_SAMPLES = 200_000
MAX_MARKERS = 16
# Fewest usable fit samples, whatever is fitted.
MIN_SAMPLES = 20
# Spread of the markers relative to the model's (capture vs robot): outside this the file is in
# another unit (metres give 0.001, centimetres 0.1, inches 0.04).
PLAUSIBLE_SCALE = (0.8, 1.25)


@dataclass(frozen=True)
class MarkerSite:
    """Where a marker sits: segment (0-based), arc length from the segment's start (mm; None = its tip)."""

    name: str
    segment: int
    arc: float | None = None

    def to_dict(self) -> dict[str, object]:
        return {"segment": self.segment + 1, "arc": "tip" if self.arc is None else self.arc}


def check_sites(sites: Sequence[MarkerSite], robot: Robot) -> None:
    """Refuse a marker on a segment the robot lacks or beyond its segment's length (one line)."""
    if not 1 <= len(sites) <= MAX_MARKERS:
        raise InputError(f"markers: 1 to {MAX_MARKERS} markers, got {len(sites)}")
    for s in sites:
        if not 0 <= s.segment < robot.n_segments:
            raise InputError(f"marker {s.name}: segment {s.segment + 1}, the robot has {robot.n_segments}")
        L = robot.segments[s.segment].length
        if s.arc is not None and not 0 <= s.arc <= L:
            raise InputError(f"marker {s.name}: arc {s.arc:g} mm is beyond segment {s.segment + 1} ({L:g} mm long)")


def paper_markers(n_segments: int) -> tuple[MarkerSite, ...]:
    """The paper's markers: the base, the tip of the proximal segment, the distal tip."""
    sites = [MarkerSite("base", 0, 0.0)]
    sites += [MarkerSite(f"tip{k + 1}" if k < n_segments - 1 else "tip", k) for k in range(n_segments)]
    return tuple(sites)


def parse_groups(text: str) -> tuple[str, ...]:
    """The groups of a ``--fit`` list (comma separated; "all" for every group)."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise InputError("--fit: empty; name one or more of " + ", ".join(GROUPS))
    if items == ["all"]:
        return GROUPS
    for s in items:
        if s not in GROUPS:
            raise InputError(f"--fit: unknown parameter group {s!r} (known: {', '.join(GROUPS)}, all)")
    return tuple(g for g in GROUPS if g in items)
