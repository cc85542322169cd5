"""Small plotting helpers shared by the commands: display tone mapping and image grids.

Figures use matplotlib's object API on the Agg backend and are saved atomically.
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

from capture_sim.atomic import atomic_path  # noqa: E402


def for_display(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] images (..., 3) to display values with a 1/2.2 gamma, clipped to [0, 1]."""
    return np.clip(np.nan_to_num(linear), 0.0, 1.0) ** (1 / 2.2)


def normal_to_rgb(normal: np.ndarray) -> np.ndarray:
    """Unit normals (..., 3) in the camera frame to RGB ((x, -y, -z) + 1) / 2: red right, green up, blue towards the camera."""
    colour = np.stack([normal[..., 0], -normal[..., 1], -normal[..., 2]], axis=-1)
    return np.clip(0.5 * (colour + 1.0), 0.0, 1.0)


def normal_panel(normal: np.ndarray, mask: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """RGB image (H, W, 3) of unit normals (H, W, 3), camera frame, for figures: ``normal_to_rgb``
    inside ``mask`` (H, W) bool, white outside it, and black where ``valid`` (H, W) bool is False
    inside it (a flagged pixel's placeholder normal would otherwise look like an estimate)."""
    image = np.where(mask[..., None], normal_to_rgb(normal), 1.0)
    if valid is not None:
        image[mask & ~valid] = 0.0
    return image


def save_figure(fig, path) -> None:
    """Save a figure as PNG atomically and release it."""
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)


ERROR_MAP_MAX_DEG = 45.0
"""Normal error maps saturate here (degrees), in every command's figures, so that they compare."""

FLAGGED_COLOUR = (0.35, 0.75, 0.95)
"""Solid light blue over flagged pixels of value maps (no colour of magma or viridis)."""


def image_grid(images: list[np.ndarray], titles: list[str], suptitle: str, caption: str, columns: int = 4, cmap=None, colorbar_label=None,
               limits: list | None = None, flagged: list | None = None):
    """A figure with one panel per image (H, W, 3) or (H, W), titled, with a caption line below.
    ``limits`` optionally gives each (H, W) image a fixed colour range (vmin, vmax) or None (its own);
    a colour bar shows an arrow where values lie beyond it. ``colorbar_label``: one label for a
    colour bar beside every panel, or a list with a label (or None: no bar) per panel. ``flagged``:
    optionally per panel an (H, W) bool mask (or None) painted ``FLAGGED_COLOUR`` over the image."""
    count = len(images)
    columns = max(1, min(columns, count))
    rows = int(np.ceil(count / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 2.9 * rows + 0.6), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    labels = colorbar_label if isinstance(colorbar_label, list) else [colorbar_label] * count
    for ax, image, title, limit, label, marked in zip(axes.ravel(), images, titles, limits or [None] * count, labels, flagged or [None] * count):
        vmin, vmax = limit if limit is not None else (None, None)
        shown = ax.imshow(image, cmap=cmap, interpolation="nearest", vmin=vmin, vmax=vmax)
        if marked is not None and marked.any():
            overlay = np.zeros((*marked.shape, 4))
            overlay[marked] = (*FLAGGED_COLOUR, 1.0)
            ax.imshow(overlay, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        if label is not None:
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.04, label=label, extend=_beyond(image, vmin, vmax))
    fig.suptitle(suptitle)
    fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=8, wrap=True)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig


def _beyond(image: np.ndarray, vmin, vmax) -> str:
    """Colour-bar ``extend``: which ends of a fixed range the image's values pass."""
    if image.ndim != 2 or not np.isfinite(image).any():
        return "neither"
    low = vmin is not None and float(np.nanmin(image)) < vmin
    high = vmax is not None and float(np.nanmax(image)) > vmax
    return "both" if low and high else "min" if low else "max" if high else "neither"
