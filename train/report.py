"""The comparison report: summary tables, report.md and charts from ``run_compare``'s results.

Everything here reads the results dict only (plus the pattern arrays for the pattern figure), so a
report can be rebuilt from ``results.json``. Learned patterns with several seeds enter tables and
charts as their mean over seeds; the seed spread has its own table.
"""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import matplotlib.ticker
import numpy as np

from capture_sim.atomic import write_text
from patterns.families import FAMILIES, PRESET_LEVELS
from reconstruct.photometric_stereo import INVALIDATING_FLAGS
from train.figures import plt, save_figure

CHARTS = {
    "mae_vs_M": "mae_vs_M.png",
    "mae_vs_capture_time": "mae_vs_capture_time.png",
    "mae_vs_compute_time": "mae_vs_compute_time.png",
    "mae_vs_noise": "mae_vs_noise.png",
    "patterns": "patterns.png",
    "specular_free": "mae_specular_free.png",
}
"""Chart name -> file name in the output folder."""

_ROW_METRICS = ("mae", "median", "under_10", "invalid_fraction", "exposure", "capture_seconds", "compute_seconds")
"""Means over a row's seeds at one noise level (``reconstruct_seconds`` is a median: ``aggregate_rows``)."""
_KIND_ORDER = {"learned": 0, "rerender": 1, "search": 2, "external": 3, "heuristic": 4, "reference": 5}
_KIND_STYLE = {
    "learned": dict(color="tab:red", marker="o", linewidth=2.5, zorder=4),  # above the heuristics' markers
    "rerender": dict(color="darkorange", marker="P", linewidth=2.0, linestyle="--", zorder=3),
    "search": dict(marker="D", linewidth=1.5),  # colours per series: _OTHER_COLOURS
    "external": dict(marker="s", linewidth=1.5),
    "heuristic": dict(linewidth=1.0, alpha=0.8, fillstyle="none"),  # markers per series: _HEURISTIC_MARKERS
    "reference": dict(color="black", marker="*", linewidth=1.0),
}


def _evaluation(method: dict, noise: float) -> dict | None:
    for evaluation in method["evaluations"]:
        if math.isclose(evaluation["noise_scale"], noise):
            return evaluation
    return None


def aggregate_rows(results: dict, noise: float, specular_free: bool = False) -> list[dict]:
    """One row per (series, M) at one noise level; learned seeds are averaged.

    With ``specular_free``, the rows of the methods' ``specular_free`` summaries (measured at the
    default noise only; empty at other noise levels).

    Returns:
        rows with series, label, kind, M, seeds (count), cost_seconds (mean), the means of mae,
        median, under_10, invalid_fraction, exposure, capture_seconds, compute_seconds, the median
        reconstruct_seconds over the methods' evaluations at every noise level, plus
        mae_std over seeds (0 for one seed); sorted by kind, then M, then MAE.
    """
    groups: dict = defaultdict(list)
    for method in results["methods"]:
        if specular_free:
            evaluation = method.get("specular_free") if math.isclose(noise, results["default_noise"]) else None
        else:
            evaluation = _evaluation(method, noise)
        if evaluation is not None:
            groups[(method["series"], method["M"])].append((method, evaluation))
    rows = []
    for (series, count), members in groups.items():
        first = members[0][0]
        row = {"series": series, "kind": first["kind"], "M": count, "seeds": len(members),
               "label": "learned" if first["kind"] == "learned" else first["label"]}  # seeds differ per M: said per cell
        for key in _ROW_METRICS:
            row[key] = float(np.mean([evaluation[key] for _, evaluation in members]))
        # Wall times of worker processes that share the cores swing by 2x: the median of the
        # methods' test-scene evaluations at every noise level is steadier than one of them.
        # Absent from results of older versions ('-' in the tables).
        times = [evaluation.get("reconstruct_seconds", math.nan) for method, _ in members for evaluation in method["evaluations"]]
        row["reconstruct_seconds"] = float(np.median(times)) if times else math.nan
        row["mae_std"] = float(np.std([evaluation["mae"] for _, evaluation in members]))
        costs = [method["cost_seconds"] for method, _ in members if method["cost_seconds"] is not None]
        row["cost_seconds"] = float(np.mean(costs)) if costs else None
        rows.append(row)
    rows.sort(key=lambda r: (_KIND_ORDER.get(r["kind"], 9), r["M"], r["mae"]))
    return rows


def summary_tables(results: dict) -> dict:
    """The derived numbers of the report.

    Returns:
        dict with ``rows`` (``aggregate_rows`` at the default noise), ``learned_vs_heuristic``
        (per M and noise: learned MAE, best heuristic family and MAE at default parameters, the
        ratio learned / best heuristic, and the same against the best of heuristics and searches),
        ``seed_spread`` (per M and noise with several seeds: mean, std, min, max MAE) and
        ``rerender`` (per M and noise: the normal-only learned MAE of the same seed against the
        normal + re-rendering learned MAE, and their ratio), ``specular_free`` (rows and ratios
        without the specular stacks) and ``learned_vs_more_captures``
        (``learned_against_more_captures`` at the default noise).
    """
    comparisons, spread, rerender = [], [], []
    for noise in results["noise_scales"]:
        rows = aggregate_rows(results, noise)
        comparisons += learned_against_best(rows, results["pattern_counts"], noise)
        by_m: dict = defaultdict(list)
        for method in results["methods"]:
            evaluation = _evaluation(method, noise)
            if method["kind"] == "learned" and evaluation is not None:
                by_m[method["M"]].append((method["seed"], evaluation["mae"]))
        learned_by_key = {(method["M"], method["seed"]): method for method in results["methods"] if method["kind"] == "learned"}
        for method in results["methods"]:
            normal_only = learned_by_key.get((method["M"], method["seed"]))
            if method["kind"] != "rerender" or normal_only is None:
                continue
            with_rerender, without = _evaluation(method, noise), _evaluation(normal_only, noise)
            # An all-invalid side measures the placeholder normal: no comparison to make.
            if with_rerender is not None and without is not None and not (all_invalid(with_rerender) or all_invalid(without)):
                rerender.append({"M": method["M"], "noise_scale": noise, "seed": method["seed"], "weight": method["info"].get("rerender_weight"),
                                 "normal_only_mae": without["mae"], "rerender_mae": with_rerender["mae"],
                                 "ratio": with_rerender["mae"] / max(without["mae"], 1e-12)})
        for count, values in sorted(by_m.items()):
            if len(values) > 1:
                maes = np.array([mae for _, mae in values])
                spread.append({"M": count, "noise_scale": noise, "seeds": [seed for seed, _ in values], "maes": maes.tolist(),
                               "mean": float(maes.mean()), "std": float(maes.std()), "min": float(maes.min()), "max": float(maes.max())})
    comparisons.sort(key=lambda c: (c["M"], c["noise_scale"]))
    spread.sort(key=lambda s: (s["M"], s["noise_scale"]))
    rerender.sort(key=lambda r: (r["M"], r["noise_scale"]))
    default = results["default_noise"]
    free_rows = aggregate_rows(results, default, specular_free=True)
    specular_free = {"rows": free_rows, "learned_vs_heuristic": learned_against_best(free_rows, results["pattern_counts"], default)}
    rows = aggregate_rows(results, default)
    return {"rows": rows, "learned_vs_heuristic": comparisons, "seed_spread": spread, "rerender": rerender,
            "specular_free": specular_free, "learned_vs_more_captures": learned_against_more_captures(rows)}


def lowest_mae_per_m(rows: list[dict], kinds: tuple[str, ...]) -> dict:
    """M -> the row of one of ``kinds`` with the lowest MAE at that M (the first on ties), among
    rows that reconstructed something (``all_invalid`` rows measure the placeholder normal: at a
    high noise one can beat every real reconstruction); M without such a row is left out."""
    best: dict = {}
    for row in rows:
        if row["kind"] in kinds and not all_invalid(row) and (row["M"] not in best or row["mae"] < best[row["M"]]["mae"]):
            best[row["M"]] = row
    return best


def learned_rows_per_m(rows: list[dict]) -> dict:
    """M -> the learned row (``aggregate_rows`` averages the seeds into one row per M)."""
    learned: dict = {}
    for row in rows:
        if row["kind"] == "learned":
            learned.setdefault(row["M"], row)
    return learned


def learned_against_best(rows: list[dict], counts, noise: float) -> list[dict]:
    """Per M with learned and heuristic rows (``aggregate_rows`` at one noise level): the learned
    MAE, the best heuristic family and MAE, their ratio, and the same against the best of the
    heuristics and the searches ("tuned")."""
    learned = learned_rows_per_m(rows)
    best = lowest_mae_per_m(rows, ("heuristic",))
    best_tuned = lowest_mae_per_m(rows, ("heuristic", "search"))
    searched = {row["M"] for row in rows if row["kind"] == "search"}

    def tuned(count, key):  # None where no search ran at that M: the tuned columns would copy the others
        return best_tuned[count][key] if count in searched else None

    return [
        {
            "M": count, "noise_scale": noise, "learned_mae": learned[count]["mae"],
            # The learned MAE, and so the ratios, then measure the placeholder normal.
            "learned_all_invalid": all_invalid(learned[count]),
            "best_heuristic": best[count]["series"], "best_heuristic_mae": best[count]["mae"],
            "ratio": learned[count]["mae"] / max(best[count]["mae"], 1e-12),
            "best_tuned": tuned(count, "label"), "best_tuned_mae": tuned(count, "mae"),
            "ratio_tuned": None if count not in searched else learned[count]["mae"] / max(best_tuned[count]["mae"], 1e-12),
        }
        for count in counts if count in learned and count in best
    ]


def learned_against_more_captures(rows: list[dict]) -> list[dict]:
    """For every learned M and every larger M with heuristic rows (``aggregate_rows`` at one noise
    level): the learned MAE at M against the best heuristic at the larger M. A ratio <= 1 means
    the learned patterns reach that accuracy with fewer captures.

    Returns:
        dicts with M, learned_mae, heuristic_M, best_heuristic, best_heuristic_mae and ratio,
        sorted by (M, heuristic_M).
    """
    # All-invalid learned rows measure the placeholder normal: they match nothing.
    learned = {count: row for count, row in learned_rows_per_m(rows).items() if not all_invalid(row)}
    best = lowest_mae_per_m(rows, ("heuristic",))
    return [
        {"M": count, "learned_mae": learned[count]["mae"], "heuristic_M": more, "best_heuristic": best[more]["series"],
         "best_heuristic_mae": best[more]["mae"], "ratio": learned[count]["mae"] / max(best[more]["mae"], 1e-12)}
        for count in sorted(learned) for more in sorted(best) if more > count
    ]


# ---------------------------------------------------------------------------------------------
# Charts
# ---------------------------------------------------------------------------------------------


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
    return {key: sorted(values, key=lambda r: r["M"]) for key, values in sorted(series.items(), key=lambda item: _KIND_ORDER.get(item[0][0], 9))}


ALL_INVALID_LABEL = "every pixel invalid (MAE of the placeholder normal)"


def invalid_note(fraction: float) -> str:
    """' (all invalid)' or ' (99.99% invalid)' after an error that (nearly) only measures the
    placeholder normal (at least 99% of the pixels invalid); '' otherwise."""
    if fraction >= 1.0:
        return " (all invalid)"
    # Rounded to float32's precision first (0.9999 is 0.99989998), then down, never up to 100%.
    return f" ({min(math.floor(round(fraction * 1e4, 3)) / 100, 99.99):g}% invalid)" if fraction >= 0.99 else ""


def all_invalid(row: dict) -> bool:
    """Whether every pixel of a method's evaluation was flagged invalid: its MAE measures the
    placeholder normal, not a reconstruction."""
    return row.get("invalid_fraction", 0.0) >= 1.0


def _cross_out(ax, points: list[tuple[float, float]]) -> None:
    """Mark chart points (x, y) of all-invalid evaluations with one labelled black cross each."""
    if points:
        ax.plot(*zip(*points), linestyle="none", marker="x", color="black", markersize=11, markeredgewidth=1.5, label=ALL_INVALID_LABEL, zorder=5)


def _label_counts(ax, points: list[tuple[float, float, int]]) -> None:
    """Label chart points (x, y, M) with "M=..." on log axes; points within 2 % of each other
    share one label listing their M values (methods with the same result would pile up)."""
    groups: list[list] = []
    for x, y, count in sorted(points):
        for group in groups:
            if all(abs(math.log(max(a, 1e-12) / max(b, 1e-12))) < 0.02 for a, b in ((x, group[0]), (y, group[1]))):
                group[2].add(count)
                break
        else:
            groups.append([x, y, {count}])
    for x, y, counts in groups:
        ax.annotate("M=" + ",".join(map(str, sorted(counts))), (x, y), textcoords="offset points", xytext=(4, 3), fontsize=6)


def close_up_limits(rows: list[dict], headroom: float = 1.4) -> tuple[float, float] | None:
    """The MAE range (deg) of the close-up panel of ``chart_mae_vs_patterns``: from just below the
    lowest MAE to ``headroom`` times the largest of the per-M lowest MAEs (the OLAT reference line
    included when it lies within twice that), all-invalid rows left out. None without a valid row."""
    valid = [row for row in rows if not all_invalid(row) and math.isfinite(row["mae"])]
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
            # An all-invalid point measures the placeholder normal: crossed out below, and the line
            # breaks there instead of joining it to real reconstructions.
            maes = [math.nan if all_invalid(row) else row["mae"] for row in values]
            errors = [row["mae_std"] for row in values]
            ax.errorbar([row["M"] for row in values], maes, yerr=errors if kind == "learned" else None, label=label, capsize=3, **_style(kind, series, peers))
        _cross_out(ax, [(row["M"], row["mae"]) for row in rows if row["kind"] != "reference" and all_invalid(row)])
        ax.set_xticks(counts)
        ax.set_xlabel("number of patterns M (images)")
        ax.set_ylabel("mean angular error (deg)")
        ax.grid(alpha=0.3)
    axes[0].set_title("Normal error against the number of patterns")
    if limits is not None:
        axes[1].set_ylim(*limits)
    axes[1].set_title("Close-up of the most accurate methods")
    axes[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _caption(fig, caption)
    fig.tight_layout()
    return fig


def _plain_tick(value: float, _position=None) -> str:
    return f"{value:g}"


def _leading_one_two_five(value: float, _position=None) -> str:
    # The leading significant digit ("2e-01" for 0.2): the first character of f"{value:g}" is 0 below 1.
    return f"{value:g}" if f"{value:.0e}"[0] in "125" else ""


def plain_log_ticks(axis) -> None:
    """Plain numbers (0.2, 0.5, 1, 2) on a log ``axis`` instead of powers of ten, the minor ticks
    labelled at 1, 2 and 5 times a power of ten only: a range inside one decade has no major tick,
    and labelling every minor tick makes the labels collide."""
    axis.set_major_formatter(matplotlib.ticker.FuncFormatter(_plain_tick))
    axis.set_minor_formatter(matplotlib.ticker.FuncFormatter(_leading_one_two_five))


HEURISTIC_MARKER_SIZES = (5.0, 7.5, 10.0, 12.5)
"""Marker sizes of heuristic families in the cost charts, by the rank of M (larger M: larger)."""


def chart_mae_vs_cost(rows: list[dict], key: str, xlabel: str, title: str, caption: str):
    """Scatter of MAE (deg) against a cost per method and M (log x axis). Points are labelled by M,
    except the heuristic families', whose labels would pile up where nine families sit at one M:
    their marker grows with M instead (``HEURISTIC_MARKER_SIZES``), as the caption says."""
    fig, ax = plt.subplots(figsize=(9.0, 4.8))
    labelled, peers = [], _peers(rows)
    counts = sorted({row["M"] for row in rows if row["kind"] == "heuristic"})
    for (kind, label, series), values in _series(rows).items():
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
    _label_counts(ax, labelled)
    _cross_out(ax, [(max(row[key], 1e-6), row["mae"]) for row in rows if all_invalid(row)])
    ax.set_xscale("log")
    plain_log_ticks(ax.xaxis)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("mean angular error (deg)")
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _caption(fig, caption)
    fig.tight_layout()
    return fig


def chart_mae_vs_noise(results: dict, caption: str):
    """MAE (deg) against noise level, one panel per M, one line per method."""
    counts = results["pattern_counts"]
    fig, axes = plt.subplots(1, len(counts), figsize=(4.2 * len(counts), 6.0), squeeze=False, sharey=True)
    per_noise = {noise: aggregate_rows(results, noise) for noise in results["noise_scales"]}
    noises = sorted(per_noise)
    peers = _peers([row for rows in per_noise.values() for row in rows])
    for ax, count in zip(axes[0], counts):
        keys = {}
        for noise in noises:
            for row in per_noise[noise]:
                if row["M"] == count or row["kind"] == "reference":
                    # An all-invalid point measures the placeholder normal: crossed out, the line breaks.
                    broken = all_invalid(row) and row["kind"] != "reference"  # crossed out below, as the reference is not
                    keys.setdefault((row["kind"], row["label"], row["series"]), []).append((noise, math.nan if broken else row["mae"]))
        for (kind, label, series), points in sorted(keys.items(), key=lambda item: _KIND_ORDER.get(item[0][0], 9)):
            style = _style(kind, series, peers)
            if kind == "reference":
                style.update(linestyle="--", marker="*")
            ax.plot([p[0] for p in points], [p[1] for p in points], label=label, **style)
        _cross_out(ax, [(noise, row["mae"]) for noise in noises for row in per_noise[noise]
                        if row["M"] == count and row["kind"] != "reference" and all_invalid(row)])
        ax.set_xscale("symlog", linthresh=min([n for n in noises if n > 0], default=1.0))
        ax.set_xticks(noises)
        ax.set_xticklabels([f"{n:g}" for n in noises])
        ax.set_xlabel("noise scale (x rig noise variance)")
        ax.set_title(f"M = {count}")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("mean angular error (deg)")
    legend = {}
    for ax in axes[0]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            legend.setdefault(label, handle)
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
    for (kind, label, series), values in _series(rows).items():
        points = [(free[(row["series"], row["M"])], row["mae"], row["M"]) for row in values if (row["series"], row["M"]) in free]
        if not points:
            continue
        style = _marker_style(kind, series, peers)
        ax.plot([p[0] for p in points], [p[1] for p in points], linestyle="none", markersize=7, label=label, **style)
        if kind != "heuristic":
            labelled += points
    _label_counts(ax, labelled)
    _cross_out(ax, [(free[(row["series"], row["M"])], row["mae"]) for row in rows if (row["series"], row["M"]) in free and all_invalid(row)])
    low = max(min([*free.values(), *(row["mae"] for row in rows)], default=0.1), 1e-2)
    high = max([*free.values(), *(row["mae"] for row in rows)], default=1.0)
    ax.plot([low, high], [low, high], color="grey", linewidth=1, linestyle=":", label="no specular error (y = x)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_ylim(bottom=max(min((row["mae"] for row in rows), default=low), 1e-2) / 1.5)  # the diagonal may leave the plot below
    plain_log_ticks(ax.xaxis)
    plain_log_ticks(ax.yaxis)
    ax.set_xlabel("mean angular error without specular reflection (deg)")
    ax.set_ylabel("mean angular error on the test scenes (deg)")
    ax.set_title("How much of each method's error is specular reflection")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _caption(fig, caption)
    fig.tight_layout()
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


# ---------------------------------------------------------------------------------------------
# report.md
# ---------------------------------------------------------------------------------------------


def _fmt(value, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return "-"
    text = f"{value:.{digits}f}"
    return text.lstrip("-") if float(text) == 0 else text  # -0.3 % of specular share printed as '-0'


def _seconds(value) -> str:
    """A timing to two significant digits (0.0044, 0.15, 1.2): fixed decimals hid 2x differences
    between small ones."""
    if value is None or not math.isfinite(value):
        return "-"
    # '#' keeps trailing zeros (0.20, not 0.2, beside 0.093), and leaves a bare point after 10 to 99.
    return f"{value:#.2g}".rstrip(".") if value < 10 else f"{value:.0f}"


def _table(header: list[str], lines: list[list[str]]) -> str:
    def row(cells):  # a "|" inside a cell (a user's method name) would split it
        return "| " + " | ".join(str(cell).replace("|", "\\|") for cell in cells) + " |"

    out = [row(header), "|" + "|".join("---" for _ in header) + "|"]
    out += [row(line) for line in lines]
    return "\n".join(out)


def _solver_text(results: dict) -> str:
    solver = results.get("config", {}).get("solver") or {}
    return f" (solver settings changed from the defaults: {', '.join(f'{k} = {v}' for k, v in solver.items())})" if solver else ""


def _pixels_text(results: dict) -> str:
    count = _pixels_per_scene(results)
    return f"a fixed random subset of at most {count} masked pixels per scene (the same for every method)" if count else "every masked pixel"


def _pixels_per_scene(results: dict) -> int:
    """The evaluation's pixels per test scene (0: every masked pixel)."""
    return results.get("config", {}).get("eval_pixels_per_scene", 0)


def _timing_text(results: dict) -> str:
    workers = results.get("config", {}).get("eval_workers", 1)
    threads = f"{results['threads']} threads" if "threads" in results else "this process's threads"
    if workers > 1:
        return f", single-threaded in up to {workers} worker processes sharing the machine (on {threads} when one set is evaluated)"
    return f", on {threads}"


def _pixels_short(results: dict) -> str:
    count = _pixels_per_scene(results)
    return f"at most {count} pixels" if count else "every masked pixel"


def _sizes_text(results: dict) -> str:
    """' of 128 x 153 pixels' (the test images' sizes; absent from results of older versions)."""
    sizes = results.get("test_image_sizes")
    return f" of {' and '.join(sizes)} pixels" if sizes else ""


def _reference_flags(results: dict) -> str:
    """' (a poor fit on 40% of the pixels)' from the OLAT reference's evaluation at the default
    noise ('' without one, or for results of older versions, which carry no flags)."""
    method = next((m for m in results["methods"] if m["kind"] == "reference"), None)
    evaluation = None if method is None else _evaluation(method, results["default_noise"])
    share = ((evaluation or {}).get("flagged") or {}).get("poor_fit", 0.0)
    return f" (a poor fit on {100 * share:.3g}% of the pixels)" if share > 0 else ""


def _held_out_text(results: dict) -> str:
    """'4 held-out test scenes', or '4 test scenes (2 of them also used for learning or searches,
    so not held out: a.npz, b.npz)' where the config listed test scene files among the training
    scenes."""
    count, shared = len(results["test_scenes"]), results.get("test_files_also_trained") or []
    if not shared:
        return f"{count} held-out test scenes"
    return f"{count} test scenes ({len(shared)} of them also used for learning or searches, so not held out: {', '.join(shared)})"


def _measurement_caption(results: dict) -> str:
    reference = any(method["kind"] == "reference" for method in results["methods"])
    return (
        f"Measured on {_held_out_text(results)}{_sizes_text(results)} ({results['test_pixels']} masked pixels in all; "
        f"{', '.join(results['test_scenes'])}), rig {results['rig']} ({results['grid'][0]} x {results['grid'][1]} superpixels). "
        "Captures are simulated from the OLAT stacks (display gamma and backlight, Poisson-Gaussian noise at the given scale "
        "times the rig's noise variances, clipping, quantisation) with auto exposure per scene, then reconstructed with the "
        f"analytic photometric stereo{_solver_text(results)}{' (the OLAT reference: Woodham least squares on all K images)' if reference else ''}. "
        f"MAE and median are angular normal errors in degrees over {_pixels_text(results)}, averaged over scenes (each scene "
        f"weighs the same). {_capture_text(results, reference)} Compute time = wall seconds per scene of the reconstruction "
        f"of {_pixels_short(results)} on this machine's CPU (the simulation of the captures, which the rig's camera replaces, "
        f"is left out){_timing_text(results)}, the median over the method's evaluations at every noise level; only "
        "differences of 2x or more are beyond the noise of such timings. Exposure = mean auto-exposure gain. Cost = wall seconds of a "
        f"learning run (its steps see the training scenes only; the time includes loading the held-out scenes and validating on them) "
        f"or of a search.{_trained_noise_text(results)} {_learning_text(results)}"
        f"{_preset_text(results)}"
    )


def externals_section(results: dict) -> list[str]:
    """The external pattern sets, one line each: name, M and file (relative to the output where
    inside it)."""
    externals = [method for method in results["methods"] if method["kind"] == "external"]
    if not externals:
        return []
    lines = ["## External pattern sets", "", "Pattern files the config lists ([[external]]) that fit the rig and the compared M (others: "
             "see Skipped), evaluated as given: sets learned or designed "
             "elsewhere, under another simulator, reconstructor or scenes, are not tuned to this comparison's.", ""]
    lines += [f"- {method['label']} (M = {method['M']}): {method.get('pattern_file') or '-'}" for method in externals]
    return lines + [""]


def _main_cause(flag_shares: dict[str, float]) -> str:
    """'ill_conditioned: too few or too similar captures': the invalidating flag on most pixels."""
    share, name = max((share, name) for name, share in flag_shares.items() if name in INVALIDATING_FLAGS)
    return f"{name}: {INVALIDATING_FLAGS[name]}"


MANY_INVALID = 0.25
"""Invalid share from which the families section names a set as a near-failure."""


def families_section(results: dict) -> list[str]:
    """The heuristic families compared, one line each: what its patterns are; where every pixel
    was invalid at the default noise, at which M and the flag on most of them (results of older
    versions carry no flags: only the M values are given); and where at least
    ``MANY_INVALID`` of them were, at which M and how many."""
    default = results["default_noise"]
    failed: dict = defaultdict(list)
    many: dict = defaultdict(list)
    names = []
    for method in results["methods"]:
        if method["kind"] != "heuristic":
            continue
        names += [method["series"]] if method["series"] not in names else []
        evaluation = _evaluation(method, default)
        if evaluation is not None and evaluation["invalid_fraction"] >= 1.0:
            failed[method["series"]].append((method["M"], evaluation.get("flagged")))
        elif evaluation is not None and evaluation["invalid_fraction"] >= MANY_INVALID:
            many[method["series"]].append((method["M"], evaluation["invalid_fraction"]))
    if not names:
        return []
    lines = ["## The heuristic families", ""]
    for name in names:
        family = FAMILIES.get(name)
        text = f"- {name}: {family.summary if family else 'not a family of this version'}."
        if name in failed:
            counts = ", ".join(str(count) for count, _ in sorted(failed[name], key=lambda item: item[0]))
            causes = {_main_cause(flagged) for _, flagged in failed[name] if flagged}
            text += f" Every pixel invalid at M = {counts}" + (f" (flagged {' or '.join(sorted(causes))})" if causes else "") + "."
        if name in many:
            shares = ", ".join(f"{100 * share:.0f}% at M = {count}" for count, share in sorted(many[name]))
            text += f" Many pixels invalid: {shares}, counted in the MAE at the placeholder normal."
        lines.append(text)
    if failed:
        lines += ["", "A pixel needs three independent lighting directions to fix its normal. A grey set (the same light in R, G and B) "
                  "gives one independent equation per pattern, so two grey patterns cannot fix a normal; near-identical patterns (gray_noise: "
                  "0.5 grey with 1% noise, the published learning start) are ill-conditioned at any M. The MAE of such a set measures "
                  "the placeholder normal."]
    return lines + [""]


TIE_MARGIN = 0.01
"""In the report's verdicts (noise trend, specular reflection), learned / best-heuristic ratios
within this of 1 are even, not a win or a loss: the test sets are a few scenes, and a heuristic
picked as the best of nine on them is favoured. Tables print the ratios themselves; the "fewer
captures" check keeps the issue's rule, ratio <= 1."""


def noise_verdict(low_noise_ratio: float, high_noise_ratio: float) -> str:
    """How the learned / best-heuristic MAE ratio moves from the lowest to the highest noise, in
    words that also say on which side of 1 it is (a ratio moving from 1.07 to 1.00 is no advantage
    that grows)."""
    low, high = low_noise_ratio < 1 - TIE_MARGIN, high_noise_ratio < 1 - TIE_MARGIN  # an advantage beyond a tie
    if not low and not high:
        return "learned patterns are no better than the best heuristic at either end"
    if low and not high:
        return "the learned advantage is lost"
    if high and not low:
        return "learned patterns overtake the best heuristic"
    change = high_noise_ratio - low_noise_ratio
    return "the learned advantage " + ("grows" if change < -TIE_MARGIN else "shrinks" if change > TIE_MARGIN else "stays about the same")


def _trained_noise_text(results: dict) -> str:
    """' Learning and searches used noise scale 1.' where the comparison learned or searched."""
    kinds = {method["kind"] for method in results["methods"]}
    text = " and ".join(what for what, kind in (("learning", {"learned", "rerender"}), ("searches", {"search"})) if kinds & kind)
    return f" {text[0].upper() + text[1:]} used noise scale {results['default_noise']:g}." if text else ""


def _learning_text(results: dict) -> str:
    """What the learned rows were learned with: steps and start per M, and the training scenes."""
    runs = sorted({(m["M"], m["info"].get("steps"), m["info"].get("init")) for m in results["methods"] if m["kind"] in ("learned", "rerender")},
                  key=lambda run: (run[0], str(run[1]), str(run[2])))
    if not runs:
        return ""
    scenes = results["config"].get("train_scenes") or []
    where = ", ".join(scenes) if scenes else "the default synthetic training split"
    return f"Learning: {'; '.join(f'M = {count}: {steps} steps from {init}' for count, steps, init in runs)}; training scenes: {where}. "


def _capture_text(results: dict, reference: bool = True) -> str:
    return (f"Capture time = M x exposure time per image: {results['exposure_ms']:g} ms ({results['exposure_ms_source']}) for the "
            "all-white display, times e / e_white for a pattern set that auto exposure gives gain e (the noise is added after e "
            "in full-scale units, so e acts as integration time: dim patterns take longer), averaged over scenes."
            + (" The OLAT reference's gain multiplies the raw OLAT stack instead of the display's emission, so its e_white is the "
               "all-white gain times the emission of a superpixel lit at 1, s mean_k (1 + B_k)^gamma (results.json: white_exposures_olat)."
               if reference else ""))


def _preset_text(results: dict) -> str:
    if not any(method["kind"] == "heuristic" for method in results["methods"]):
        return ""
    preset = results["config"].get("heuristic_preset", "default")
    off, on = PRESET_LEVELS[preset]
    published = ("the published levels; tri_gradient keeps 0 and 1, as published" if preset == "ddps"
                 else "the published definitions use 0.1 and 0.9: preset ddps")
    return f"Heuristic families use preset {preset}: off level {off:g}, on level {on:g} where a family has both ({published})."


def specular_free_section(results: dict, summary: dict, rows: list[dict]) -> list[str]:
    """Report lines comparing each method's MAE on the test scenes with its MAE on the same scenes
    without specular reflection (``summary["specular_free"]``); a note when the check was skipped."""
    check = results.get("specular_free") or {}
    if not check.get("enabled"):
        return []
    heading = ["## Where the error comes from: specular reflection", ""]
    if "skipped" in check:
        return heading + [f"Skipped: {check['skipped']}.", ""]
    free = summary.get("specular_free") or {"rows": [], "learned_vs_heuristic": []}
    free_rows = {(row["series"], row["M"]): row for row in free["rows"]}
    default = results["default_noise"]
    lines = heading + [
        f"Every method again at noise scale {default:g} on the same test scenes, pixels, noise draws and exposures (each scene "
        "at the gain of the method's main evaluation), but with each scene's specular stack removed (the OLAT stack replaced by its "
        "diffuse part). What remains is the error of the patterns under noise and shadows; the difference is what specular "
        "reflection costs the Lambertian reconstructor (its model error on glossy pixels and clipped highlights). Specular share = "
        "difference / MAE; '-' where every pixel is invalid both ways.", ""]
    body = []
    for row in sorted(rows, key=lambda r: (r["M"], _KIND_ORDER.get(r["kind"], 9), r["label"])):
        other = free_rows.get((row["series"], row["M"]))
        if other is None:
            continue
        share = None if (all_invalid(row) and all_invalid(other)) or not row["mae"] > 0 else 100.0 * (1.0 - other["mae"] / row["mae"])
        body.append([row["label"], str(row["M"]), _fmt(row["mae"]), _fmt(other["mae"]), _fmt(share, 0)])
    lines += [_table(["method", "M", "MAE (deg)", "specular-free MAE (deg)", "specular share (%)"], body), ""]
    with_specular = {c["M"]: c for c in summary["learned_vs_heuristic"] if math.isclose(c["noise_scale"], default)}
    for c in free["learned_vs_heuristic"]:
        full = with_specular.get(c["M"])
        if c.get("learned_all_invalid") or (full and full.get("learned_all_invalid")):
            lines.append(f"- M = {c['M']}: the learned patterns leave every pixel invalid (no ratio).")
            continue
        head = f"- M = {c['M']}: learned / best heuristic = "
        head += f"{full['ratio']:.3f} on the scenes ({full['best_heuristic']}), " if full else ""
        line = head + f"{c['ratio']:.3f} without specular reflection ({c['best_heuristic']}, {c['best_heuristic_mae']:.2f} deg)"
        if full and full["ratio"] < 1 - TIE_MARGIN and c["ratio"] >= 1 + TIE_MARGIN:
            line += "; the learned advantage comes with specular reflection: without it the best heuristic is better"
        elif full and full["ratio"] < 1 - TIE_MARGIN and c["ratio"] > 1 - TIE_MARGIN:
            line += "; the learned advantage comes with specular reflection: without it the two are even"
        lines.append(line + ".")
    return lines + [""]


def pivot_cell(row: dict, key: str, digits: int | None) -> str:
    """One cell of a method x M table: the row's value (to ``digits`` decimals, or as a timing to
    two significant digits when ``digits`` is None), and how many seeds it averages when more
    than one (a series can average several seeds at one M and one at another). An error where
    every pixel, or at least 99% of them, was invalid is marked (``invalid_note``): it measures
    the placeholder normal, not a reconstruction."""
    note = invalid_note(row.get("invalid_fraction", 0.0)) if key in ("mae", "median") else ""
    return (_seconds(row[key]) if digits is None else _fmt(row[key], digits)) + note + (f" (mean of {row['seeds']} seeds)" if row["seeds"] > 1 else "")


CHART_TITLES = {"mae_vs_M": "MAE against M", "mae_vs_capture_time": "MAE against capture time", "mae_vs_compute_time": "Speed-accuracy (compute time)",
                "mae_vs_noise": "MAE against noise level", "patterns": "The pattern sets", "specular_free": "Error with and without specular reflection"}
"""Report headings of the charts (``CHARTS``)."""


def write_report(results: dict, out_dir: Path, pattern_sets: dict, into: Path) -> Path:
    """Write ``report.md`` and the charts (``CHARTS``) for the output folder ``out_dir``.

    Args:
        results: ``run_compare`` results (with ``summary``).
        out_dir: output folder; the report's links are relative to it.
        pattern_sets: method id -> (M, R, C, 3) patterns, for the pattern figure.
        into: folder the files are written into: ``out_dir``'s staging folder
            (``capture_sim.atomic.staged_files``). A chart this report does not show is not
            written; the caller removes an earlier run's copy of it.

    Returns:
        Path of report.md in ``into``.
    """
    out_dir, into = Path(out_dir), Path(into)
    summary = results.get("summary") or summary_tables(results)
    rows = summary["rows"]
    written = _write_charts(results, summary, pattern_sets, into)
    lines = ["# Pattern comparison", ""]
    lines += summary_section(results, summary)
    lines += ["## How it was measured", "", _measurement_caption(results), ""]
    lines += families_section(results)
    lines += externals_section(results)
    lines += _accuracy_section(results, rows)
    lines += _noise_section(results, rows)
    lines += _advantage_section(summary, results["pattern_counts"])
    lines += _more_captures_section(summary, results["default_noise"])
    lines += specular_free_section(results, summary, rows)
    lines += scene_section(results, summary)
    lines += _seed_section(summary)
    lines += _rerender_section(summary)
    lines += _search_section(results, out_dir)
    if results["skipped"]:
        lines += ["## Skipped", ""] + [f"- {s['method']} at M = {s['M']}: {s['reason']}" for s in results["skipped"]] + [""]
    lines += ["## Charts", ""]
    for name, file_name in CHARTS.items():
        if name in written:
            lines += [f"### {CHART_TITLES[name]}", "", f"![{CHART_TITLES[name]}]({file_name})", ""]
    timings = results["timings"]
    lines += ["## Run", "",
              f"Learning {timings.get('learning_seconds', 0):.0f} s, searches {timings.get('search_seconds', 0):.0f} s, "
              f"evaluation {timings.get('evaluation_seconds', 0):.0f} s"
              + (f", specular-free check {timings['specular_free_seconds']:.0f} s" if "specular_free_seconds" in timings else "")
              + ". All numbers: `results.json`; resolved config: `config.json`; "
              "pattern files: `patterns/`.", ""]
    path = into / "report.md"
    write_text(path, "\n".join(lines))
    return path


def _write_charts(results: dict, summary: dict, pattern_sets: dict, into: Path) -> set[str]:
    """Write the report's charts into ``into``; returns the ``CHARTS`` keys written."""
    rows = summary["rows"]
    short = f"{len(results['test_scenes'])} test scenes, noise scale {results['default_noise']:g}, analytic PS (OLAT: Woodham); MAE averaged over scenes."
    learned_seeds = [row["seeds"] for row in rows if row["kind"] == "learned"]
    seeds_note = "" if not learned_seeds else " Learned: mean over seeds, bars = std." if max(learned_seeds) > 1 else " Learned: one seed."
    save_figure(chart_mae_vs_patterns(rows, short + seeds_note), into / CHARTS["mae_vs_M"])
    save_figure(chart_mae_vs_cost(rows, "capture_seconds", f"capture time (s) = M x {results['exposure_ms']:g} ms x e / e_white", "Accuracy against capture time",
                                  short), into / CHARTS["mae_vs_capture_time"])
    save_figure(chart_mae_vs_cost(rows, "reconstruct_seconds", f"compute time per scene (s): reconstruction of {_pixels_short(results)}, CPU",
                                  "Speed-accuracy: normal error against compute time", short), into / CHARTS["mae_vs_compute_time"])
    save_figure(chart_mae_vs_noise(results, f"{len(results['test_scenes'])} test scenes; analytic PS (OLAT: Woodham); noise scale multiplies the rig's noise variances."),
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


def _accuracy_section(results: dict, rows: list[dict]) -> list[str]:
    """Method x M tables of MAE, median, capture and compute time at the default noise, then one
    table per M with every metric."""
    default, counts = results["default_noise"], results["pattern_counts"]
    series_rows: dict = defaultdict(dict)
    labels = {}
    for row in rows:
        if row["kind"] == "reference":
            continue
        series_rows[row["series"]][row["M"]] = row
        labels[row["series"]] = (row["kind"], row["label"])
    ordered = sorted(series_rows, key=lambda s: (_KIND_ORDER.get(labels[s][0], 9), labels[s][1]))
    reference = next((row for row in rows if row["kind"] == "reference"), None)

    def pivot(key: str, digits: int | None) -> str:
        body = [[labels[s][1], labels[s][0]] + [pivot_cell(series_rows[s][m], key, digits) if m in series_rows[s] else "-" for m in counts] for s in ordered]
        return _table(["method", "kind"] + [f"M = {m}" for m in counts], body)

    lines = [f"## Accuracy and cost at noise scale {default:g}", "",
             "Mean angular error (deg), method x M (lower is better):", "", pivot("mae", 2), ""]
    labels_by_id = {method["id"]: method["label"] for method in results["methods"]}
    copies = [f"{method['label']} holds the same patterns as {labels_by_id.get(method['info']['same_patterns_as'], method['info']['same_patterns_as'])} "
              f"at M = {method['M']}" for method in results["methods"] if (method.get("info") or {}).get("same_patterns_as")]
    if copies:  # identical numbers in two rows are one measurement, not two that agree
        lines += ["Evaluated once, so their rows repeat the other's numbers: " + "; ".join(copies) + ".", ""]
    if reference is not None:
        lines += [f"Reference: {reference['label']}: MAE {reference['mae']:.2f} deg, median {reference['median']:.2f} deg, "
                  f"invalid {100 * reference['invalid_fraction']:.1f}% of the pixels, capture {reference['capture_seconds']:.1f} s, "
                  f"compute {_seconds(reference['reconstruct_seconds'])} s per scene. It is no upper bound: Woodham least squares "
                  "fits one Lambertian model to every lit image, specular highlights included (it drops only dark, shadowed and "
                  "saturated captures)" + _reference_flags(results)
                  + ".", ""]
    lines += ["Median angular error (deg):", "", pivot("median", 2), "",
              "Capture time (s: M x exposure time, scaled by each method's exposure gain as stated above):", "", pivot("capture_seconds", 2), "",
              "Compute time (s per scene: the reconstruction, as stated above):", "", pivot("reconstruct_seconds", None), ""]
    for count in counts:
        at_m = [row for row in rows if row["M"] == count]
        if not at_m:
            continue
        body = [[row["label"], row["kind"], _fmt(row["mae"]), _fmt(row["median"]), _fmt(100 * row["under_10"], 1), _fmt(100 * row["invalid_fraction"], 1),
                 _fmt(row["capture_seconds"], 2), _seconds(row["reconstruct_seconds"]), _fmt(row["exposure"], 3), _fmt(row["cost_seconds"], 0)] for row in at_m]
        lines += [f"### M = {count}", "", _table(["method", "kind", "MAE (deg)", "median (deg)", "< 10 deg (%)", "invalid (%)", "capture (s)",
                                                 "compute (s/scene)", "exposure", "cost (s)"], body), ""]
    return lines


def _noise_section(results: dict, rows: list[dict]) -> list[str]:
    """MAE of every method at every noise scale."""
    trained = _trained_noise_text(results).strip().rstrip(".") if len(results["noise_scales"]) > 1 else ""
    note = f"; {trained[0].lower() + trained[1:]} only, so at the other levels their patterns meet a noise they were not made for" if trained else ""
    lines = ["## MAE against noise level", "", f"Mean angular error (deg) at each noise scale (x the rig's noise variances{note}):", ""]
    noises = results["noise_scales"]
    per_noise = {noise: {(row["series"], row["M"]): row for row in aggregate_rows(results, noise)} for noise in noises}
    body = []
    for row in sorted(rows, key=lambda r: (r["M"], _KIND_ORDER.get(r["kind"], 9), r["label"])):
        key = (row["series"], row["M"])
        body.append([row["label"], str(row["M"])] + [pivot_cell(per_noise[n][key], "mae", 2) if key in per_noise[n] else "-" for n in noises])
    return lines + [_table(["method", "M"] + [f"noise {n:g}" for n in noises], body), ""]


def _lowest_median(rows: list[dict], count: int, winner: dict) -> dict | None:
    """The row with the lowest median error at M = ``count`` among the compared methods (learned,
    re-rendering, heuristic, searched, external; all-invalid rows left out) when its median is
    below ``winner``'s (the lowest-MAE row) by more than ``TIE_MARGIN``; None otherwise."""
    candidates = [row for row in rows if row["M"] == count and row["kind"] in ("learned", "rerender", "heuristic", "search", "external")
                  and not all_invalid(row) and math.isfinite(row["median"])]
    if not candidates or not math.isfinite(winner["median"]):
        return None
    best = min(candidates, key=lambda row: row["median"])
    return best if best["median"] < (1 - TIE_MARGIN) * winner["median"] else None


def _summary_name(row: dict) -> str:
    """A row's name in the summary: 'learned patterns' for the learned series (every seed's label
    is 'learned'), else its label."""
    return "learned patterns" if row["kind"] == "learned" else row["label"]


def summary_section(results: dict, summary: dict) -> list[str]:
    """The answer first: per M at the default noise, the method of lowest MAE and its capture time
    (and the one of lowest median where that is clearly lower),
    the learned patterns against the best heuristic family with the test scenes each wins, and how
    much of the evidence there is (scenes, learning seeds, noise draws)."""
    rows, default = summary["rows"], results["default_noise"]
    best = lowest_mae_per_m(rows, ("learned", "rerender", "heuristic", "search", "external"))
    comparisons = {c["M"]: c for c in summary["learned_vs_heuristic"] if math.isclose(c["noise_scale"], default)}
    learned_rows = learned_rows_per_m(rows)
    lines = ["## Summary", "", f"At noise scale {default:g} (lower MAE is better):", ""]
    for count in results["pattern_counts"]:
        if count not in best:
            ran = any(row["M"] == count and row["kind"] != "reference" for row in rows)
            lines.append(f"- M = {count}: " + ("every method leaves every pixel invalid (see the tables)." if ran else "no method ran at this M."))
            continue
        winner = best[count]
        name = _summary_name(winner)
        text = f"- M = {count}: lowest mean error: {name}, MAE {winner['mae']:.2f} deg (capture {winner['capture_seconds']:.2f} s)"
        by_median = _lowest_median(rows, count, winner)
        if by_median is not None:
            text += f"; lowest median: {_summary_name(by_median)}, {by_median['median']:.2f} deg against {winner['median']:.2f}"
            if by_median["invalid_fraction"] > winner["invalid_fraction"]:
                text += (f" (invalid pixels {100 * by_median['invalid_fraction']:.1f}% against {100 * winner['invalid_fraction']:.1f}%: "
                         "the mean counts them at the placeholder normal, the median hardly)")
        if count in learned_rows and all_invalid(learned_rows[count]):
            text += "; the learned patterns leave every pixel invalid"
        elif count in comparisons:
            c = comparisons[count]
            wins, scenes = _scene_wins(results, count, c["best_heuristic"], default)
            learned = "" if winner["kind"] == "learned" else f"; learned {c['learned_mae']:.2f} deg"
            text += (f"{learned}; best heuristic family {c['best_heuristic']} {c['best_heuristic_mae']:.2f} deg; learned / heuristic "
                     f"{c['ratio']:.3f}" + (f", learned better on {wins} of {scenes} test scenes" if scenes else ""))
        lines.append(text + ".")
    seeds = {count: row["seeds"] for count, row in learned_rows.items()}  # aggregate_rows counts them
    learning = ""
    if seeds:
        counts = sorted(set(seeds.values()))
        if len(counts) == 1:
            where = "every M" if set(seeds) == set(results["pattern_counts"]) else "M = " + ", ".join(map(str, sorted(seeds)))
            per_m = f"{counts[0]} learning seed{'s' if counts[0] > 1 else ''} at {where}"
        else:
            per_m = "learning seeds " + ", ".join(f"{seeds[count]} at M = {count}" for count in sorted(seeds))
        learning = f", learned patterns from {per_m}" + ("" if max(counts) > 1 else " (no seed spread measured)")
    lines += ["", f"Evidence: {len(results['test_scenes'])} test scenes, one noise draw per scene and method (the same draws for "
              f"every method){learning}. A pixel the solver flags invalid (too dark, too few or too similar captures, a fit that "
              "faces away from the camera, or a point behind the camera or on a superpixel) counts in the MAE with the placeholder normal (0, 0, -1), facing the camera; the invalid "
              "share is in the tables below. Ratios are learned / other MAE: below 1, learned is better.", ""]
    return lines


def _scene_maes(results: dict, count: int | None, noise: float, kind: str, series: str | None = None) -> list[tuple[float, float] | None]:
    """Per test scene, in ``results["test_scenes"]`` order (positions, not names: two files may
    carry one scene name): (MAE, invalid share) of the ``kind`` methods (of ``series``, if given)
    at M = ``count`` (any M if None) and ``noise``, the mean MAE over seeds where several methods
    match (learned seeds) and the least invalid share of them; None where none has
    the scene."""
    values: list[list] = [[] for _ in results["test_scenes"]]
    for method in results["methods"]:
        if method["kind"] == kind and (count is None or method["M"] == count) and (series is None or method["series"] == series):
            evaluation = _evaluation(method, noise)
            for position, scene in enumerate((evaluation or {}).get("scenes", [])[: len(values)]):
                values[position].append((scene["mae"], scene.get("invalid_fraction", 0.0)))
    return [(float(np.mean([mae for mae, _ in entries])), min(invalid for _, invalid in entries)) if entries else None for entries in values]


def _scene_wins(results: dict, count: int, heuristic: str, noise: float) -> tuple[int, int]:
    """(test scenes where the learned patterns' mean MAE over seeds beats ``heuristic``'s, scenes
    compared) at M = ``count`` and ``noise``."""
    learned, other = _scene_maes(results, count, noise, "learned"), _scene_maes(results, count, noise, "heuristic", heuristic)
    shared = [(mine, theirs) for mine, theirs in zip(learned, other) if mine is not None and theirs is not None]
    return sum(mine[0] < theirs[0] for mine, theirs in shared), len(shared)


def scene_section(results: dict, summary: dict) -> list[str]:
    """Per test scene at the default noise: the learned patterns' MAE and, at each M with learned
    patterns, the best heuristic family's (the family best over all scenes), and the OLAT
    reference's, so that a reader sees on which objects and materials every method fails."""
    default = results["default_noise"]
    best = {c["M"]: c["best_heuristic"] for c in summary["learned_vs_heuristic"] if math.isclose(c["noise_scale"], default)}
    columns = []
    for count in results["pattern_counts"]:
        columns.append((f"learned, M = {count}", _scene_maes(results, count, default, "learned")))
        if count in best:
            columns.append((f"{best[count]}, M = {count}", _scene_maes(results, count, default, "heuristic", best[count])))
    reference = next((m for m in results["methods"] if m["kind"] == "reference"), None)
    if reference is not None:
        columns.append((reference["label"], _scene_maes(results, None, default, "reference")))
    columns = [(name, maes) for name, maes in columns if any(entry is not None for entry in maes)]
    if not columns:
        return []

    def cell(entry) -> str:
        return "-" if entry is None else _fmt(entry[0]) + invalid_note(entry[1])

    body = [[scene] + [cell(maes[position]) for _, maes in columns] for position, scene in enumerate(results["test_scenes"])]
    return ["## Per test scene", "",
            f"MAE (deg) of each test scene at noise scale {default:g}: the learned patterns (mean over seeds) and the heuristic "
            "family with the lowest MAE over all scenes at that M. The scene names give the shape and the material: where "
            "every method's error is high, the scene is beyond what the Lambertian reconstructor can fit. '(all invalid)' "
            "(or '(99.9% invalid)'): every pixel (or nearly every) was flagged invalid, and the number measures the placeholder normal.", "",
            _table(["scene"] + [name for name, _ in columns], body), ""]


def _advantage_section(summary: dict, counts: list[int]) -> list[str]:
    """Learned MAE over the best heuristic's at every M and noise, and its trend with noise."""
    comparisons = summary["learned_vs_heuristic"]
    if not comparisons:
        return []
    lines = ["## How the advantage of learned patterns changes with noise", "",
             "Ratio = learned MAE / best heuristic MAE (< 1: learned is better). Best heuristic: the family with the lowest MAE at "
             "its default parameters at that M and noise; 'tuned' also counts the NLopt-searched families ('-' where no search ran at that M).", ""]
    def failed(c):
        return c.get("learned_all_invalid", False)

    body = [[str(c["M"]), f"{c['noise_scale']:g}", _fmt(c["learned_mae"]) + (" (all invalid)" if failed(c) else ""),
             f"{c['best_heuristic']} ({_fmt(c['best_heuristic_mae'])})", "-" if failed(c) else _fmt(c["ratio"], 3),
             "-" if c["best_tuned"] is None else f"{c['best_tuned']} ({_fmt(c['best_tuned_mae'])})",
             "-" if failed(c) else _fmt(c["ratio_tuned"], 3)] for c in comparisons]
    lines += [_table(["M", "noise", "learned MAE", "best heuristic (MAE)", "ratio", "best tuned (MAE)", "ratio (tuned)"], body), ""]
    for count in counts:
        at_m = sorted((c for c in comparisons if c["M"] == count), key=lambda c: c["noise_scale"])
        if len(at_m) > 1:
            trend = " -> ".join(f"{'every pixel invalid' if failed(c) else format(c['ratio'], '.3f')} (noise {c['noise_scale']:g})" for c in at_m)
            failures = [f"{c['noise_scale']:g}" for c in at_m if failed(c)]
            verdict = (f"the learned patterns leave every pixel invalid at noise {', '.join(failures)}" if failures
                       else f"{noise_verdict(at_m[0]['ratio'], at_m[-1]['ratio'])} as the noise rises")
            lines.append(f"- M = {count}: ratio {trend}; {verdict}.")
    return lines + [""]


def _more_captures_section(summary: dict, default: float) -> list[str]:
    """Learned patterns at M against the best heuristic at a larger M."""
    more_captures = summary.get("learned_vs_more_captures") or []
    if not more_captures:
        return []
    lines = [f"## Fewer captures for the same accuracy? (noise scale {default:g})", "",
             "Learned patterns at M against the best heuristic family at a larger M (ratio <= 1: the learned set matches "
             "it with fewer captures):", ""]
    body = [[str(c["M"]), _fmt(c["learned_mae"]), str(c["heuristic_M"]), f"{c['best_heuristic']} ({_fmt(c['best_heuristic_mae'])})",
             _fmt(c["ratio"], 3), "yes" if c["ratio"] <= 1 else "no"] for c in more_captures]
    return lines + [_table(["learned M", "learned MAE", "heuristic M", "best heuristic (MAE)", "ratio", "matched"], body), ""]


def _seed_section(summary: dict) -> list[str]:
    """Test MAE spread of patterns learned with different seeds."""
    if not summary["seed_spread"]:
        return []
    lines = ["## Seed spread of learned patterns", "", "Test MAE (deg) of patterns learned with different seeds (same config otherwise):", ""]
    body = [[str(s["M"]), f"{s['noise_scale']:g}", ", ".join(map(str, s["seeds"])), _fmt(s["mean"]), _fmt(s["std"]), _fmt(s["min"]), _fmt(s["max"])]
            for s in summary["seed_spread"]]
    return lines + [_table(["M", "noise", "seeds", "mean", "std", "min", "max"], body), ""]


def _rerender_section(summary: dict) -> list[str]:
    """Normal-only learning against learning with the re-rendering loss."""
    if not summary.get("rerender"):
        return []
    lines = ["## Learning through the renderer: normal-only against normal + re-rendering loss", "",
             "Test MAE (deg) of patterns learned with the normal loss only and with the re-rendering loss added "
             "(the analytic estimate rendered under the patterns against the simulated captures; same seed and steps). "
             "Ratio < 1: the re-rendering loss helps.", ""]
    body = [[str(r["M"]), f"{r['noise_scale']:g}", str(r["seed"]), _fmt(r["weight"], 3) if r["weight"] is not None else "-",
             _fmt(r["normal_only_mae"]), _fmt(r["rerender_mae"]), _fmt(r["ratio"], 3)] for r in summary["rerender"]]
    return lines + [_table(["M", "noise", "seed", "weight", "normal only", "normal + re-rendering", "ratio"], body), ""]


def _search_section(results: dict, out_dir: Path) -> list[str]:
    """NLopt searches: their training objective from start to best, test MAE, cost and trace chart."""
    searches = [m for m in results["methods"] if m["kind"] == "search"]
    if not searches:
        return []
    lines = ["## NLopt searches", "", "Training-scene objective (fixed pixel subset and noise draw), then test MAE at the default noise. "
             "The start is the family's parameters of preset default (levels 0 and 1 where it has levels) with its edges softened to the "
             "search's sharpness (so that they get gradients), which can score worse than the family's binary patterns in the tables above."
             + (" LN_BOBYQA spends its first 2 P + 1 evaluations (P parameters) on points around the start before it steps (its trace "
                "chart marks where they end)."
                if any(method.get("series", "").endswith(":LN_BOBYQA") for method in searches) else ""), ""]
    body = []
    for method in searches:
        info = method["info"]
        test = _evaluation(method, results["default_noise"])
        trace = Path(info["trace_png"])  # relative to the output folder when inside it (``compare.method_record``)
        if not trace.is_absolute() and not (out_dir / trace).exists() and trace.exists():
            trace = trace.resolve()  # results of older versions: relative to the working directory
        if trace.is_absolute():
            try:
                trace = trace.resolve().relative_to(out_dir.resolve())
            except ValueError:
                pass
        body.append([method["label"], str(method["M"]), str(info.get("parameters", "-")), str(info["evaluations"]), _fmt(info["start_mae"]), _fmt(info["best_mae"]),
                     _fmt(test["mae"]) if test else "-", _fmt(method["cost_seconds"], 0), info["stop_reason"], f"[trace]({trace.as_posix()})"])
    return lines + [_table(["search", "M", "parameters P", "evaluations", "start (train)", "best (train)", "test MAE", "cost (s)", "stop", "chart"], body), ""]
