"""Evaluation of a pattern set on scenes: simulate, reconstruct, measure (DESIGN section 5).

The `displex evaluate` command built on it lives in ``train.evaluate_command``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from capture_sim.errors import InputError, check_seed
from capture_sim.rig import check_noise_scale
from capture_sim.simulator import auto_exposure, check_exposure_range, sensor
from reconstruct.metrics import angular_error_deg, normal_metrics
from reconstruct.photometric_stereo import PSConfig, PSResult, solve_ps
from reconstruct.woodham import solve_woodham, solve_woodham_olat
from train.capture import capture_scene
from train.scene_pixels import ScenePixels

METHODS = ("ps", "woodham")


@dataclass(frozen=True)
class EvalSettings:
    """How a pattern set is evaluated."""

    method: str = "ps"
    """'ps' (analytic multiplexed photometric stereo) or 'woodham' (least squares; grey patterns or OLAT)."""
    noise_scale: float = 1.0
    """Multiplier of the rig's noise variances; 0 = noise-free, unquantised sensor."""
    exposure: float | str = "auto"
    """'auto' per scene (DESIGN section 3) or a fixed gain."""
    seed: int = 0
    """Noise seed; scene i uses seed * 1000 + i."""
    ps: PSConfig = field(default_factory=PSConfig)
    """Solver settings."""

    def __post_init__(self):
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        check_noise_scale("noise scale", self.noise_scale)
        check_seed("seed", self.seed)


@dataclass(frozen=True, eq=False)
class SceneEvaluation:
    """Result for one scene: metrics dict, (N, ...) reconstruction of its masked pixels, exposure."""

    metrics: dict
    result: PSResult
    exposure: float


def olat_captures(pixels: ScenePixels, settings: EvalSettings, generator: torch.Generator, columns: torch.Tensor | None = None):
    """Captures of the full OLAT stack: (K, N or P, 3), the diagonal effective emission (K, K, 3)
    and the exposure gain (float).

    Each OLAT image is exposed as the operator would for the whole stack (auto: 99.9th percentile of
    all of them over every masked pixel at 0.9), with the backlight removed as in the definition of
    O (DESIGN section 2). ``columns`` (P,) restricts the captures to a pixel subset.
    """
    radiance = pixels.transport.matrix.permute(1, 2, 0)  # (K, N, 3)
    if settings.exposure == "auto":
        exposure = auto_exposure(radiance)
    else:
        exposure = float(settings.exposure)
    if columns is not None:
        radiance = radiance[:, columns]
    rig = pixels.rig
    noisy = settings.noise_scale > 0
    # Exposed pattern-major, (K, 3, N) in memory: the sensor keeps that layout, and the solvers'
    # pixels-last (K, 3, N) captures are then a view, not a second full-size copy.
    exposed = torch.mul(radiance.permute(0, 2, 1), exposure, out=radiance.new_empty((radiance.shape[0], 3, radiance.shape[1]))).permute(0, 2, 1)
    emission = exposure * torch.eye(pixels.transport.num_lights, dtype=radiance.dtype)[:, :, None].expand(-1, -1, 3)
    check_exposure_range(exposure, exposed, emission)
    captures = sensor(exposed, rig.noise.scaled(settings.noise_scale) if noisy else None, rig.bit_depth if noisy else None, generator)
    return captures, emission, exposure


def evaluate_scene(pixels: ScenePixels, patterns, settings: EvalSettings, scene_index: int = 0, columns: torch.Tensor | None = None) -> SceneEvaluation:
    """Simulate, reconstruct and measure one scene.

    Args:
        pixels: prepared scene; needs true normals.
        patterns: (M, R, C, 3) tensor of set values, or the string "olat" for the full OLAT stack.
        settings: method, noise, exposure, seed, solver.
        scene_index: position of the scene in its set (chooses its noise seed).
        columns: optional (P,) indices of the masked pixels to reconstruct and measure (None = all);
            auto exposure still looks at every masked pixel.

    Returns:
        SceneEvaluation with metrics {mae, median, under_5, ..., invalid_fraction, flagged (the
        fraction of pixels carrying each of the solver's flags), seconds (wall time of simulation
        and reconstruction), reconstruct_seconds (of the reconstruction alone), exposure} and the
        (N or P, ...) reconstruction.
    """
    if pixels.normal is None:
        raise InputError(f"scene {pixels.name} has no ground-truth normals to evaluate against")
    generator = torch.Generator().manual_seed(settings.seed * 1000 + scene_index)
    start = time.perf_counter()
    with torch.no_grad():
        lights, falloff = pixels.lights(), pixels.rig.falloff
        points = pixels.points if columns is None else pixels.points[columns]
        truth = pixels.normal if columns is None else pixels.normal[columns]
        olat = isinstance(patterns, str)
        if olat:
            if patterns != "olat":
                raise InputError(f"patterns must be a pattern array or 'olat', got {patterns!r}")
            captures, emission, exposure = olat_captures(pixels, settings, generator, columns)
        else:
            capture = capture_scene(pixels, patterns, settings.noise_scale, settings.exposure, generator, columns)
            captures, emission, exposure = capture.captures, capture.emission, capture.exposure
        solve_start = time.perf_counter()
        if settings.method == "woodham" and olat:
            result = solve_woodham_olat(captures, points, lights, falloff, exposure)
        elif settings.method == "woodham":
            result = solve_woodham(captures, emission, points, lights, falloff)
        else:
            result = solve_ps(captures, emission, points, lights, falloff, settings.ps)
    end = time.perf_counter()
    everywhere = torch.ones(truth.shape[0], dtype=torch.bool)
    metrics = {"name": pixels.name, **normal_metrics(result.normal, truth, everywhere)}
    metrics["invalid_fraction"] = float((~result.valid).float().mean())
    metrics["flagged"] = {name: float(flag.float().mean()) for name, flag in result.flags.items()}
    metrics["seconds"] = end - start
    metrics["reconstruct_seconds"] = end - solve_start
    metrics["exposure"] = exposure
    return SceneEvaluation(metrics, result, exposure)


def mean_mae(evaluations: list[SceneEvaluation]) -> float:
    """Mean over scenes of the per-scene MAE (degrees)."""
    return float(np.mean([evaluation.metrics["mae"] for evaluation in evaluations]))


def error_map(pixels: ScenePixels, result: PSResult) -> np.ndarray:
    """(H, W) angular error in degrees, NaN outside the mask (for plotting)."""
    return masked_map(pixels, angular_error_deg(result.normal, pixels.normal))


def masked_map(pixels: ScenePixels, values: torch.Tensor) -> np.ndarray:
    """(H, W) float32 image of per-masked-pixel ``values`` (N,), NaN outside the mask."""
    image = np.full(pixels.mask.shape, np.nan, dtype=np.float32)
    image[pixels.mask] = values.detach().float().numpy()
    return image
