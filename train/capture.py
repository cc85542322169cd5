"""Simulated capture of a prepared scene, shared by learning, search and evaluation."""
from __future__ import annotations

import torch

from capture_sim.display import display_emission
from capture_sim.simulator import AUTO_EXPOSURE_TARGET, Capture, auto_exposure, auto_exposure_at, noise_free_radiance, simulate
from train.scene_pixels import ScenePixels


def scene_exposure(pixels: ScenePixels, patterns: torch.Tensor) -> float:
    """Auto exposure (DESIGN section 3) of a scene under a pattern set, over all its pixels, no gradient.

    Args:
        pixels: the prepared scene.
        patterns: (M, R, C, 3) set values in [0, 1].
    """
    with torch.no_grad():
        return auto_exposure(noise_free_radiance(_emitted(pixels, patterns), pixels.transport))


def _emitted(pixels: ScenePixels, patterns: torch.Tensor) -> torch.Tensor:
    """(M, K, 3) emission of the scene's display, from patterns promoted to float32 at least, as
    ``simulate`` does."""
    rig = pixels.rig
    patterns = patterns.to(torch.promote_types(patterns.dtype, torch.float32))
    return display_emission(patterns, rig.backlight_flat(patterns.dtype), rig.gamma, rig.scale)


def exposure_with_gradient(pixels: ScenePixels, patterns: torch.Tensor) -> torch.Tensor:
    """Auto exposure e = target / r* (the value ``simulate`` computes, in float64) as a scalar
    tensor that carries its gradient: r* is the noise-free capture at the percentile, which depends on the patterns.
    A brighter pattern set is exposed for less time, so its gain in signal over noise is mostly
    taken back; without this path a gradient sees only the gain.

    Args:
        pixels: the prepared scene (the pixels auto exposure looks at).
        patterns: (M, R, C, 3) set values in [0, 1], possibly requiring grad.
    """
    emitted = _emitted(pixels, patterns)  # (M, K, 3)
    with torch.no_grad():
        radiance = noise_free_radiance(emitted.detach(), pixels.transport)  # (M, N, 3)
        value, index = auto_exposure_at(radiance)
    if index is None:
        return torch.tensor(value, dtype=torch.float64)  # a dark scene: auto exposure's fixed 1, no gradient
    m, n, c = (int(i) for i in torch.unravel_index(torch.tensor(index), radiance.shape))
    at_percentile = (emitted[m, :, c].double() * pixels.transport.matrix[c, :, n].double()).sum()
    gain = AUTO_EXPOSURE_TARGET / at_percentile
    # The value is auto exposure's to the last bit (recomputing r* in another order rounds
    # differently, and the objectives jump at changes that small); only the gradient is gain's.
    return gain - gain.detach() + value


def capture_scene(
    pixels: ScenePixels,
    patterns: torch.Tensor,
    noise_scale: float = 1.0,
    exposure: float | str = "auto",
    generator: torch.Generator | None = None,
    columns: torch.Tensor | None = None,
) -> Capture:
    """Simulate the captures of a scene's pixels under a pattern set.

    Args:
        pixels: the prepared scene (masked pixels).
        patterns: (M, R, C, 3) set values in [0, 1]; gradients flow to them.
        noise_scale: multiplies both variance terms of the rig's noise model; 0 gives an ideal
            sensor (no noise and no quantisation; clipping stays).
        exposure: "auto" (over all the scene's masked pixels, no gradient), a fixed number, or
            a scalar tensor whose gradient reaches the captures (``exposure_with_gradient``).
        generator: noise generator.
        columns: optional (P,) indices or a slice of a pixel subset to simulate (exposure still
            uses all; a slice selects a view, without copying the transport).

    Returns:
        Capture with (M, N or P, 3) captures, (M, K, 3) effective emission and the exposure.
    """
    rig = pixels.rig
    if exposure == "auto":
        exposure = scene_exposure(pixels, patterns)
    transport = pixels.transport if columns is None else pixels.transport.subset(columns)
    noisy = noise_scale > 0
    return simulate(
        patterns,
        transport,
        rig,
        exposure=exposure if isinstance(exposure, torch.Tensor) else float(exposure),
        noise=rig.noise.scaled(noise_scale) if noisy else None,
        bit_depth=rig.bit_depth if noisy else None,
        generator=generator,
    )
