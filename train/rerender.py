"""Re-rendering loss for learning through the baseline renderer (issue: learning through the renderer).

The analytic estimate (normals, albedo) is rendered back under the patterns with the Lambertian
basis of the baseline renderer (J = 1, no specular lobe: the analytic method has no specular
estimate) and compared with the simulated captures. Patterns that make the estimate explain the
captures well are rewarded, not only patterns that give good normals on the training scenes.
"""
from __future__ import annotations

import math

import torch

from capture_sim.render import render_olat
from capture_sim.simulator import Capture
from train.scene_pixels import ScenePixels


def rerender_loss(normal: torch.Tensor, albedo: torch.Tensor, capture: Capture, pixels: ScenePixels, columns: torch.Tensor | slice) -> torch.Tensor:
    """RMSE between captures and the estimate rendered under the same patterns.

    Args:
        normal: (P, 3) estimated unit normals of the sampled pixels.
        albedo: (P, 3) estimated albedo a = rho / pi.
        capture: the simulated capture (captures (M, P, 3), effective emission (M, K, 3)).
        pixels: the scene the pixels come from.
        columns: (P,) indices, or a slice, of the sampled pixels in the scene.

    Returns:
        Scalar RMSE in units of full scale.
    """
    count = normal.shape[0]
    diffuse, _ = render_olat(
        pixels.points[columns],
        normal,
        pixels.lights(),
        torch.ones(count, 1, dtype=normal.dtype),
        (albedo * math.pi)[:, None, :],
        torch.zeros(count, 1, dtype=normal.dtype),
        torch.ones(count, 1, dtype=normal.dtype),
        pixels.rig.falloff,
    )  # (K, P, 3)
    rendered = torch.einsum("mkc,kpc->mpc", capture.emission, diffuse).clamp(0.0, 1.0)
    return torch.sqrt(((rendered - capture.captures) ** 2).mean() + 1e-12)
