"""`displex evaluate`: reconstruct scenes under a pattern set and report normal errors."""
from __future__ import annotations

import contextlib
import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import refuse_overwriting, save_npy, separate_json, staged_files, write_json
from capture_sim.errors import DisplexWarning, InputError
from capture_sim.rig import DEFAULT_RIG, load_rig, rig_file
from capture_sim.scene import rig_for_scene
from patterns.io import check_patterns_match_rig, load_patterns
from reconstruct.photometric_stereo import invalid_causes
from train.evaluate import EvalSettings, error_map, evaluate_scene, masked_map
from train.figures import ERROR_MAP_MAX_DEG, image_grid, normal_panel, save_figure
from train.scene_pixels import require_ground_truth, scene_pixels
from train.scene_sets import resolve_scenes
from train.simulate_command import parse_exposure


@dataclass(frozen=True)
class EvaluateConfig:
    """What `displex evaluate` does."""

    scenes: tuple[Path, ...]
    """Scene files or folders of .npz; empty = the default synthetic test split."""
    patterns: str
    """Pattern file, or 'olat' for the full OLAT stack."""
    method: str = "ps"
    """'ps' or 'woodham'."""
    noise: str = "default"
    """'default' (the rig's noise) or 'off'."""
    exposure: str = "rig"
    """'rig' (the rig's exposure setting; auto for the presets), 'auto' or a positive number."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path."""
    seed: int = 0
    """Noise seed."""
    json: Path | None = None
    """Where to write the JSON results."""
    out: Path | None = None
    """Folder for normal maps, error maps and the summary figure."""


def run_evaluate(config: EvaluateConfig, progress: bool = True) -> dict:
    """Evaluate and write outputs; returns the JSON document."""
    if config.noise not in ("off", "default"):
        raise InputError(f"--noise must be 'off' or 'default', got {config.noise!r}")
    rig = load_rig(config.rig)
    if config.patterns == "olat":
        patterns = "olat"
    else:
        values, _ = load_patterns(config.patterns)
        check_patterns_match_rig(values, rig.rows, rig.cols, rig.name, config.patterns)
        patterns = torch.as_tensor(values)
        if config.method == "woodham" and not bool((patterns == patterns[..., :1]).all()):
            warnings.warn("Woodham solves each colour channel on its own, and a colour pattern set lights each channel differently: "
                          "a channel with fewer than three independent patterns is left out (a pixel no channel determines is flagged), "
                          "and with three a wrong shadow mask can fit a channel exactly; --method ps solves the channels together",
                          DisplexWarning, stacklevel=2)
    settings = EvalSettings(method=config.method, noise_scale=0.0 if config.noise == "off" else 1.0, exposure=parse_exposure(str(config.exposure), rig), seed=config.seed)
    json_path = separate_json(config.json, config.out, "results.json")
    known_inputs = [("pattern file", None if config.patterns == "olat" else config.patterns), ("rig file", rig_file(config.rig))]
    # The outputs whose names do not depend on the scenes are checked before the scenes are read
    # (the default ones are synthesised, seconds here); the scenes' own maps are checked below.
    refuse_overwriting([("--json", json_path), *_out_files(config.out, [])], known_inputs, folders=[("--out", config.out)])
    scenes = resolve_scenes(config.scenes, "test", rig, separated=False)  # the OLAT stacks alone
    for scene in scenes:  # a later scene's refusal must not wait for the earlier scenes' solves
        require_ground_truth(scene)
        rig_for_scene(rig, scene)
    files = [Path(scene.meta.get("file", scene.name)) for scene in scenes]
    _refuse_repeated_scenes(files, config.out is not None)
    # Every output is checked before the work: none may replace an input or another output.
    refuse_overwriting([("--json", json_path), *_out_files(config.out, files)], [("scene file", file) for file in files] + known_inputs,
                       folders=[("--out", config.out)])
    with contextlib.ExitStack() as stack:
        # Files for --out are staged and land together at the end: a failure part-way (a bad
        # later scene, an unwritable --json) leaves no new maps beside an earlier run's results;
        # the maps of scenes an earlier run had and this one has not go before results.json lands.
        staging = None
        if config.out is not None:
            obsolete = sorted(set(_previous_scene_outputs(Path(config.out))) - {path for _, path in _out_files(config.out, files)})
            staging = stack.enter_context(staged_files(config.out, last=("results.json",), obsolete=obsolete))
        document = _evaluate_scenes(config, scenes, files, rig, patterns, settings, staging, progress)
        if json_path is not None:
            write_json(json_path, document)
    return document


def _previous_scene_outputs(out: Path) -> list[Path]:
    """The per-scene files of an earlier ``evaluate --out`` into ``out``: those of the scenes its
    results.json lists (only names evaluate writes itself, so a hand-edited file cannot delete
    others), and those of every scene with a complete set of them there (a run interrupted while
    its files moved in removes results.json first)."""
    try:
        files = json.loads((out / "results.json").read_text()).get("scene_files", [])
        stems = {Path(file).stem for file in files if isinstance(file, str) and Path(file).stem}
    except (OSError, ValueError, AttributeError):
        stems = set()
    first, *others = SCENE_OUTPUT_ENDINGS
    for path in out.glob(f"*{first}"):
        stem = path.name[: -len(first)]
        if stem and all((out / f"{stem}{ending}").is_file() for ending in others):
            stems.add(stem)
    return [out / f"{stem}{ending}" for stem in sorted(stems) for ending in SCENE_OUTPUT_ENDINGS]


def _out_files(out: Path | None, files: list[Path]) -> list[tuple[str, Path]]:
    """(what, path) of every file ``run_evaluate`` writes into ``out`` (none without one)."""
    if out is None:
        return []
    names = ["results.json", "summary.png"] + [f"{file.stem}{ending}" for file in files for ending in SCENE_OUTPUT_ENDINGS]
    return [("--out file", Path(out) / name) for name in names]


SCENE_OUTPUT_ENDINGS = ("_normal.npy", "_valid.npy", "_residual.npy", "_normals.png")
"""The per-scene files of ``--out``, after the scene file's stem."""


def _evaluate_scenes(config: EvaluateConfig, scenes, files, rig, patterns, settings: EvalSettings, out: Path | None, progress: bool) -> dict:
    """Evaluate every scene; with ``out``, write its maps, ``results.json`` and ``summary.png``
    there. Returns the JSON document."""
    rows, panels = [], []
    for index, (scene, file) in enumerate(zip(tqdm(scenes, desc="evaluating", unit="scene", disable=not progress), files)):
        pixels = scene_pixels(scene, rig, require_normals=True)
        evaluation = evaluate_scene(pixels, patterns, settings, index)
        rows.append(evaluation.metrics)
        if evaluation.metrics["invalid_fraction"] >= 1.0:
            # The MAE of such a scene measures the default normal, not a reconstruction.
            warnings.warn(f"every pixel of {evaluation.metrics['name']} is flagged invalid ({invalid_causes(evaluation.metrics['flagged'])}): "
                          "its MAE says nothing about the patterns", DisplexWarning, stacklevel=3)
        if out is not None:
            panels.append(_write_scene_outputs(out, file.stem, pixels, evaluation, settings.ps.residual_threshold))
    document = {
        "patterns": str(config.patterns),
        "method": config.method,
        "noise": config.noise,
        "rig": rig.name,
        "exposure": str(config.exposure),
        "seed": config.seed,
        "scene_files": [str(file) for file in files],
        "scenes": rows,
        "mean_mae": float(np.mean([row["mae"] for row in rows])),
    }
    if out is not None:
        write_json(out / "results.json", document)
        _summary_figure(out / "summary.png", panels, document)
    return document


def _refuse_repeated_scenes(files: list[Path], writes_maps: bool) -> None:
    """Refuse a scene file given twice (it would count twice in the mean, with another noise
    draw), and, if per-scene maps are written (``writes_maps``), scene files whose maps (named
    by the file stem) would overwrite each other."""
    resolved, stems = set(), set()
    for file in files:
        place = file.resolve()
        if place in resolved:
            raise InputError(f"the scene file {file} is given twice (directly or through its folder)")
        if writes_maps and file.stem in stems:
            raise InputError(f"scenes from different folders share the file name {file.stem}: their outputs in --out would overwrite each other")
        resolved.add(place)
        stems.add(file.stem)


def _write_scene_outputs(out: Path, stem: str, pixels, evaluation, residual_threshold: float) -> tuple:
    normal = pixels.transport.to_image(evaluation.result.normal[None].float(), fill=0.0)[0].numpy()
    normal[~pixels.mask] = (0.0, 0.0, -1.0)
    truth = pixels.transport.to_image(pixels.normal[None], fill=0.0)[0].numpy()
    valid = np.zeros(pixels.mask.shape, dtype=bool)
    valid[pixels.mask] = evaluation.result.valid.numpy()
    save_npy(out / f"{stem}_normal.npy", normal.astype(np.float32))
    save_npy(out / f"{stem}_valid.npy", valid)
    residual = masked_map(pixels, evaluation.result.residual)
    save_npy(out / f"{stem}_residual.npy", np.nan_to_num(residual, nan=1.0))
    errors = error_map(pixels, evaluation.result)
    estimate = normal_panel(normal, pixels.mask, valid)
    invalid = pixels.mask & ~valid
    fig = image_grid(
        [estimate, normal_panel(truth, pixels.mask), errors, residual],
        ["estimated normals (black: flagged invalid)", "ground truth", f"angular error, MAE {evaluation.metrics['mae']:.2f} deg",
         "relative fit residual"],
        f"{pixels.name}",
        "Normals shown as RGB = ((x, -y, -z) + 1) / 2 in the camera frame, white outside the mask. Error: angle to the true "
        f"normal inside the mask, colours saturate at {ERROR_MAP_MAX_DEG:g} deg; light blue: flagged invalid ({invalid.mean() / max(pixels.mask.mean(), 1e-12):.1%} "
        "of the mask), counted in the MAE with their placeholder normal. Residual: RMS misfit of the Lambertian model over the "
        f"RMS capture, a confidence the solver computes without the truth (specular light and wrong shadow masks raise it); "
        f"colours saturate at {residual_threshold:g}, above which a valid pixel is flagged poor_fit.",
        columns=4,
        cmap="magma",
        colorbar_label=[None, None, "degrees", "residual"],
        limits=[None, None, (0.0, ERROR_MAP_MAX_DEG), (0.0, residual_threshold)],
        flagged=[None, None, invalid, invalid],
    )
    save_figure(fig, out / f"{stem}_normals.png")
    return pixels.name, estimate, errors, evaluation.metrics["mae"], invalid


def _gains_text(document: dict) -> str:
    """' (gain e = 0.0062..0.041)': the exposures the scenes were captured at."""
    gains = [row["exposure"] for row in document["scenes"] if isinstance(row.get("exposure"), (int, float))]
    if not gains:
        return ""
    low, high = min(gains), max(gains)
    return f" (gain e = {low:.2g})" if math.isclose(low, high) else f" (gain e = {low:.2g}..{high:.2g})"


def _summary_figure(path: Path, panels: list, document: dict) -> None:
    images, titles, limits, labels, flagged = [], [], [], [], []
    for name, normal_rgb, errors, mae, invalid in panels:
        images += [normal_rgb, errors]
        titles += [f"{name}: normals", f"error, MAE {mae:.2f} deg"]
        limits += [None, (0.0, ERROR_MAP_MAX_DEG)]
        labels += [None, "degrees"]
        flagged += [None, invalid]
    fig = image_grid(
        images,
        titles,
        f"{document['method']} with {Path(document['patterns']).name}: mean MAE {document['mean_mae']:.2f} deg",
        f"Noise {document['noise']}, rig {document['rig']}, exposure {document['exposure']}{_gains_text(document)}. Normals white outside the mask, black where "
        f"flagged invalid. Error maps: angle between estimated and true normals, colours saturate at {ERROR_MAP_MAX_DEG:g} degrees; "
        "light blue: flagged invalid (counted in the MAE with the placeholder normal).",
        columns=4,
        cmap="magma",
        colorbar_label=labels,
        limits=limits,
        flagged=flagged,
    )
    save_figure(fig, path)
