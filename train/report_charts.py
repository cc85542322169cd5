"""The comparison's charts (PNG): MAE against M, capture time, compute time and noise level, the
specular-free check, and the pattern sets, from the rows of ``train.report_rows``."""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import matplotlib.patches
import matplotlib.ticker
import matplotlib.transforms
import numpy as np

from patterns.families import FAMILIES
from train.figures import plt, save_figure
from train.report_rows import KIND_ORDER, NEARLY_ALL_INVALID, aggregate_rows, placeholder_error, test_scenes_text


CHARTS = {
    "mae_vs_M": "mae_vs_M.png",
    "mae_vs_capture_time": "mae_vs_capture_time.png",
    "mae_vs_compute_time": "mae_vs_compute_time.png",
    "mae_vs_noise": "mae_vs_noise.png",
    "patterns": "patterns.png",
    "specular_free": "mae_specular_free.png",
}
"""Chart name -> file name in the output folder."""
_KIND_STYLE = {
    "learned": dict(color="tab:red", marker="o", linewidth=2.5, zorder=4),  # above the heuristics' markers
    "rerender": dict(color="darkorange", marker="P", linewidth=2.0, linestyle="--", zorder=3),
    "search": dict(marker="D", linewidth=1.5),  # colours per series: _OTHER_COLOURS
    "external": dict(marker="s", linewidth=1.5),
    "heuristic": dict(linewidth=1.0, alpha=0.8, fillstyle="none"),  # markers per series: _HEURISTIC_MARKERS
    "reference": dict(color="black", marker="*", linewidth=1.0),
}




def _caption(fig, text: str) -> None:
    fig.text(0.5, -0.01, text, ha="center", va="top", fontsize=8, wrap=True)


_HEURISTIC_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:cyan", "tab:olive", "tab:pink", "tab:gray", "gold", "teal")
# Hollow, unlike the other kinds' filled markers: nine families at one M sit on top of each other in
# the cost charts, where colour alone did not tell them apart.
_HEURISTIC_MARKERS = ("v", "^", "<", ">", "p", "d", "h", "1", "2")
_OTHER_COLOURS = {"search": ("tab:purple", "darkviolet", "mediumorchid", "indigo"), "external": ("tab:brown", "peru", "saddlebrown", "rosybrown")}
# After every colour of its kind, a series takes the next marker (search: D first, external: s).
_OTHER_MARKERS = {"search": ("D", "d", "H", "8"), "external": ("s", "X", "h", "8")}


def _peers(rows: list[dict]) -> dict[str, list[str]]:
    """Per kind, its series in the chart's rows, sorted: their ranks pick distinct styles
    (``_style``), the same in every chart of one comparison, whose charts show the same methods."""
    peers: dict = defaultdict(set)
    for row in rows:
        peers[row["kind"]].add(row["series"])
    return {kind: sorted(names) for kind, names in peers.items()}


def _style(kind: str, series: str = "", peers: dict | None = None) -> dict:
    """Line style of a method: fixed per kind; colour and marker fixed per series. Heuristic
    families go by their place in ``FAMILIES``; searches and external sets take their kind's
    colours in the order of their names among ``peers`` (``_peers``), then further markers: two
    never look alike in one chart."""
    style = dict(_KIND_STYLE.get(kind, {}))
    if kind == "heuristic":
        order = list(FAMILIES)
        index = order.index(series) if series in order else sum(map(ord, series))
        style["color"] = _HEURISTIC_COLOURS[index % len(_HEURISTIC_COLOURS)]
        style["marker"] = _HEURISTIC_MARKERS[index % len(_HEURISTIC_MARKERS)]
    elif kind in _OTHER_COLOURS:
        colours, markers = _OTHER_COLOURS[kind], _OTHER_MARKERS[kind]
        names = (peers or {}).get(kind, [])
        rank = names.index(series) if series in names else sum(map(ord, series))
        style["color"] = colours[rank % len(colours)]
        style["marker"] = markers[(rank // len(colours)) % len(markers)]
    return style


def _marker_style(kind: str, series: str, peers: dict | None = None) -> dict:
    """``_style`` for a scatter of markers: its line settings dropped."""
    return {key: value for key, value in _style(kind, series, peers).items() if key not in ("linewidth", "linestyle")}


def _series(rows: list[dict]) -> dict:
    series: dict = defaultdict(list)
    for row in rows:
        series[(row["kind"], row["label"], row["series"])].append(row)  # every seed's label is "learned" (``aggregate_rows``)
    return {key: sorted(values, key=lambda r: r["M"]) for key, values in sorted(series.items(), key=lambda item: KIND_ORDER.get(item[0][0], 9))}


FAILED_LABEL = f"crossed out at the top: {NEARLY_ALL_INVALID:.0%} or more of the pixels invalid, no MAE to show"
FAILED_BAND = 0.955
"""Height (axes fraction) of the band at the top of a chart where failed methods are drawn."""
FAILED_ROOM = 0.15
"""Room made above the data for that band, as a fraction of the value axis' span."""
FAILED_SPACING = 8.5
"""Points between the markers of methods failing at one x."""


def _legend_entries(axes) -> dict:
    """Label -> handle of every labelled artist of ``axes``, the first of each label kept (panels
    of one figure draw the same methods), the failure band's explanation (``FAILED_LABEL``) last."""
    entries: dict = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    if FAILED_LABEL in entries:  # the long explanation last: in a middle column it widened the legend
        entries[FAILED_LABEL] = entries.pop(FAILED_LABEL)
    return entries


def _make_room_for_failed(ax) -> None:
    """Extend the value axis upwards by ``FAILED_ROOM`` so that the failure band covers no data
    (once per shared axis: the panels of one figure share their limits)."""
    low, high = ax.get_ylim()
    if ax.get_yscale() == "log":
        ax.set_ylim(low, high * (high / low) ** FAILED_ROOM)
    else:
        ax.set_ylim(low, high + FAILED_ROOM * (high - low))


def _mark_failed(ax, failed: list[tuple[float, dict]], peers: dict, make_room: bool = True) -> None:
    """Draw the failed methods (x, row), whose MAE (nearly) only measures the placeholder
    normal (``placeholder_error``), in a band at the top of the axes instead of at that MAE: it
    is the same ~40 deg for every such method and would sit among real results. Each shows its
    own marker, crossed out, at its x; methods failing at one x stand side by side, so the legend
    tells which failed (a method drawn nowhere else gets its legend entry here)."""
    if not failed:
        return
    # The band's markers are placed by x only: the x axis must reach them, as it would real points.
    low = ax.get_ylim()[0]
    ax.update_datalim([(x, low) for x, _ in failed], updatex=True, updatey=False)
    ax.autoscale_view(scalex=True, scaley=False)
    if make_room:
        _make_room_for_failed(ax)
    band = ax.get_xaxis_transform()  # x in data, y in axes units
    ax.plot([0, 1], [FAILED_BAND - 0.035] * 2, transform=ax.transAxes, color="0.75", linewidth=0.8, label="_nolegend_")
    by_x: dict = defaultdict(dict)
    for x, row in failed:
        by_x[x].setdefault((row["kind"], row["series"]), row["label"])
    listed = set(ax.get_legend_handles_labels()[1])
    label = FAILED_LABEL
    for x, methods in by_x.items():
        # Centred on x, or starting (ending) there near the left (right) edge of the panel.
        where = ax.transAxes.inverted().transform(ax.transData.transform((x, 1.0)))[0]
        first = 0.0 if where < 0.15 else -(len(methods) - 1.0) if where > 0.85 else -(len(methods) - 1) / 2
        for rank, ((kind, series), method) in enumerate(methods.items()):
            shifted = matplotlib.transforms.offset_copy(band, fig=ax.figure, x=FAILED_SPACING * (first + rank), y=0.0, units="points")
            ax.plot([x], [FAILED_BAND], transform=shifted, linestyle="none", markersize=7, clip_on=False,
                    label="_nolegend_" if method in listed else method, **_marker_style(kind, series, peers))
            listed.add(method)
            ax.plot([x], [FAILED_BAND], transform=shifted, linestyle="none", marker="x", color="black", markersize=4, markeredgewidth=0.8,
                    clip_on=False, label=label, zorder=5)
            label = "_nolegend_"


LABEL_OFFSETS = ((4, 3), (4, -9), (-4, 3), (-4, -9), (4, 10), (4, -16))
"""Where an "M=" label may sit, tried in order: (x, y) of its lower corner from its point, in
points; a negative x puts the label's right edge there (left of the point)."""
LABEL_FONT_SIZE = 6


def _boxes_overlap(first, second) -> bool:
    return first[0] < second[2] and second[0] < first[2] and first[1] < second[3] and second[1] < first[3]


def _label_counts(ax, points: list[tuple[float, float, int]]) -> None:
    """Label chart points (x, y, M) with "M=..." on log axes; points within 2 % of each other
    share one label listing their M values (methods with the same result would pile up). Each
    label takes the first of ``LABEL_OFFSETS`` that covers no labelled point and no label placed
    before it (sizes estimated from the font size), so call this after the axes' scales and
    limits are set."""
    groups: list[list] = []
    for x, y, count in sorted(points):
        for group in groups:
            if all(abs(math.log(max(a, 1e-12) / max(b, 1e-12))) < 0.02 for a, b in ((x, group[0]), (y, group[1]))):
                group[2].add(count)
                break
        else:
            groups.append([x, y, {count}])
    ax.get_xlim(), ax.get_ylim()  # settle the automatic limits before mapping points to the display
    points_per_pixel = 72.0 / ax.figure.dpi
    anchors = [ax.transData.transform((x, y)) * points_per_pixel for x, y, _ in groups]
    taken = [(px - 3.5, py - 3.5, px + 3.5, py + 3.5) for px, py in anchors]  # the markers
    for (x, y, counts), (px, py) in zip(groups, anchors):
        text = "M=" + ",".join(map(str, sorted(counts)))
        width, height = 0.6 * LABEL_FONT_SIZE * len(text), LABEL_FONT_SIZE
        options = [(dx if dx >= 0 else dx - width, dy) for dx, dy in LABEL_OFFSETS]
        boxes = [(px + dx, py + dy, px + dx + width, py + dy + height) for dx, dy in options]
        choice = next((index for index, box in enumerate(boxes) if not any(_boxes_overlap(box, other) for other in taken)), 0)
        taken.append(boxes[choice])
        ax.annotate(text, (x, y), textcoords="offset points", xytext=options[choice], fontsize=LABEL_FONT_SIZE)


def close_up_limits(rows: list[dict], headroom: float = 1.4) -> tuple[float, float] | None:
    """The MAE range (deg) of the close-up panel of ``chart_mae_vs_patterns``: from just below the
    lowest MAE to ``headroom`` times the largest of the per-M lowest MAEs (the OLAT reference line
    included when it lies within twice that), failed rows (``placeholder_error``) left out. None
    without another row."""
    valid = [row for row in rows if not placeholder_error(row) and math.isfinite(row["mae"])]
    best_per_m = [min(row["mae"] for row in valid if row["M"] == count) for count in {row["M"] for row in valid if row["kind"] != "reference"}]
    if not best_per_m:
        return None
    high = headroom * max(best_per_m)
    reference = [row["mae"] for row in valid if row["kind"] == "reference" and row["mae"] < 2 * high]
    high = max([high] + [1.05 * value for value in reference])
    return 0.95 * min(best_per_m + reference), high


def chart_mae_vs_patterns(rows: list[dict], caption: str):
    """MAE (deg) against M, one line per method; the OLAT reference as a horizontal line. Two
    panels: every method, and a close-up of the best ones (``close_up_limits``), which the
    full range squeezes into a few millimetres when some methods fail."""
    limits, peers = close_up_limits(rows), _peers(rows)
    fig, axes = plt.subplots(1, 2, figsize=(12.5, 4.8))
    counts = sorted({row["M"] for row in rows if row["kind"] != "reference"})
    for ax in axes:
        for (kind, label, series), values in _series(rows).items():
            if kind == "reference":
                ax.axhline(values[0]["mae"], color="black", linestyle="--", linewidth=1, label=f"{values[0]['label']}")
                continue
            # A failed point measures the placeholder normal: drawn in the failure band below, and
            # the line breaks there instead of joining it to real reconstructions.
            maes = [math.nan if placeholder_error(row) else row["mae"] for row in values]
            errors = [row["mae_std"] for row in values]
            ax.errorbar([row["M"] for row in values], maes, yerr=errors if kind == "learned" else None, label=label, capsize=3, **_style(kind, series, peers))
        if ax is axes[0]:  # the close-up shows the most accurate methods only
            _mark_failed(ax, [(row["M"], row) for row in rows if row["kind"] != "reference" and placeholder_error(row)], peers)
        ax.set_xticks(counts)
        ax.set_xlabel("number of patterns M (images)")
        ax.set_ylabel("mean angular error (deg)")
        ax.grid(alpha=0.3)
    axes[0].set_title("Normal error against the number of patterns")
    if limits is not None:
        axes[1].set_ylim(*limits)
    axes[1].set_title("Close-up of the most accurate methods")
    # The close-up's entries, and the failure band's of the full panel (its crossed-out mark and
    # the methods drawn nowhere else).
    legend = _legend_entries([axes[1], axes[0]])
    axes[1].legend(list(legend.values()), list(legend), fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _caption(fig, caption)
    fig.tight_layout()
    return fig


def _plain_tick(value: float, _position=None) -> str:
    return f"{value:g}"


def _leading_one_two_five(value: float, _position=None) -> str:
    # The leading significant digit ("2e-01" for 0.2): the first character of f"{value:g}" is 0 below 1.
    return f"{value:g}" if f"{value:.0e}"[0] in "125" else ""


MINOR_LABEL_DECADES = 2.5
"""Widest span (decades) of a log axis whose minor ticks at 2 and 5 are labelled: on wider ones
"500", "1000" and "2000" ran together."""


def plain_log_ticks(axis) -> None:
    """Plain numbers (0.2, 0.5, 1, 2) on a log ``axis`` instead of powers of ten, the minor ticks
    labelled at 1, 2 and 5 times a power of ten only, and only on axes spanning at most
    ``MINOR_LABEL_DECADES`` when drawn: a range inside one decade has no major tick, and labelling
    every minor tick (or, on a wide axis, every 2 and 5) makes the labels collide."""

    def minor(value, position=None):
        low, high = sorted(abs(bound) for bound in axis.get_view_interval())
        narrow = low > 0 and math.log10(high / low) <= MINOR_LABEL_DECADES
        return _leading_one_two_five(value) if narrow else ""

    axis.set_major_formatter(matplotlib.ticker.FuncFormatter(_plain_tick))
    axis.set_minor_formatter(matplotlib.ticker.FuncFormatter(minor))


HEURISTIC_MARKER_SIZES = (5.0, 7.5, 10.0, 12.5)
"""Marker sizes of heuristic families in the cost charts, by the rank of M (larger M: larger)."""


def chart_mae_vs_cost(rows: list[dict], key: str, xlabel: str, title: str, caption: str):
    """Scatter of MAE (deg) against a cost per method and M (log x axis). Points are labelled by M,
    except the heuristic families', whose labels would pile up where nine families sit at one M:
    their marker grows with M instead (``HEURISTIC_MARKER_SIZES``), as the caption says."""
    fig, ax = plt.subplots(figsize=(9.0, 4.8))
    labelled, peers = [], _peers(rows)
    counts = sorted({row["M"] for row in rows if row["kind"] == "heuristic"})
    failed = [(max(row[key], 1e-6), row) for row in rows if placeholder_error(row)]
    for (kind, label, series), values in _series([row for row in rows if not placeholder_error(row)]).items():
        xs = [max(row[key], 1e-6) for row in values]
        ys = [row["mae"] for row in values]
        style = _marker_style(kind, series, peers)
        if kind == "heuristic":
            for index, (x, y, row) in enumerate(zip(xs, ys, values)):
                size = HEURISTIC_MARKER_SIZES[min(counts.index(row["M"]), len(HEURISTIC_MARKER_SIZES) - 1)]
                ax.plot([x], [y], linestyle="none", markersize=size, label=label if index == 0 else "_nolegend_", **style)
            continue
        ax.plot(xs, ys, linestyle="none", markersize=7, label=label, **style)
        labelled += [(x, y, row["M"]) for x, y, row in zip(xs, ys, values)]
    if len(counts) > 1:
        caption += f" Heuristic families: marker size grows with M ({', '.join(map(str, counts))})."
    ax.set_xscale("log")
    _mark_failed(ax, failed, peers)
    plain_log_ticks(ax.xaxis)
    ax.set_xlabel(f"{xlabel}; log scale")
    ax.set_ylabel("mean angular error (deg)")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _caption(fig, caption)
    fig.tight_layout()
    _label_counts(ax, labelled)  # after the layout: labels make room for each other on the final axes
    return fig


def chart_mae_vs_noise(results: dict, caption: str):
    """MAE (deg) against noise level, one panel per M, one line per method."""
    counts = results["pattern_counts"]
    fig, axes = plt.subplots(1, len(counts), figsize=(4.2 * len(counts), 6.0), squeeze=False, sharey=True)
    per_noise = {noise: aggregate_rows(results, noise) for noise in results["noise_scales"]}
    noises = sorted(per_noise)
    peers = _peers([row for rows in per_noise.values() for row in rows])
    failed: dict = {}
    for ax, count in zip(axes[0], counts):
        keys = {}
        for noise in noises:
            for row in per_noise[noise]:
                if row["M"] == count or row["kind"] == "reference":
                    # A failed point measures the placeholder normal: drawn in the failure band, the line breaks.
                    broken = placeholder_error(row) and row["kind"] != "reference"
                    keys.setdefault((row["kind"], row["label"], row["series"]), []).append((noise, math.nan if broken else row["mae"]))
        for (kind, label, series), points in sorted(keys.items(), key=lambda item: KIND_ORDER.get(item[0][0], 9)):
            style = _style(kind, series, peers)
            if kind == "reference":
                style.update(linestyle="--", marker="*")
            ax.plot([p[0] for p in points], [p[1] for p in points], label=label, **style)
        failed[ax] = [(noise, row) for noise in noises for row in per_noise[noise]
                      if row["M"] == count and row["kind"] != "reference" and placeholder_error(row)]
        ax.set_xscale("symlog", linthresh=min([n for n in noises if n > 0], default=1.0))
        ax.set_xticks(noises)
        ax.set_xticklabels([f"{n:g}" for n in noises])
        ax.set_xlabel("noise scale (x rig noise variance; log scale)")
        ax.set_title(f"M = {count}")
        ax.grid(alpha=0.3)
    if any(failed.values()):
        _make_room_for_failed(axes[0, 0])  # once: the panels share their limits
    for ax, points in failed.items():
        _mark_failed(ax, points, peers, make_room=False)
    axes[0, 0].set_ylabel("mean angular error (deg)")
    legend = _legend_entries(axes[0])
    fig.suptitle("Normal error against sensor noise (where methods fail)")
    # Axes in the top 70 %, the legend below them, the caption at the bottom: nothing overlaps.
    fig.tight_layout(rect=(0, 0.3, 1, 0.97))
    fig.legend(list(legend.values()), list(legend), fontsize=7, loc="upper center", ncol=min(4, max(1, len(legend))), bbox_to_anchor=(0.5, 0.25))
    fig.text(0.5, 0.005, caption, ha="center", va="bottom", fontsize=8, wrap=True)
    return fig


def chart_specular_free(rows: list[dict], free_rows: list[dict], caption: str):
    """MAE (deg) on the test scenes against MAE without their specular stacks, one point per method
    and M (log axes); the distance above the diagonal is the error due to specular reflection."""
    free = {(row["series"], row["M"]): row["mae"] for row in free_rows}
    fig, ax = plt.subplots(figsize=(9.0, 5.2))
    labelled, peers = [], _peers(rows)
    shown = [row for row in rows if (row["series"], row["M"]) in free]
    drawn = [row for row in shown if not placeholder_error(row)]
    for (kind, label, series), values in _series(drawn).items():
        points = [(free[(row["series"], row["M"])], row["mae"], row["M"]) for row in values]
        if not points:
            continue
        style = _marker_style(kind, series, peers)
        ax.plot([p[0] for p in points], [p[1] for p in points], linestyle="none", markersize=7, label=label, **style)
        if kind != "heuristic":
            labelled += points
    values = [free[(row["series"], row["M"])] for row in drawn] + [row["mae"] for row in drawn]
    low, high = max(min(values, default=0.1), 1e-2), max(values, default=1.0)
    ax.plot([low, high], [low, high], color="grey", linewidth=1, linestyle=":", label="no specular error (y = x)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(bottom=max(min((row["mae"] for row in drawn), default=low), 1e-2) / 1.5)  # the diagonal may leave the plot below
    _mark_failed(ax, [(free[(row["series"], row["M"])], row) for row in shown if placeholder_error(row)], peers)
    plain_log_ticks(ax.xaxis)
    plain_log_ticks(ax.yaxis)
    ax.set_xlabel("mean angular error without specular reflection (deg, log scale)")
    ax.set_ylabel("mean angular error on the test scenes (deg, log scale)")
    ax.set_title("How much of each method's error is specular reflection")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _caption(fig, caption)
    fig.tight_layout()
    _label_counts(ax, labelled)  # after the layout: labels make room for each other on the final axes
    return fig


def pattern_strip(patterns: np.ndarray, gap: int = 1) -> np.ndarray:
    """(R, M * (C + gap) - gap, 3) image of M patterns side by side, white gaps between them."""
    count, rows, cols, _ = patterns.shape
    strip = np.ones((rows, count * (cols + gap) - gap, 3), dtype=np.float32)
    for index in range(count):
        strip[:, index * (cols + gap): index * (cols + gap) + cols] = patterns[index]
    return strip


def chart_patterns(entries: list[tuple[str, np.ndarray]], caption: str):
    """One row per pattern set: its M patterns as display set values (row 0 = top of the panel)."""
    widest = max(patterns.shape[0] * (patterns.shape[2] + 1) for _, patterns in entries)
    fig, axes = plt.subplots(len(entries), 1, figsize=(min(16, 2.0 + widest / 10), 0.95 * len(entries) + 0.8), squeeze=False)
    for ax, (title, patterns) in zip(axes[:, 0], entries):
        strip = pattern_strip(patterns)
        canvas = np.ones((strip.shape[0], widest, 3), dtype=np.float32)
        canvas[:, : strip.shape[1]] = strip
        ax.imshow(canvas, interpolation="nearest")
        # Outlined: fully lit superpixels would merge with the white gaps and background.
        count, rows, cols, _ = patterns.shape
        for index in range(count):
            ax.add_patch(matplotlib.patches.Rectangle((index * (cols + 1) - 0.5, -0.5), cols, rows, fill=False, edgecolor="0.45", linewidth=0.6))
        ax.set_title(title, fontsize=8, loc="left")
        ax.set_axis_off()
    fig.suptitle("Pattern sets (display set values in [0, 1], before the display gamma)")
    _caption(fig, caption)
    fig.tight_layout()
    return fig


def pattern_entries(results: dict, rows: list[dict], pattern_sets: dict) -> list[tuple[str, np.ndarray]]:
    """Pattern sets to draw: per M the first learned seed, the best heuristic, searches, externals."""
    entries = []
    for count in results["pattern_counts"]:
        learned = sorted((m for m in results["methods"] if m["kind"] == "learned" and m["M"] == count), key=lambda m: m["seed"])
        if learned and learned[0]["id"] in pattern_sets:
            entries.append((f"learned, M = {count} (seed {learned[0]['seed']})", pattern_sets[learned[0]["id"]]))
        heuristics = [row for row in rows if row["kind"] == "heuristic" and row["M"] == count]
        if heuristics:
            best = min(heuristics, key=lambda row: row["mae"])
            method_id = next((m["id"] for m in results["methods"] if m["kind"] == "heuristic" and m["series"] == best["series"] and m["M"] == count), None)
            if method_id in pattern_sets:
                entries.append((f"best heuristic, M = {count}: {best['series']} ({best['mae']:.1f} deg)", pattern_sets[method_id]))
        for method in results["methods"]:
            if method["kind"] in ("rerender", "search", "external") and method["M"] == count and method["id"] in pattern_sets:
                entries.append((f"{method['kind']}: {method['label']}, M = {count}", pattern_sets[method["id"]]))
    return entries


def write_charts(results: dict, summary: dict, pattern_sets: dict, into: Path, pixels: str) -> set[str]:
    """Write the report's charts into ``into``; returns the ``CHARTS`` keys written.

    Args:
        results, summary: ``run_compare``'s results and their ``summary_tables``.
        pattern_sets: method id -> (M, R, C, 3) patterns, for the pattern figure.
        into: the folder written into.
        pixels: the pixels reconstructed per scene, as the compute-time axis names them
            (e.g. "at most 4000 pixels").
    """
    rows = summary["rows"]
    solvers = "analytic PS (OLAT: Woodham)" if any(method["kind"] == "reference" for method in results["methods"]) else "analytic PS"
    scenes = test_scenes_text(results)
    short = f"{scenes}, noise scale {results['default_noise']:g}, {solvers}; MAE averaged over scenes."
    learned_seeds = [row["seeds"] for row in rows if row["kind"] == "learned"]
    seeds_note = "" if not learned_seeds else " Learned: mean over seeds, bars = sample std over seeds." if max(learned_seeds) > 1 else " Learned: one seed."
    save_figure(chart_mae_vs_patterns(rows, short + seeds_note), into / CHARTS["mae_vs_M"])
    save_figure(chart_mae_vs_cost(rows, "capture_seconds", f"capture time (s) = M x {results['exposure_ms']:g} ms x e / e_white", "Accuracy against capture time",
                                  short), into / CHARTS["mae_vs_capture_time"])
    save_figure(chart_mae_vs_cost(rows, "reconstruct_seconds", f"compute time per scene (s): reconstruction of {pixels}, CPU",
                                  "Speed-accuracy: normal error against compute time", short), into / CHARTS["mae_vs_compute_time"])
    save_figure(chart_mae_vs_noise(results, f"{scenes}; {solvers}; noise scale multiplies the rig's noise variances."),
                into / CHARTS["mae_vs_noise"])
    written = {"mae_vs_M", "mae_vs_capture_time", "mae_vs_compute_time", "mae_vs_noise"}
    free_rows = (summary.get("specular_free") or {}).get("rows")
    if free_rows:
        save_figure(chart_specular_free(rows, free_rows, f"{short} x: the same scenes, pixels and noise without the specular stacks."),
                    into / CHARTS["specular_free"])
        written.add("specular_free")
    entries = pattern_entries(results, rows, pattern_sets)
    if entries:
        save_figure(chart_patterns(entries, "Each row: one pattern set, patterns left to right; superpixel grid in pattern order (on the preset rigs column 0 is at camera-left, and the display, facing the object, shows it mirrored left-right)."), into / CHARTS["patterns"])
        written.add("patterns")
    return written
