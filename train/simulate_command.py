"""`displex simulate`: captures of one scene under a pattern set, written as arrays, PNGs and a sheet."""
from __future__ import annotations

import json
import re

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from capture_sim.atomic import check_output_folder, refuse_overwriting, save_npy, staged_files, write_json
from capture_sim.errors import InputError, check_seed
from capture_sim.png import write_png
from capture_sim.rig import DEFAULT_RIG, Rig, load_rig, rig_file
from capture_sim.scene import load_scene, rig_for_scene
from capture_sim.simulator import LightTransport, auto_exposure, display_emission, light_transport, noise_free_radiance, simulate
from patterns.io import check_patterns_match_rig, load_patterns
from train.figures import for_display, image_grid, save_figure
from train.scene_pixels import warn_if_black_inside_mask


SHEET_CAPTURES = 48
"""Captures shown on the contact sheet (every capture is still written as a PNG)."""


@dataclass(frozen=True)
class SimulateConfig:
    """What `displex simulate` does."""

    scene: Path
    """Scene interchange .npz (DESIGN section 7)."""
    patterns: Path
    """Pattern file (.npz or .npy), (M, R, C, 3) in [0, 1]."""
    out: Path
    """Output folder."""
    noise: str = "default"
    """'default': the rig's noise model and bit depth; 'off': noise-free and unquantised (clipping stays)."""
    exposure: str = "rig"
    """'rig' (the rig's exposure setting), 'auto' (DESIGN section 3, over the scene's mask) or a
    positive number."""
    seed: int = 0
    """Seed of the noise generator."""
    rig: str = DEFAULT_RIG
    """Rig preset or TOML path: display model and sensor."""


def parse_exposure(text: str, rig: Rig | None = None) -> float | str:
    """'auto' or a positive float from an exposure setting; anything else raises ``InputError``.

    'rig' stands for the rig's own setting: its fixed exposure, or 'auto' when it has none (as
    the presets do). Without a ``rig`` it is accepted (for early validation) and returned as is.
    """
    if text == "rig":
        if rig is None:
            return "rig"
        return "auto" if rig.exposure is None else float(rig.exposure)
    if text == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"exposure must be 'rig', 'auto' or a positive number, got {text!r}") from None
    if not value > 0 or not np.isfinite(value):
        raise InputError(f"exposure must be 'rig', 'auto' or a positive number, got {text!r}")
    return value


def resolve_exposure(exposure, patterns: torch.Tensor, transport: LightTransport, mask: np.ndarray, rig: Rig) -> float:
    """A fixed exposure as given, or auto exposure over the masked pixels ((H, W) bool ``mask``) of
    the whole-image ``transport`` (the background must not set the object's exposure)."""
    if exposure != "auto":
        return float(exposure)
    emitted = display_emission(patterns, rig.backlight_flat(), rig.gamma, rig.scale)
    return auto_exposure(noise_free_radiance(emitted, transport)[:, torch.as_tensor(mask.reshape(-1))])


def run_simulate(config: SimulateConfig) -> dict:
    """Simulate, write ``captures.npy``, 16-bit PNGs, ``contact_sheet.png`` and ``meta.json``; return the meta."""
    check_seed("--seed", config.seed)
    check_output_folder(config.out, "simulate")
    scene = load_scene(config.scene)
    rig = rig_for_scene(load_rig(config.rig), scene)
    warn_if_black_inside_mask(scene)
    pattern_values, pattern_meta = load_patterns(config.patterns)
    check_patterns_match_rig(pattern_values, rig.rows, rig.cols, rig.name, config.patterns)
    if config.noise not in ("off", "default"):
        raise InputError(f"--noise must be 'off' or 'default', got {config.noise!r}")
    patterns = torch.as_tensor(pattern_values, dtype=torch.float32)
    out = Path(config.out)
    names = [f"capture_{index:03d}.png" for index in range(len(pattern_values))]
    # Every output is checked before any is written: a bad one must not leave a half-replaced run.
    _refuse_foreign_captures(out)
    refuse_overwriting([("output", out / name) for name in ("captures.npy", "meta.json", "contact_sheet.png", *names)],
                       [("scene file", config.scene), ("pattern file", config.patterns), ("rig file", rig_file(config.rig))])
    setting = parse_exposure(str(config.exposure), rig)
    noise_free = config.noise == "off"
    with torch.no_grad():
        transport = light_transport(scene.olat)
        exposure = resolve_exposure(setting, patterns, transport, scene.mask, rig)
        capture = simulate(
            patterns,
            transport,
            rig,
            exposure=exposure,
            noise=None if noise_free else "rig",
            bit_depth=None if noise_free else "rig",
            generator=torch.Generator().manual_seed(config.seed),
        )
    images = transport.to_image(capture.captures).numpy().astype(np.float32)
    obsolete = [out / name for name in _previous_captures(out) if name not in names]  # an earlier run with more patterns
    meta = {
        "scene": str(config.scene),
        "patterns": str(config.patterns),
        "pattern_meta": pattern_meta,
        "rig": rig.name,
        "scale": rig.scale,
        "gamma": rig.gamma,
        "exposure": capture.exposure,
        "exposure_mode": "auto" if setting == "auto" else "fixed",
        "backlight": rig.backlight.tolist(),
        "bit_depth": None if noise_free else rig.bit_depth,
        "noise": None if noise_free else {"shot": rig.noise.shot, "read_std": rig.noise.read_std},
        "seed": config.seed,
        "saturated_fraction": float((images[:, scene.mask] >= 1.0).mean()),  # of the object's captured values, not the background's
        "files": names,
        "formula": "captures = q(clip(exposure * sum_k scale * (P[m,k] + backlight[k]) ** gamma * olat[k] + noise))",
    }
    shown = images[:SHEET_CAPTURES]
    # Written into a staging folder and moved into place at the end (meta.json last): an
    # interrupted run leaves an earlier run's files whole.
    with staged_files(out, last=("meta.json",), obsolete=obsolete) as staging:
        save_npy(staging / "captures.npy", images)
        for name, image in zip(names, images):
            write_png(staging / name, np.round(image * 65535).astype(np.uint16))
        fig = image_grid(
            [for_display(image) for image in shown],
            [f"pattern {index}" for index in range(len(shown))],
            f"Simulated captures of {scene.name}",
            f"{len(images)} patterns{f' (the first {len(shown)} shown)' if len(shown) < len(images) else ''}, exposure "
            f"{capture.exposure:.4g} ({meta['exposure_mode']}), noise {config.noise}; shown with a 1/2.2 display gamma.",
        )
        save_figure(fig, staging / "contact_sheet.png")
        write_json(staging / "meta.json", meta)
    return meta


def _refuse_foreign_captures(out: Path) -> None:
    """Refuse a folder holding ``capture_NNN.png`` files but neither a meta.json nor a
    captures.npy of a simulate run: they are someone's own images, which this run would overwrite
    or remove. (A run killed while its files moved in has removed its meta.json; once its
    captures.npy moved in, ``_previous_captures`` takes the PNGs as its own. A first run killed
    before that, by SIGKILL or power loss (Ctrl-C waits for the moves), leaves PNGs alone, which
    this refuses: the message says to remove them.)"""
    if (out / "meta.json").exists() or (out / "captures.npy").exists() or not out.is_dir():
        return
    found = sorted(path.name for path in out.glob("capture_*.png") if re.fullmatch(r"capture_\d{3,}\.png", path.name))
    if found:
        raise InputError(f"{out} holds {len(found)} capture_NNN.png file(s) ({', '.join(found[:3])}{', ...' if len(found) > 3 else ''}) "
                         "but no meta.json of a simulate run: choose another folder, or remove them")


def _previous_captures(out: Path) -> list[str]:
    """Capture PNGs of an earlier ``simulate`` into ``out``: those its meta.json lists, or, when
    it has none (a run interrupted while its files moved in removes it first), every
    ``capture_NNN.png`` there beside its captures.npy (a folder with neither is refused before
    the work: ``_refuse_foreign_captures``)."""
    try:
        files = json.loads((out / "meta.json").read_text()).get("files", [])
    except (OSError, ValueError, AttributeError):
        files = [path.name for path in out.glob("capture_*.png")]
    # Only names simulate writes itself: a hand-edited meta cannot delete other files.
    return [name for name in files if isinstance(name, str) and re.fullmatch(r"capture_\d{3,}\.png", name)]
