"""The comparison report: ``report.md`` from ``run_compare``'s results, with the charts of
``train.report_charts``.

Everything here reads the results dict only (plus the pattern arrays for the pattern figure), so a
report can be rebuilt from ``results.json``. Learned patterns with several seeds enter tables and
charts as their mean over seeds; the seed spread has its own table.
"""
from __future__ import annotations

import math
import os
from collections import defaultdict
from pathlib import Path

import numpy as np

from capture_sim.atomic import write_text
from patterns.families import FAMILIES, PRESET_LEVELS
from reconstruct.photometric_stereo import INVALIDATING_FLAGS
from train.report_charts import CHARTS, write_charts
from train.report_rows import (KIND_ORDER, NEARLY_ALL_INVALID, aggregate_rows, all_invalid, evaluation_at, learned_rows_per_m, lowest_mae_per_m,
                               summary_tables, test_scenes_text)


def invalid_note(fraction: float) -> str:
    """' (all invalid)' or ' (99.99% invalid)' after an error that (nearly) only measures the
    placeholder normal (at least ``NEARLY_ALL_INVALID`` of the pixels invalid); '' otherwise."""
    if fraction >= 1.0:
        return " (all invalid)"
    # Rounded to float32's precision first (0.9999 is 0.99989998), then down, never up to 100%.
    return f" ({min(math.floor(round(fraction * 1e4, 3)) / 100, 99.99):g}% invalid)" if fraction >= NEARLY_ALL_INVALID else ""




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
    threads = f"{results['threads']} thread{'s' if results['threads'] != 1 else ''}" if "threads" in results else "this process's threads"
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
    evaluation = None if method is None else evaluation_at(method, results["default_noise"])
    share = ((evaluation or {}).get("flagged") or {}).get("poor_fit", 0.0)
    return f" (a poor fit on {100 * share:.3g}% of the pixels)" if share > 0 else ""


def scene_labels(results: dict) -> list[str]:
    """The test scenes' names, in ``results["test_scenes"]`` order, each name that several scenes
    carry (scene sets of other seeds reuse the names) followed by its file: the file name, or the
    whole path where the file names repeat too."""
    names = results["test_scenes"]
    files = results.get("test_scene_files") or [None] * len(names)
    labels = []
    for name, file in zip(names, files):
        if names.count(name) == 1 or not file:
            labels.append(name)
            continue
        short = Path(file).name
        twins = [Path(other).name for other_name, other in zip(names, files) if other_name == name and other]
        labels.append(f"{name} ({short if twins.count(short) == 1 else file})")
    return labels


def _held_out_text(results: dict) -> str:
    """'4 held-out test scenes', or '4 test scenes (2 of them also used for learning or searches,
    so not held out: a.npz, b.npz)' where the config listed test scene files among the training
    scenes."""
    scenes, shared = test_scenes_text(results), results.get("test_files_also_trained") or []
    if not shared:
        return scenes.replace(" test ", " held-out test ", 1)
    return f"{scenes} ({len(shared)} of them also used for learning or searches, so not held out: {', '.join(shared)})"


def _measurement_caption(results: dict) -> str:
    reference = any(method["kind"] == "reference" for method in results["methods"])
    return (
        f"Measured on {_held_out_text(results)}{_sizes_text(results)} ({results['test_pixels']} masked pixels in all; "
        f"{', '.join(scene_labels(results))}), rig {results['rig']} ({results['grid'][0]} x {results['grid'][1]} superpixels). "
        "Captures are simulated from the OLAT stacks (display gamma and backlight, Poisson-Gaussian noise at the given scale "
        "times the rig's noise variances, clipping, quantisation) with auto exposure per scene, then reconstructed with the "
        f"analytic photometric stereo{_solver_text(results)}{' (the OLAT reference: Woodham least squares on all K images)' if reference else ''}. "
        f"MAE and median are angular normal errors in degrees over {_pixels_text(results)}, averaged over scenes (each scene "
        f"weighs the same). {_capture_text(results, reference)} Compute time = wall seconds per scene of the reconstruction "
        f"of {_pixels_short(results)} on this machine's CPU (the simulation of the captures, which the rig's camera replaces, "
        f"is left out){_timing_text(results)}, the median over the method's evaluations at every noise level; only "
        f"differences of 2x or more are beyond the noise of such timings. Exposure = mean auto-exposure gain.{_cost_text(results)}"
        f"{_trained_noise_text(results)} {_learning_text(results)}"
        f"{_preset_text(results)}"
    )


def _cost_text(results: dict) -> str:
    """What the cost column measures, for the kinds of run the comparison made (none: nothing)."""
    kinds = {method["kind"] for method in results["methods"]}
    kinds |= {"learned"} if "rerender" in kinds else set()  # re-rendering runs are learning runs too
    runs = [text for kind, text in (("learned", "a learning run (its steps see the training scenes only; the time includes loading the "
                                                 "held-out scenes and validating on them)"), ("search", "a search")) if kind in kinds]
    return f" Cost = wall seconds of {' or of '.join(runs)}." if runs else ""


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
        evaluation = evaluation_at(method, default)
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
    where = ", ".join(os.path.normpath(scene) for scene in scenes) if scenes else "the default synthetic training split"  # no "cfg/../sc"
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
    for row in sorted(rows, key=lambda r: (r["M"], KIND_ORDER.get(r["kind"], 9), r["label"])):
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
    written = write_charts(results, summary, pattern_sets, into, _pixels_short(results))
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
    ordered = sorted(series_rows, key=lambda s: (KIND_ORDER.get(labels[s][0], 9), labels[s][1]))
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
    for row in sorted(rows, key=lambda r: (r["M"], KIND_ORDER.get(r["kind"], 9), r["label"])):
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
            per_m = ", ".join(f"{seeds[count]} learning seed{'s' if seeds[count] > 1 else ''} at M = {count}" for count in sorted(seeds))
        learning = f", learned patterns from {per_m}" + ("" if max(counts) > 1 else " (no seed spread measured)")
    lines += ["", f"Evidence: {test_scenes_text(results)}, one noise draw per scene and method (the same draws for "
              f"every method){learning}. A pixel the solver flags invalid (too dark, too few or too similar captures, a fit that "
              "faces away from the camera, or a point behind the camera or on a superpixel) counts in the MAE with the placeholder normal (0, 0, -1), facing the camera; the invalid "
              "share is in the tables below." + (" Ratios are learned / other MAE: below 1, learned is better." if learned_rows else ""), ""]
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
            evaluation = evaluation_at(method, noise)
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

    body = [[scene] + [cell(maes[position]) for _, maes in columns] for position, scene in enumerate(scene_labels(results))]
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
    lines = ["## Seed spread of learned patterns", "", "Test MAE (deg) of patterns learned with different seeds (same config otherwise); std: the sample standard deviation over the seeds:", ""]
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
        test = evaluation_at(method, results["default_noise"])
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
