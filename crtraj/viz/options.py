"""The view's options (the problem file's ``[view]`` section) and its colour strings.

Colours are "#rrggbb" strings in the file and in `ViewOptions`; `color_value` turns one into the integer meshcat
takes, with a one-line error naming the field. Lengths in mm.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from typing import Any, ClassVar

from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.core.options import Options, option

_COLOR_RE = re.compile(r"^#[0-9a-fA-F]{6}$")
# Most colours in view.segment_colors (cycled over the segments; a robot has a few).
MAX_SEGMENT_COLORS = 100


@dataclasses.dataclass(frozen=True)
class ViewOptions(Options):
    """How a scene is drawn; the problem file's ``[view]`` section.

    backbone_radius: drawn radius of the backbone tube (mm); None means the
    robot's body_radius, the radius its clearance is measured with.
    disc_spacing: largest arc length between two discs (mm). disc_thickness
    (mm). disc_radius: None means 1.5 times the tube's radius (mm).
    segment_colors: "#rrggbb" per segment, cycled. obstacle_color and
    obstacle_opacity (0..1); shell_opacity: the faint D_sf shell around each
    obstacle. closest_color: the closest-approach line. marker_radius:
    start/goal spheres (mm). ghost_opacity: the second robot of a comparison.
    show_tree: None shows planner trees of plans and hides those of runs
    (a layer the page's legend turns on). play: start the animation when the
    page opens.
    """

    SECTION: ClassVar[str] = "view"

    backbone_radius: float | None = option(None, gt=0.0)
    disc_spacing: float = option(20.0, gt=0.0)
    disc_thickness: float = option(2.0, gt=0.0)
    disc_radius: float | None = option(None, gt=0.0)
    # a list in the file: read and checked by the hooks below (the base reads scalars only)
    segment_colors: tuple[str, ...] = option(("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#17becf"), read=False)
    obstacle_color: str = option("#d62728")
    obstacle_opacity: float = option(0.3, gt=0.0, le=1.0)
    shell_opacity: float = option(0.08, gt=0.0, le=1.0)
    closest_color: str = option("#000000")
    ghost_opacity: float = option(0.35, gt=0.0, le=1.0)
    start_color: str = option("#ffb000")
    goal_color: str = option("#e000e0")
    path_color: str = option("#8a8a8a")
    trail_color: str = option("#ff7f0e")
    tree_color: str = option("#8c8c8c")
    marker_radius: float = option(4.0, gt=0.0)
    show_tree: bool | None = option(None)
    play: bool = option(True)

    def _check(self) -> None:
        colors = self.segment_colors
        if isinstance(colors, (str, bytes)) or not isinstance(colors, Sequence):
            raise InputError(f'view.segment_colors: expected a list of "#rrggbb" strings, got {colors!r:.60}')
        if not colors:
            raise InputError("view.segment_colors: give at least one colour")
        if len(colors) > MAX_SEGMENT_COLORS:
            raise InputError(f"view.segment_colors: at most {MAX_SEGMENT_COLORS} colours, got {len(colors)}")
        for i, c in enumerate(colors):
            color_value(c, f"view.segment_colors[{i}]")
        object.__setattr__(self, "segment_colors", tuple(colors))  # a list from Python is stored as the file's
        for name in (
            "obstacle_color",
            "start_color",
            "goal_color",
            "path_color",
            "trail_color",
            "tree_color",
            "closest_color",
        ):
            color_value(getattr(self, name), f"view.{name}")

    @classmethod
    def _read_extra(cls, t: Table) -> dict[str, Any]:
        default = cls.__dataclass_fields__["segment_colors"].default
        colors = t.raw("segment_colors", list(default))
        if not isinstance(colors, list) or not all(isinstance(c, str) for c in colors):
            raise t.error("segment_colors", f'expected a list of "#rrggbb" strings, got {colors!r:.60}')
        return {"segment_colors": tuple(colors)}


def color_value(text: str, name: str) -> int:
    """'#rrggbb' -> 0xrrggbb (the integer colour meshcat takes); one-line error naming `name` otherwise."""
    if not isinstance(text, str) or not _COLOR_RE.match(text):
        raise InputError(f'{name}: expected a colour "#rrggbb", got {text!r}')
    return int(text[1:], 16)
