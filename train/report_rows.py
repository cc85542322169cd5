"""Rows of the comparison: ``run_compare``'s results per (series, M) and noise level, and the
summaries the report and charts are made of (best heuristic per M, learned against it).

Learned patterns with several seeds enter as their mean over seeds.
"""
from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

_ROW_METRICS = ("mae", "median", "under_10", "invalid_fraction", "exposure", "capture_seconds", "simulate_reconstruct_seconds")
"""Means over a row's seeds at one noise level (``reconstruct_seconds`` is a median: ``aggregate_rows``)."""
KIND_ORDER = {"learned": 0, "rerender": 1, "search": 2, "external": 3, "heuristic": 4, "reference": 5}
"""Order of the kinds of method in tables, charts and legends."""


def test_scenes_text(results: dict) -> str:
    """'4 test scenes' ('1 test scene') for the scenes of ``results``."""
    count = len(results["test_scenes"])
    return f"{count} test scene{'' if count == 1 else 's'}"


def seed_std(values) -> float:
    """Sample standard deviation (n - 1 in the denominator) of a few seeds' values; 0 for one."""
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def evaluation_at(method: dict, noise: float) -> dict | None:
    """A method's evaluation at noise scale ``noise`` (a results entry), or None if it has none."""
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
        median, under_10, invalid_fraction, exposure, capture_seconds, simulate_reconstruct_seconds, the median
        reconstruct_seconds over the methods' evaluations at every noise level (with
        ``specular_free``: over their specular-free evaluations), plus mae_std, the sample
        standard deviation over seeds (0 for one seed); sorted by kind, then M, then MAE.
    """
    groups: dict = defaultdict(list)
    for method in results["methods"]:
        if specular_free:
            evaluation = method.get("specular_free") if math.isclose(noise, results["default_noise"]) else None
        else:
            evaluation = evaluation_at(method, noise)
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
        timed = [evaluation for _, evaluation in members] if specular_free else [e for method, _ in members for e in method["evaluations"]]
        times = [evaluation.get("reconstruct_seconds", math.nan) for evaluation in timed]
        row["reconstruct_seconds"] = float(np.median(times)) if times else math.nan
        row["mae_std"] = seed_std([evaluation["mae"] for _, evaluation in members])
        costs = [method["cost_seconds"] for method, _ in members if method["cost_seconds"] is not None]
        row["cost_seconds"] = float(np.mean(costs)) if costs else None
        rows.append(row)
    rows.sort(key=lambda r: (KIND_ORDER.get(r["kind"], 9), r["M"], r["mae"]))
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
            evaluation = evaluation_at(method, noise)
            if method["kind"] == "learned" and evaluation is not None:
                by_m[method["M"]].append((method["seed"], evaluation["mae"]))
        learned_by_key = {(method["M"], method["seed"]): method for method in results["methods"] if method["kind"] == "learned"}
        for method in results["methods"]:
            normal_only = learned_by_key.get((method["M"], method["seed"]))
            if method["kind"] != "rerender" or normal_only is None:
                continue
            with_rerender, without = evaluation_at(method, noise), evaluation_at(normal_only, noise)
            # An all-invalid side measures the placeholder normal: no comparison to make.
            if with_rerender is not None and without is not None and not (all_invalid(with_rerender) or all_invalid(without)):
                rerender.append({"M": method["M"], "noise_scale": noise, "seed": method["seed"], "weight": method["info"].get("rerender_weight"),
                                 "normal_only_mae": without["mae"], "rerender_mae": with_rerender["mae"],
                                 "ratio": with_rerender["mae"] / max(without["mae"], 1e-12)})
        for count, values in sorted(by_m.items()):
            if len(values) > 1:
                maes = np.array([mae for _, mae in values])
                spread.append({"M": count, "noise_scale": noise, "seeds": [seed for seed, _ in values], "maes": maes.tolist(),
                               "mean": float(maes.mean()), "std": seed_std(maes), "min": float(maes.min()), "max": float(maes.max())})
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


NEARLY_ALL_INVALID = 0.99
"""Share of invalid pixels from which a method's MAE (nearly) only measures the placeholder normal
of invalid pixels: the report's tables mark such errors and the charts draw them as failures."""


def placeholder_error(row: dict) -> bool:
    """Whether at least ``NEARLY_ALL_INVALID`` of a method's pixels were invalid, so that its MAE
    is (nearly) that of the placeholder normal, the same for every such method."""
    return row.get("invalid_fraction", 0.0) >= NEARLY_ALL_INVALID


def all_invalid(row: dict) -> bool:
    """Whether every pixel of a method's evaluation was flagged invalid: its MAE measures the
    placeholder normal, not a reconstruction."""
    return row.get("invalid_fraction", 0.0) >= 1.0
