"""A contact sheet: every pattern of a set side by side, in pattern grid order."""
from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
from capture_sim.atomic import atomic_path
from capture_sim.errors import InputError
from patterns.io import validate_patterns

_CAPTION = (
    "Display set values P in [0, 1] before the display gamma, in pattern grid order: row 0 at the top, "
    "column 0 at the left (on the preset rigs, column c grows with camera x; exported frames may mirror "
    "columns: see columns_mirrored in the manifest)."
)
_MIRRORED_CAPTION = (
    "Display set values P in [0, 1] before the display gamma, as the exported frames show them on the display "
    "(seen from the object): row 0 at the top, pattern column 0 at the right (columns_mirrored in the manifest)."
)


MAX_PANELS = 48
"""Patterns drawn on one sheet: beyond a few dozen panels the sheet is unreadable, and each costs
about a quarter of a second (1000 patterns took over ten minutes)."""


def contact_sheet_figure(patterns, title: str, labels: list[str] | None = None, columns: int = 4, max_panels: int = MAX_PANELS,
                         mirrored: bool = False):
    """A figure with one panel per pattern (the first ``max_panels`` of larger sets, said in the title).

    Args:
        patterns: (M, R, C, 3) display set values in [0, 1].
        title: figure title (e.g. family, M and rig).
        labels: optional M panel titles; default "pattern m".
        columns: panels per row of the sheet.
        max_panels: most patterns drawn.
        mirrored: draw the patterns as frames that mirror columns show them (column 0 at the
            right, the axis still numbering pattern columns), as an export does on such a rig.

    Returns:
        A matplotlib ``Figure`` (object API, no pyplot state).
    """
    from matplotlib.figure import Figure  # imported here: matplotlib costs a second at start-up

    values = validate_patterns(patterns)
    count, rows, cols, _ = values.shape
    labels = labels or [f"pattern {m}" for m in range(count)]
    if len(labels) != count:
        raise InputError(f"contact sheet: {len(labels)} labels for {count} patterns")
    if count > max_panels:
        title = f"{title}; the first {max_panels} of {count} shown"
        values, labels, count = values[:max_panels], labels[:max_panels], max_panels
    columns = max(1, min(columns, count))
    sheet_rows = math.ceil(count / columns)
    panel_width = 3.2
    panel_height = panel_width * rows / cols + 0.9
    width = max(panel_width * columns, 6.4)  # room for the title and caption of a one-pattern sheet
    caption = textwrap.fill(_MIRRORED_CAPTION if mirrored else _CAPTION, width=int(width * 14))
    fig = Figure(figsize=(width, panel_height * sheet_rows + 1.0 + 0.15 * caption.count("\n")), layout="constrained")
    axes = np.atleast_1d(fig.subplots(sheet_rows, columns, squeeze=False)).ravel()
    for m, ax in enumerate(axes):
        if m >= count:
            ax.set_axis_off()
            continue
        # A reversed x extent draws column 0 at the right, with the ticks still naming pattern columns.
        left, right = (cols - 0.5, -0.5) if mirrored else (-0.5, cols - 0.5)
        ax.imshow(values[m], interpolation="nearest", vmin=0.0, vmax=1.0, extent=(left, right, rows - 0.5, -0.5))
        ax.set_title(f"{labels[m]}  (mean {values[m].mean():.2f})", fontsize=9)
        ax.set_xlabel("column c (superpixel)", fontsize=8)
        ax.set_ylabel("row r (superpixel)", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(textwrap.fill(title, width=int(width * 9)))
    fig.supxlabel(caption, fontsize=8)  # laid out below the panels, unlike free figure text
    return fig


def save_contact_sheet(path: str | Path, patterns, title: str, labels: list[str] | None = None, dpi: int = 100, mirrored: bool = False) -> None:
    """Write the contact sheet of ``patterns`` (M, R, C, 3) as a PNG file, atomically (``mirrored``:
    see ``contact_sheet_figure``)."""
    fig = contact_sheet_figure(patterns, title, labels, mirrored=mirrored)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi)

