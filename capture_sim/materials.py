"""Synthetic materials as basis-BRDF mixtures, ready for ``render_olat`` (DESIGN section 3).

A material is J Cook-Torrance GGX basis BRDFs (diffuse RGB albedo rho_d, specular albedo rho_s,
perceptual roughness) plus per-pixel weights on the simplex: f(x) = sum_j w_j(x) f_j. A Lambertian
basis has rho_s = 0. Spatial variation comes from smooth 3D noise evaluated at the surface points
(a solid texture, so it sticks to the object, not to the image): random Fourier features with a
chosen wavelength, turned into weights by a softmax whose sharpness sets how crisp the regions are.

Kinds (``MATERIALS``):
    lambertian: one Lambertian basis, uniform albedo (given, or drawn from the seed).
    textured: three Lambertian bases, smooth weights -> textured albedo.
    svbrdf: three GGX bases with different colours, specular albedos and roughnesses, smooth weights.
    regions: four bases (one Lambertian) in near-piecewise regions with soft borders.
    glossy: two dark-diffuse, strongly specular, low-roughness bases, smooth weights.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from capture_sim.errors import InputError, check_array, check_seed

MATERIALS: tuple[str, ...] = ("lambertian", "textured", "svbrdf", "regions", "glossy")


@dataclass(frozen=True, eq=False)
class Material:
    """Basis BRDFs and their per-pixel weights (float64 tensors).

    Attributes:
        kind: one of ``MATERIALS``.
        diffuse_albedo: (J, 3) diffuse albedo rho_d of each basis, linear RGB in [0, 1].
        specular_albedo: (J,) specular albedo rho_s (0 = Lambertian basis).
        roughness: (J,) perceptual GGX roughness in (0, 1] (alpha = roughness ** 2).
        weights: (H, W, J) basis weights, non-negative, summing to 1 per pixel.
        texture: how the weights were made (noise wavelength in metres, softmax sharpness).
    """

    kind: str
    diffuse_albedo: torch.Tensor
    specular_albedo: torch.Tensor
    roughness: torch.Tensor
    weights: torch.Tensor
    texture: dict

    @property
    def num_basis(self) -> int:
        return int(self.diffuse_albedo.shape[0])

    def albedo_map(self) -> torch.Tensor:
        """(H, W, 3) per-pixel diffuse albedo sum_j w_j rho_d,j."""
        return self.weights @ self.diffuse_albedo

    def describe(self) -> dict:
        """JSON-ready description of the basis BRDFs and the texture."""
        return {
            "kind": self.kind,
            "brdf": "Cook-Torrance GGX, Smith-Schlick masking, constant Fresnel (capture_sim.brdf)",
            "num_basis": self.num_basis,
            "diffuse_albedo": self.diffuse_albedo.tolist(),
            "specular_albedo": self.specular_albedo.tolist(),
            "roughness": self.roughness.tolist(),
            "texture": self.texture,
        }


def smooth_noise(points: torch.Tensor, num_fields: int, wavelength: float, rng: np.random.Generator,
                 num_waves: int = 8) -> torch.Tensor:
    """Smooth random 3D fields: sums of ``num_waves`` plane waves of about ``wavelength`` metres.

    Args:
        points: (..., 3) positions in metres.
        num_fields: F independent fields.
        wavelength: typical spatial period in metres (each wave's period varies by +-30%).
        rng: numpy generator (drawn from in a fixed order, so results are reproducible).
        num_waves: plane waves per field.

    Returns:
        (..., F) float64 fields with zero mean and unit variance over random phases.
    """
    directions = rng.normal(size=(num_fields, num_waves, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    periods = wavelength * rng.uniform(0.7, 1.3, size=(num_fields, num_waves, 1))
    frequencies = torch.as_tensor(2.0 * math.pi * directions / periods)  # (F, M, 3) rad / m
    phases = torch.as_tensor(rng.uniform(0.0, 2.0 * math.pi, size=(num_fields, num_waves)))
    waves = torch.cos(torch.einsum("...d,fmd->...fm", points.to(torch.float64), frequencies) + phases)
    return waves.sum(-1) * math.sqrt(2.0 / num_waves)


def softmax_weights(fields: torch.Tensor, sharpness: float) -> torch.Tensor:
    """(..., J) simplex weights from (..., J) fields: softmax(sharpness * fields)."""
    return torch.softmax(sharpness * fields, dim=-1)


def _random_colours(rng: np.random.Generator, count: int, low: float, high: float) -> np.ndarray:
    """(count, 3) RGB albedos with well separated hues and values in [low, high]."""
    hues = (rng.uniform() + np.arange(count) / count) % 1.0
    saturation = rng.uniform(0.35, 0.8, count)
    value = rng.uniform(low, high, count)
    # HSV -> RGB by the standard piecewise formula, vectorised over the colours.
    k = (np.array([5.0, 3.0, 1.0])[None, :] + hues[:, None] * 6.0) % 6.0
    ramp = np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return value[:, None] * (1.0 - saturation[:, None] * ramp)


def make_material(kind: str, points, seed: int = 0, albedo=None) -> Material:
    """Build one of ``MATERIALS`` over a surface.

    Args:
        kind: one of ``MATERIALS``.
        points: (H, W, 3) surface points in metres, camera frame (texture coordinates; values at
            background pixels are irrelevant but must be finite).
        seed: non-negative integer; same seed and points, same material.
        albedo: for ``"lambertian"`` only: (3,) or scalar uniform diffuse albedo in [0, 1];
            None draws a colour from the seed.

    Returns:
        The material, weights of shape (H, W, J).
    """
    if kind not in MATERIALS:
        raise InputError(f"unknown material {kind!r}; choose from {', '.join(MATERIALS)}")
    check_seed("seed", seed)
    points = torch.as_tensor(points, dtype=torch.float64)
    check_array("points", points, ("H", "W", 3))
    if albedo is not None and kind != "lambertian":
        raise InputError(f"albedo applies only to material 'lambertian', not {kind!r}")
    rng = np.random.default_rng([int(seed), 23])
    height, width = points.shape[:2]

    if kind == "lambertian":
        if albedo is None:
            colour = rng.uniform(0.3, 0.85, size=3)
        else:
            colour = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (3,)).copy()
            check_array("albedo", colour, (3,), value_range=(0.0, 1.0))
        return Material(
            kind=kind,
            diffuse_albedo=torch.as_tensor(colour[None, :]),
            specular_albedo=torch.zeros(1, dtype=torch.float64),
            roughness=torch.ones(1, dtype=torch.float64),
            weights=torch.ones(height, width, 1, dtype=torch.float64),
            texture={"type": "uniform"},
        )

    # Per kind: number of bases, diffuse value range, specular albedo range, roughness choices,
    # noise wavelength (m) and softmax sharpness.
    if kind == "textured":
        count, diffuse_range, specular_range, roughness_choices, wavelength, sharpness = (
            3, (0.2, 0.9), (0.0, 0.0), (1.0,), 0.05, 3.0)
    elif kind == "svbrdf":
        count, diffuse_range, specular_range, roughness_choices, wavelength, sharpness = (
            3, (0.15, 0.8), (0.1, 0.5), (0.2, 0.35, 0.6), 0.06, 3.0)
    elif kind == "regions":
        count, diffuse_range, specular_range, roughness_choices, wavelength, sharpness = (
            4, (0.15, 0.85), (0.15, 0.6), (0.15, 0.3, 0.5, 0.8), 0.08, 10.0)
    else:  # glossy
        count, diffuse_range, specular_range, roughness_choices, wavelength, sharpness = (
            2, (0.05, 0.35), (0.6, 0.9), (0.15, 0.25), 0.07, 2.0)

    diffuse = _random_colours(rng, count, *diffuse_range)
    specular = rng.uniform(*specular_range, size=count)
    roughness = rng.permutation(np.asarray(roughness_choices * count, dtype=np.float64)[:count])
    if kind == "regions":
        specular[0] = 0.0  # one Lambertian region, as real objects mix matte and shiny parts
    weights = softmax_weights(smooth_noise(points, count, wavelength, rng), sharpness)
    return Material(
        kind=kind,
        diffuse_albedo=torch.as_tensor(diffuse),
        specular_albedo=torch.as_tensor(specular),
        roughness=torch.as_tensor(roughness),
        weights=weights,
        texture={"type": "softmax of smooth 3D noise", "wavelength_m": wavelength, "sharpness": sharpness},
    )
