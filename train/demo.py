"""`displex demo`: the main job on the embedded default, end to end.

Synthesises the default scene set, learns M = 2 and M = 4 patterns on its training split, searches
one heuristic family's parameters with NLopt, evaluates them on the held-out split against every
heuristic family and the published learned patterns at three noise levels, and writes ``results.json``, ``report.md`` and charts.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import write_json, write_text
from capture_sim.rig import DEFAULT_RIG, load_rig
from capture_sim.scene import load_scene, scene_paths
from capture_sim.synth import write_scene_set
from patterns.families import FAMILIES, get_family, make_patterns
from patterns.io import load_patterns, save_patterns
from reconstruct.photometric_stereo import PSConfig
from train.evaluate import EvalSettings, evaluate_scene
from train.figures import save_figure
from train.learn import TrainConfig, train_patterns
from train.nlopt_search import SearchConfig, run_search
from train.scene_pixels import scene_pixels

PUBLISHED_DIR = Path(__file__).resolve().parent.parent / "patterns" / "data" / "ddps"
SECONDS_PER_IMAGE = 0.44
"""Capture time of one image on the reference rig (440 ms exposure, DESIGN section 8)."""


@dataclass(frozen=True)
class DemoConfig:
    """What `displex demo` runs."""

    pattern_counts: tuple[int, ...] = (2, 4)
    """M values to learn and compare."""
    noise_scales: tuple[float, ...] = (0.25, 1.0, 4.0)
    """Multipliers of the rig's noise variances to evaluate at (1 = the rig's default)."""
    train_steps: int = 150
    """Learning steps per learned pattern set."""
    size: tuple[int, int] = (128, 153)
    """Image size of the synthetic scenes."""
    seed: int = 0
    """Seed of scenes, learning and noise."""
    rig: str = DEFAULT_RIG
    """Rig preset."""
    families: tuple[str, ...] = tuple(FAMILIES)
    """Heuristic families to compare (each at every M it supports)."""
    search_family: str = "tri_complementary"
    """Family searched with NLopt (LN_BOBYQA) at the smallest M; '' skips the search."""
    search_evaluations: int = 20
    """Objective evaluations of that search."""


DEMO_SOLVER = PSConfig(restart_condition=math.inf, max_shadow_iterations=6)
"""The demo evaluates ~20 pattern sets at three noise levels: it skips the solver's multi-start
search for doubtful pixels (3-10x faster on rank-deficient sets, same results on well-posed ones)."""


def _evaluate_method(name, patterns, scenes, noise_scales, seed):
    """Mean metrics over scenes for every noise level: {noise: {mae, median, seconds, exposure}}."""
    by_noise = {}
    for noise in noise_scales:
        settings = EvalSettings(noise_scale=noise, seed=seed, ps=DEMO_SOLVER)
        rows = [evaluate_scene(pixels, patterns, settings, index).metrics for index, pixels in enumerate(scenes)]
        by_noise[str(noise)] = {key: float(np.mean([row[key] for row in rows])) for key in ("mae", "median", "under_10", "invalid_fraction", "seconds", "exposure")}
    return by_noise


def run_demo(out: Path, config: DemoConfig = DemoConfig(), progress: bool = True) -> dict:
    """Run the main job into ``out``; returns the results document."""
    out = Path(out)
    rig = load_rig(config.rig)
    scene_dir = out / "scenes"
    if not (scene_dir / "index.json").exists():
        write_scene_set(scene_dir, rig, height=config.size[0], width=config.size[1], seed=config.seed, progress=progress)
    test_scenes = [scene_pixels(load_scene(path), rig, require_normals=True) for path in scene_paths([scene_dir / "test"])]
    methods: dict[str, dict] = {}
    pattern_sets: dict[str, np.ndarray] = {}
    costs: dict[str, float] = {}
    for count in config.pattern_counts:
        start = time.perf_counter()
        train_config = TrainConfig(num_patterns=count, steps=config.train_steps, scenes=(str(scene_dir / "train"),), val_scenes=(str(scene_dir / "test"),), seed=config.seed, val_every=0)
        learned = train_patterns(train_config, out / "patterns" / f"learned_M{count}.npz", logdir=out / "tensorboard" / f"learned_M{count}", progress=progress)
        pattern_sets[f"learned M={count}"] = learned.patterns
        costs[f"learned M={count}"] = time.perf_counter() - start
        for family in config.families:
            if get_family(family).supports(count, rig.rows, rig.cols):
                pattern_sets[f"{family} M={count}"] = make_patterns(family, count, rows=rig.rows, cols=rig.cols, seed=config.seed).numpy()
        published = PUBLISHED_DIR / f"optimized_tri_random_{count}.npy"
        if published.exists():
            pattern_sets[f"published learned M={count}"] = load_patterns(published)[0]
    if config.search_family:
        count = min(config.pattern_counts)
        start = time.perf_counter()
        search_config = SearchConfig(config.search_family, count, "LN_BOBYQA", maxeval=config.search_evaluations, seed=config.seed, scenes=(str(scene_dir / "train"),), rig=config.rig)
        searched = out / "patterns" / f"searched_{config.search_family}_M{count}.npz"
        run_search(search_config, searched, progress=progress)
        pattern_sets[f"searched {config.search_family} M={count}"] = load_patterns(searched)[0]
        costs[f"searched {config.search_family} M={count}"] = time.perf_counter() - start
    for name, values in tqdm(pattern_sets.items(), desc="evaluating methods", disable=not progress, unit="method"):
        methods[name] = {"M": int(values.shape[0]), "kind": _kind(name), "by_noise": _evaluate_method(name, torch.as_tensor(values), test_scenes, config.noise_scales, config.seed)}
    document = {
        "config": {k: list(v) if isinstance(v, tuple) else v for k, v in config.__dict__.items()},
        "test_scenes": [pixels.name for pixels in test_scenes],
        "methods": methods,
        "learning_seconds": costs,
        "seconds_per_image": SECONDS_PER_IMAGE,
    }
    write_json(out / "results.json", document)
    _charts(out, document, pattern_sets)
    write_text(out / "report.md", _report(document))
    return document


def _kind(name: str) -> str:
    if name.startswith("learned"):
        return "learned"
    if name.startswith("searched"):
        return "searched"
    if name.startswith("published"):
        return "published"
    return "heuristic"


def _best(document, kind, count, noise):
    rows = [(m["by_noise"][noise]["mae"], name) for name, m in document["methods"].items() if m["kind"] == kind and m["M"] == count]
    return min(rows) if rows else (float("nan"), "-")


def _report(document) -> str:
    noises = [str(n) for n in document["config"]["noise_scales"]]
    default = "1.0" if "1.0" in noises else noises[0]
    lines = [
        "# displex demo: learned against heuristic patterns",
        "",
        f"Held-out scenes: {', '.join(document['test_scenes'])}. Analytic photometric stereo, auto exposure per "
        f"scene; capture time = M x {document['seconds_per_image']} s; compute time = mean reconstruction wall "
        "seconds per scene on this machine. MAE in degrees over each scene's mask, averaged over scenes.",
        "",
        f"## Methods at the default noise (scale {default})",
        "",
        "| method | M | MAE (deg) | median (deg) | < 10 deg | capture (s) | compute (s) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, method in sorted(document["methods"].items(), key=lambda item: (item[1]["M"], item[1]["by_noise"][default]["mae"])):
        row = method["by_noise"][default]
        lines.append(f"| {name} | {method['M']} | {row['mae']:.2f} | {row['median']:.2f} | {row['under_10']:.2f} | {method['M'] * document['seconds_per_image']:.2f} | {row['seconds']:.3f} |")
    lines += ["", "## Learned against the best heuristic, by noise level", "", "| M | noise | learned MAE | best heuristic | heuristic MAE | ratio |", "| --- | --- | --- | --- | --- | --- |"]
    for count in document["config"]["pattern_counts"]:
        for noise in noises:
            learned, _ = _best(document, "learned", count, noise)
            heuristic, name = _best(document, "heuristic", count, noise)
            lines.append(f"| {count} | {noise} | {learned:.2f} | {name} | {heuristic:.2f} | {learned / heuristic:.2f} |")
    lines += ["", "Learning and search time (s): " + ", ".join(f"{k}: {v:.0f}" for k, v in document["learning_seconds"].items()), ""]
    lines += ["## Charts", "", "![MAE against M](mae_vs_m.png)", "", "![MAE against capture time](mae_vs_capture_time.png)", "",
              "![MAE against compute time](mae_vs_compute_time.png)", "", "![MAE against noise](mae_vs_noise.png)", "", "![Patterns](patterns.png)", ""]
    return "\n".join(lines)


def _charts(out: Path, document, pattern_sets) -> None:
    import matplotlib.pyplot as plt

    noises = [str(n) for n in document["config"]["noise_scales"]]
    default = "1.0" if "1.0" in noises else noises[0]
    methods = document["methods"]
    families = sorted({name.rsplit(" M=", 1)[0] for name in methods})
    markers = {"learned": "o", "published": "s", "heuristic": "x", "searched": "^"}
    for key, xlabel, filename, title in (
        ("M", "number of patterns M", "mae_vs_m.png", "Normal error against pattern count"),
        ("capture", "capture time (s) = M x exposure", "mae_vs_capture_time.png", "Accuracy against capture time"),
        ("compute", "reconstruction time per scene (s)", "mae_vs_compute_time.png", "Accuracy against compute time"),
    ):
        fig, ax = plt.subplots(figsize=(7, 4.5))
        for family in families:
            points = sorted(
                (m["M"] if key == "M" else m["M"] * document["seconds_per_image"] if key == "capture" else m["by_noise"][default]["seconds"], m["by_noise"][default]["mae"], m["kind"])
                for name, m in methods.items()
                if name.rsplit(" M=", 1)[0] == family
            )
            ax.plot([p[0] for p in points], [p[1] for p in points], marker=markers[points[0][2]], label=family, linewidth=2.2 if points[0][2] == "learned" else 1.0)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean angular error (deg)")
        ax.set_title(title)
        ax.legend(fontsize=7, ncol=2)
        fig.text(0.5, 0.005, f"Held-out synthetic scenes, noise scale {default}, auto exposure; lower is better.", ha="center", fontsize=8)
        save_figure(fig, out / filename)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, method in methods.items():
        if method["kind"] != "heuristic" or name.startswith(("olat", "grouped", "mono_random", "gray", "tri_random", "mono_complementary")):
            ax.plot([float(n) for n in noises], [method["by_noise"][n]["mae"] for n in noises], marker=markers[method["kind"]], label=name)
    ax.set_xscale("log")
    ax.set_xlabel("noise scale (x the rig's noise variance)")
    ax.set_ylabel("mean angular error (deg)")
    ax.set_title("Where methods fail: error against noise level")
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, out / "mae_vs_noise.png")
    shown = [name for name in pattern_sets if not name.startswith(("mono_random", "gray_noise", "olat", "grouped"))]
    rows = len(shown)
    columns = max(values.shape[0] for values in pattern_sets.values())
    fig, axes = plt.subplots(rows, columns, figsize=(1.6 * columns, 1.0 * rows + 0.5), squeeze=False)
    for ax in axes.ravel():
        ax.set_axis_off()
    for row, name in enumerate(shown):
        for index, pattern in enumerate(pattern_sets[name]):
            axes[row, index].imshow(np.clip(pattern, 0, 1), interpolation="nearest")
        axes[row, 0].set_title(name, fontsize=7, loc="left")
    fig.suptitle("Pattern sets (display set values, row 0 at the top of the panel)")
    save_figure(fig, out / "patterns.png")
