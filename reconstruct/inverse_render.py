"""Baseline inverse renderer: normals and J basis Cook-Torrance BRDFs from captures (DESIGN section 4).

Image model (DESIGN section 3), pixel n with surface point x_n, normal n_n and view v_n:
    I[m, n, c] = sum_k E[m, k, c] O[k, n, c]
    O[k, n, c] = (sum_j w_nj f_j(l_nk, v_n))_c * max(0, n_n . l_nk) * falloff(d_nk)
E: effective emission exposure * scale * (P + B) ** gamma (backlight included), (M, K, 3);
w_n: basis weights on the simplex; f_j: GGX Cook-Torrance with diffuse albedo rho_d (RGB),
specular albedo rho_s and perceptual roughness r (alpha = r^2, constant Fresnel, as
``capture_sim.brdf``).

Fast shading. Geometry is fixed during a fit, so everything about a (pixel, light) pair that does not
depend on the normal is a constant computed once: 1 / d, falloff(d) and 1 / |l + v| (the norm of the
unnormalised half vector). The normal enters only through cosines taken from one matrix product:
    n . l_k = (n . p_k - n . x) / d_k,      n . h_k = (n . l_k + n . v) / |l_k + v|
so no (N, K, 3) tensor is built. The GGX lobe times its Smith-Schlick term simplifies to
    D G / (4 (n.l)(n.v)) = alpha^2 / (4 pi) / ((n.h^2 (alpha^2 - 1) + 1)^2 (n.l (1 - k) + k) (n.v (1 - k) + k))
with k = alpha / 2; the last factor is per pixel, not per light. Emission meets shading in one
matrix product (N, K) @ (K, 3M); when every pattern lights a single superpixel (OLAT) it is a
per-pattern gain instead, and lights no pattern uses are not shaded at all.
``capture_sim.render.render_olat`` followed by a sum over lights is the plain reference.

Far field: with ``far_field=True`` every pixel sees every light from the object's centroid (one
direction, distance and half vector per light), which is what a distant display would do.

Fit (Choi et al., ICCV 2025), with the changes marked (*):
1. Start: analytic photometric stereo (``solve_ps``; for OLAT captures a near-field Woodham least
   squares with reweighting against highlights, ``olat_least_squares``). (*) Pixels photometric
   stereo leaves invalid take their valid neighbours' values instead of facing the camera, and
   every normal is tilted to n . v >= 0.2: a start at n . v <= 0 sees no specular lobe, hence no
   gradient to leave by.
2. Clusters: k-means on hue and saturation of the photometric-stereo albedo (a pseudo-diffuse
   image) into J clusters: one-hot weights (softmax logits, 0.9 on the own cluster). (*) The
   tightest of 8 seeded k-means++ runs is kept: a single run can split one material and merge two.
3. Basis BRDFs: roughness 0.5. (*) Diffuse and specular albedos from their least-squares values at
   the starting normals and clusters (``least_squares_albedos``) instead of the cluster median and
   rho_s = 0.5: 0.5 in a scene's arbitrary radiometric units can be far off, and a lobe the scene
   does not have then dominates a short fit.
4. Adam on random batches of pixels, minimising
       RMSE(rendered - captured) + lambda_tv * TV(normals)
   with TV the mean L1 difference of unit normals between right and lower neighbours in the image
   grid. Saturated captures only say "at least full scale": their residual counts only where the
   rendering is darker. Learning rates decay exponentially.
5. (*) Normal search: with few patterns and sharp lobes, a pixel's error has local minima in the
   normal that gradient steps cannot leave (a start 15 degrees off stays there even with the true
   BRDFs). At a few points of the fit, the worst-fitted pixels try a grid over the visible
   hemisphere and a finer cap around the best (``search_normals``); the best candidate wins.
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from torch.utils.checkpoint import checkpoint

from capture_sim.brdf import MIN_ALPHA
from capture_sim.errors import InputError, check_array
from capture_sim.geometry import light_geometry, view_directions
from capture_sim.rig import check_falloff_values
from reconstruct.photometric_stereo import PSConfig, solve_ps

RENDER_CHUNK_PIXELS = 4096
"""Pixels shaded at once by ``render_under_patterns``: a few (4096, K) temporaries of ~2.4 MB each."""

_EPS = 1e-6


# ----------------------------------------------------------------------------------------------
# Geometry constants
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ShadingGeometry:
    """Normal-independent constants of every (pixel, light) pair, computed once per fit.

    Rows are pixels (P = N), or a single row (P = 1) shared by all pixels in the far field.

    Attributes:
        lights: (K, 3) superpixel positions p_k, metres, camera frame.
        anchor: (P, 3) points x the light directions start from, metres, camera frame.
        view: (P, 3) unit vectors from the anchor towards the camera centre.
        inverse_distance: (P, K) 1 / |p_k - x|, 1/metres.
        falloff: (P, K) falloff(|p_k - x|), positive and finite.
        inverse_half_norm: (P, K) 1 / |l_k + v|.
    """

    lights: torch.Tensor
    anchor: torch.Tensor
    view: torch.Tensor
    inverse_distance: torch.Tensor
    falloff: torch.Tensor
    inverse_half_norm: torch.Tensor

    @property
    def far_field(self) -> bool:
        return self.anchor.shape[0] == 1

    def take(self, index: torch.Tensor) -> "ShadingGeometry":
        """Constants of the pixels ``index`` (the far-field row is shared, so it is returned as is)."""
        if self.far_field:
            return self
        return ShadingGeometry(
            self.lights, self.anchor[index], self.view[index],
            self.inverse_distance[index], self.falloff[index], self.inverse_half_norm[index],
        )


def shading_geometry(points: torch.Tensor, lights: torch.Tensor, falloff: Callable, far_field: bool = False,
                     min_distance: float = 1e-3, chunk_pixels: int = 8192) -> ShadingGeometry:
    """Compute the normal-independent shading constants (no gradient flows to points or lights).

    Args:
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable mapping distances (metres, any shape) to falloff factors.
        far_field: use the centroid of ``points`` for every pixel (one row of constants).
        min_distance: metres; distances are clamped to at least this so nothing divides by zero.
        chunk_pixels: pixels processed at once (bounds the (chunk, K, 3) temporaries).

    Returns:
        ShadingGeometry in the dtype of ``points``.

    Raises:
        InputError: the falloff is not positive and finite at some pixel's light distance.
    """
    with torch.no_grad():
        points = points.detach()
        lights = lights.detach().to(points.dtype)
        anchor = points.mean(0, keepdim=True) if far_field else points
        rows = anchor.shape[0]
        num_lights = lights.shape[0]
        inverse_distance = torch.empty((rows, num_lights), dtype=points.dtype)
        falloff_values = torch.empty_like(inverse_distance)
        inverse_half_norm = torch.empty_like(inverse_distance)
        view = view_directions(anchor, _EPS)
        for start in range(0, rows, chunk_pixels):
            block = slice(start, start + chunk_pixels)
            light_dirs, distance = light_geometry(anchor[block], lights, min_distance)
            inverse_distance[block] = 1.0 / distance
            values = torch.as_tensor(falloff(distance), dtype=points.dtype)
            check_falloff_values(values, distance)
            falloff_values[block] = values
            inverse_half_norm[block] = 1.0 / (light_dirs + view[block, None, :]).norm(dim=-1).clamp_min(_EPS)
    return ShadingGeometry(lights, anchor, view, inverse_distance, falloff_values, inverse_half_norm)


# ----------------------------------------------------------------------------------------------
# Shading and emission
# ----------------------------------------------------------------------------------------------


def _cosines(normal: torch.Tensor, geometry: ShadingGeometry):
    """n . l (B, K), n . h clamped to [0, 1] (B, K) and n . v (B, 1) for unit normals (B, 3)."""
    n_dot_x = (normal * geometry.anchor).sum(-1, keepdim=True)
    n_dot_l = torch.addmm(-n_dot_x, normal, geometry.lights.T) * geometry.inverse_distance
    n_dot_v = (normal * geometry.view).sum(-1, keepdim=True)
    n_dot_h = ((n_dot_l + n_dot_v) * geometry.inverse_half_norm).clamp(0.0, 1.0)
    return n_dot_l, n_dot_h, n_dot_v


_LOBE_BLOCK_ROWS = 1024
"""Pixels per block of ``_LobeSum``: its per-basis temporaries then stay in the CPU cache (about
1.6x faster than whole (B, K) passes at B = 8192, K = 144)."""


class _LobeSum(torch.autograd.Function):
    """S = sum_j c_j / (t_j^2 u_j) with t_j = n.h^2 a_j + s and u_j = k_j + n.l (1 - k_j), where
    a_j = alpha_j^2 and s = 1 - n.h^2 = (1 - n.h)(1 + n.h).

    t = 1 + n.h^2 (a - 1) written so: near the lobe's peak (n.h -> 1, small alpha) that form
    cancels to a few float32 steps and sharp lobes came out up to 6% too bright at alpha = 0.05.
    The (B, K) per-basis terms are recomputed in the backward pass instead of being stored, built
    with in-place operations, block by block of pixels: faster than autograd through the same loop
    (about 2.5x at B = 8192, K = 144, J = 3), with the memory of the inputs only. Derivatives
    (q = 1 / (t^2 u)):
        dq/d(n.h^2) = -2 a q / t,   dq/d s = -2 q / t,   dq/d a = -2 n.h^2 q / t,
        dq/d(n.l)   = -(1 - k) q / u,  dq/d k    = -(1 - n.l) q / u.
    """

    @staticmethod
    def forward(ctx, n_dot_l_pos, n_dot_h2, sin2, coefficient, alpha2, k):
        # The first basis writes each block, later ones add: no zero-filled (B, K) pass.
        total = torch.empty_like(n_dot_l_pos) if alpha2.numel() else torch.zeros_like(n_dot_l_pos)
        alpha2s, ks = alpha2.tolist(), k.tolist()
        for start in range(0, total.shape[0], _LOBE_BLOCK_ROWS):
            rows = slice(start, start + _LOBE_BLOCK_ROWS)
            n_dot_l_rows, n_dot_h2_rows, sin2_rows, out = n_dot_l_pos[rows], n_dot_h2[rows], sin2[rows], total[rows]
            for j, (alpha2_j, k_j) in enumerate(zip(alpha2s, ks)):
                term = n_dot_h2_rows * alpha2_j
                term += sin2_rows
                smith = n_dot_l_rows * (1.0 - k_j)
                smith += k_j
                term.square_().mul_(smith).reciprocal_()
                if j == 0:
                    torch.mul(term, coefficient[rows, :1], out=out)
                else:
                    out.addcmul_(term, coefficient[rows, j : j + 1])
        ctx.save_for_backward(n_dot_l_pos, n_dot_h2, sin2, coefficient, alpha2, k)
        return total

    @staticmethod
    def backward(ctx, grad):
        n_dot_l_pos, n_dot_h2, sin2, coefficient, alpha2, k = ctx.saved_tensors
        grad = grad.contiguous()
        empty = torch.zeros_like if alpha2.numel() == 0 else torch.empty_like  # first basis writes
        grad_n_dot_l = empty(n_dot_l_pos)
        grad_n_dot_h2 = empty(n_dot_h2)
        grad_sin2 = empty(sin2)
        grad_coefficient = torch.empty_like(coefficient)
        grad_alpha2 = torch.zeros(alpha2.shape, dtype=torch.float64)
        grad_k = torch.zeros(k.shape, dtype=torch.float64)
        alpha2s, ks = alpha2.tolist(), k.tolist()
        for start in range(0, grad.shape[0], _LOBE_BLOCK_ROWS):
            rows = slice(start, start + _LOBE_BLOCK_ROWS)
            n_dot_l_rows, n_dot_h2_rows, sin2_rows, grad_rows = n_dot_l_pos[rows], n_dot_h2[rows], sin2[rows], grad[rows]
            for j, (alpha2_j, k_j) in enumerate(zip(alpha2s, ks)):
                inverse_t = n_dot_h2_rows * alpha2_j
                inverse_t += sin2_rows
                inverse_t.reciprocal_()
                inverse_u = n_dot_l_rows * (1.0 - k_j)
                inverse_u += k_j
                inverse_u.reciprocal_()
                weighted = inverse_t.square().mul_(inverse_u).mul_(grad_rows)  # grad * q
                grad_coefficient[rows, j] = weighted.sum(1)
                weighted.mul_(coefficient[rows, j : j + 1])  # grad * c * q
                over_t = weighted * inverse_t
                if j == 0:
                    torch.mul(over_t, -2.0, out=grad_sin2[rows])
                    torch.mul(over_t, -2.0 * alpha2_j, out=grad_n_dot_h2[rows])
                else:
                    grad_sin2[rows].add_(over_t, alpha=-2.0)
                    grad_n_dot_h2[rows].add_(over_t, alpha=-2.0 * alpha2_j)
                grad_alpha2[j] += -2.0 * float(torch.dot(over_t.reshape(-1), n_dot_h2_rows.reshape(-1)))
                over_u = weighted.mul_(inverse_u)
                if j == 0:
                    torch.mul(over_u, -(1.0 - k_j), out=grad_n_dot_l[rows])
                else:
                    grad_n_dot_l[rows].add_(over_u, alpha=-(1.0 - k_j))
                grad_k[j] += float(torch.dot(over_u.reshape(-1), n_dot_l_rows.reshape(-1))) - float(over_u.sum())
        return grad_n_dot_l, grad_n_dot_h2, grad_sin2, grad_coefficient, grad_alpha2.to(alpha2.dtype), grad_k.to(k.dtype)


def _specular_sum(n_dot_l_pos, n_dot_h, n_dot_v, weights, specular, roughness):
    """sum_j w_j rho_s,j D_j G_j / (4 (n.l)(n.v)) per pixel and light, (B, K); 0 where n . v <= 0."""
    alpha = (roughness * roughness).clamp_min(MIN_ALPHA)  # (J,)
    alpha2 = alpha * alpha
    k = alpha / 2.0
    visible = (n_dot_v > 0).to(n_dot_v.dtype)
    n_dot_v_safe = n_dot_v.clamp_min(_EPS)
    # Per-pixel factor of each basis: w rho_s alpha^2 / (4 pi (n.v (1 - k) + k)), (B, J).
    coefficient = weights * (specular * alpha2 / (4.0 * math.pi)) * visible / (n_dot_v_safe * (1.0 - k) + k)
    return _LobeSum.apply(n_dot_l_pos, n_dot_h * n_dot_h, (1.0 - n_dot_h) * (1.0 + n_dot_h), coefficient, alpha2, k)


class EmissionPlan:
    """How an emission (M, K, 3) meets per-light shading, prepared once per emission.

    Lights no pattern uses are dropped; if every pattern then lights exactly one superpixel (an
    OLAT-style set), shading is evaluated for that light only and multiplied by a per-pattern RGB
    gain; otherwise shading of the used lights is contracted with the emission in one matrix
    product. When the emission requires gradients every light is kept (a zero entry still has a
    derivative), and the dense path is used.
    """

    def __init__(self, emission: torch.Tensor):
        self.num_patterns = emission.shape[0]
        num_lights = emission.shape[1]
        if emission.requires_grad:
            used = torch.arange(num_lights)
        else:
            used = torch.nonzero((emission != 0).any(dim=2).any(dim=0)).squeeze(1)
        lit = emission.detach()[:, used] != 0  # (M, K', 3)
        one_light = used.numel() > 0 and not emission.requires_grad and bool((lit.any(-1).sum(1) == 1).all())
        if one_light:
            which = lit.any(-1).to(torch.int64).argmax(1)  # (M,) index into used
            self.light_index = used[which]
            self.gain = emission[torch.arange(self.num_patterns), self.light_index]  # (M, 3)
            self.matrix = None
        else:
            self.light_index = used
            self.gain = None
            # (K', 3M): column (m, c) holds E[m, :, c].
            self.matrix = emission[:, used].permute(1, 0, 2).reshape(used.numel(), emission.shape[0] * 3)

    def contract(self, irradiance: torch.Tensor, specular_radiance: torch.Tensor | None, diffuse_albedo: torch.Tensor) -> torch.Tensor:
        """Images (M, B, 3) from shading of the plan's lights.

        Args:
            irradiance: (B, K') max(0, n . l) falloff for the lights ``light_index``.
            specular_radiance: (B, K') specular BRDF times irradiance, or None (Lambertian).
            diffuse_albedo: (B, 3) per-pixel rho_d.
        """
        batch = irradiance.shape[0]
        rho = diffuse_albedo / math.pi
        if self.gain is not None:
            images = irradiance[:, :, None] * rho[:, None, :]  # (B, M, 3)
            if specular_radiance is not None:
                images = images + specular_radiance[:, :, None]
            return (images * self.gain[None]).permute(1, 0, 2)
        if self.matrix.shape[0] == 0:
            return irradiance.new_zeros((self.num_patterns, batch, 3))
        matrix = self.matrix.to(irradiance.dtype)
        images = (irradiance @ matrix).view(batch, self.num_patterns, 3) * rho[:, None, :]
        if specular_radiance is not None:
            images = images + (specular_radiance @ matrix).view(batch, self.num_patterns, 3)
        return images.permute(1, 0, 2)


def shade_and_contract(normal, geometry: ShadingGeometry, plan: EmissionPlan, weights, diffuse, specular, roughness) -> torch.Tensor:
    """Images (M, B, 3) of B pixels; ``geometry`` must already be restricted to ``plan.light_index``.

    Args:
        normal: (B, 3) unit normals, camera frame.
        geometry: constants of the B pixels (or the far-field row) for the plan's lights.
        plan: the emission plan.
        weights: (B, J) basis weights.
        diffuse: (J, 3) basis diffuse albedos rho_d.
        specular: (J,) basis specular albedos rho_s, or None for Lambertian bases.
        roughness: (J,) basis perceptual roughness (ignored when ``specular`` is None).
    """
    n_dot_l, n_dot_h, n_dot_v = _cosines(normal, geometry)
    n_dot_l_pos = n_dot_l.clamp_min(0.0)
    irradiance = n_dot_l_pos * geometry.falloff
    specular_radiance = None
    if specular is not None:
        specular_radiance = irradiance * _specular_sum(n_dot_l_pos, n_dot_h, n_dot_v, weights, specular, roughness)
    return plan.contract(irradiance, specular_radiance, weights @ diffuse)


def render_under_patterns(
    normals: torch.Tensor,
    points: torch.Tensor,
    lights: torch.Tensor,
    emission: torch.Tensor,
    weights: torch.Tensor,
    diffuse: torch.Tensor,
    specular: torch.Tensor | None,
    roughness: torch.Tensor,
    falloff: Callable,
    far_field: bool = False,
    chunk_pixels: int = RENDER_CHUNK_PIXELS,
) -> torch.Tensor:
    """Noise-free, unclipped captures of a basis-BRDF scene under patterns, differentiably.

    I[m, n, c] = sum_k E[m, k, c] O[k, n, c] with O the OLAT image of ``capture_sim.render.render_olat``
    (no cast shadows). Pixels are processed in chunks of ``chunk_pixels``; with gradients and more
    than one chunk, each chunk is recomputed in the backward pass (activation checkpointing), so
    memory stays at about one chunk's temporaries plus the (M, N, 3) output.

    Args:
        normals: (N, 3) normals, camera frame (normalised here; visible ones have n . v > 0).
        points: (N, 3) surface points, metres, camera frame (constant: no gradient).
        lights: (K, 3) superpixel positions, metres, camera frame (constant).
        emission: (M, K, 3) effective emission E >= 0 (exposure * scale * (P + B) ** gamma).
        weights: (N, J) basis weights (on the simplex for physical mixtures).
        diffuse: (J, 3) basis diffuse albedos rho_d >= 0.
        specular: (J,) basis specular albedos rho_s >= 0, or None for Lambertian bases.
        roughness: (J,) basis perceptual roughness in (0, 1] (alpha = roughness ** 2).
        falloff: callable distance (metres) -> falloff factor (constant), e.g. ``Falloff()``.
        far_field: shade every pixel with the light directions and distances of the centroid.
        chunk_pixels: pixels per chunk.

    Returns:
        (M, N, 3) radiance times exposure (full scale 1), differentiable in normals, emission,
        weights, diffuse, specular and roughness.

    Example:
        >>> from capture_sim.rig import Falloff
        >>> images = render_under_patterns(normals, points, lights, emission, weights, diffuse,
        ...                                specular, roughness, Falloff())  # doctest: +SKIP
    """
    check_array("normals", normals, ("N", 3))
    count = normals.shape[0]
    check_array("points", points, (count, 3))
    check_array("lights", lights, ("K", 3))
    check_array("emission", emission, ("M", lights.shape[0], 3), value_range=(0.0, math.inf))
    check_array("weights", weights, (count, "J"))
    num_basis = weights.shape[1]
    check_array("diffuse", diffuse, (num_basis, 3), value_range=(0.0, math.inf))
    if specular is not None:
        check_array("specular", specular, (num_basis,), value_range=(0.0, math.inf))
    check_array("roughness", roughness, (num_basis,), value_range=(0.0, 1.0))
    if chunk_pixels < 1:
        raise InputError(f"chunk_pixels must be positive, got {chunk_pixels}")
    dtype = normals.dtype
    plan = EmissionPlan(emission.to(dtype))
    plan_lights = lights.to(dtype)[plan.light_index]
    far_geometry = shading_geometry(points.to(dtype), plan_lights, falloff, far_field=True) if far_field else None
    unit_normals = normals / normals.norm(dim=-1, keepdim=True).clamp_min(_EPS)

    def render_chunk(chunk_normals, chunk_points, chunk_weights, *basis):
        geometry = far_geometry if far_field else shading_geometry(chunk_points, plan_lights, falloff)
        chunk_specular = basis[1] if specular is not None else None
        return shade_and_contract(chunk_normals, geometry, plan, chunk_weights, basis[0], chunk_specular, basis[-1])

    basis = (diffuse.to(dtype),) + ((specular.to(dtype),) if specular is not None else ()) + (roughness.to(dtype),)
    tracked = torch.is_grad_enabled() and any(t.requires_grad for t in (normals, emission, weights, *basis))
    chunks = []
    for start in range(0, count, chunk_pixels):
        block = slice(start, start + chunk_pixels)
        arguments = (unit_normals[block], points[block].to(dtype), weights[block].to(dtype), *basis)
        if tracked and count > chunk_pixels:
            chunks.append(checkpoint(render_chunk, *arguments, use_reentrant=False))
        else:
            chunks.append(render_chunk(*arguments))
    if not chunks:
        return normals.new_zeros((emission.shape[0], 0, 3))
    return torch.cat(chunks, dim=1)


# ----------------------------------------------------------------------------------------------
# Model and initialisation
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FitConfig:
    """Settings of one inverse-rendering fit (``fit_inverse_render``)."""

    num_basis: int = 3
    """J, the number of basis BRDFs."""
    specular: bool = True
    """Fit GGX specular lobes; False fits Lambertian bases only (rho_s = 0, no lobe evaluated)."""
    iterations: int = 400
    """Adam steps."""
    batch_pixels: int = 8192
    """Pixels per step (random batches drawn without replacement from a shuffled order, reshuffled
    when fewer than a batch remain, so up to batch_pixels - 1 pixels sit out an epoch); all when fewer."""
    normal_lr: float = 0.03
    """Adam learning rate of the unnormalised normal vectors (unit length at the start)."""
    weight_lr: float = 0.1
    """Adam learning rate of the weight logits (weights = softmax of logits)."""
    brdf_lr: float = 0.03
    """Adam learning rate of the log diffuse albedos and the roughness logits."""
    specular_lr: float = 0.1
    """Adam learning rate of the log specular albedos: high enough that a lobe the scene does not
    have can fade by orders of magnitude within a short fit (rho_s starts at its least-squares
    value with ``least_squares_init``, else at 0.5)."""
    final_lr_fraction: float = 0.05
    """Learning rates decay exponentially to this fraction of their start by the last step."""
    tv_weight: float = 1e-3
    """lambda_tv: weight of the normals' total variation (mean L1 difference between neighbours)
    relative to the RMSE in full-scale units."""
    far_field: bool = False
    """Shade with the centroid's light directions and distances (see module docstring)."""
    initial_specular: float = 0.5
    """Starting rho_s of every basis when ``least_squares_init`` is off, in the fit's albedo units
    (the scene's, or scaled to order one by ``albedo_unit``)."""
    least_squares_init: bool = True
    """Start the basis albedos (rho_d and rho_s) from their least-squares values at the initial
    normals, clusters and roughness (``least_squares_albedos``) instead of the cluster medians and
    0.5. A deliberate change from the published initialisation: 0.5 in a scene's arbitrary
    radiometric units can be far off (on a matte scene it starts the fit with a lobe 50 times the
    data's error), and a lobe the scene lacks then takes most of a short fit to fade."""
    specular_floor: float = 0.1
    """Least-squares rho_s start no lower than this fraction of ``initial_specular``. Some pattern
    sets leave the specular images nearly unconstrained at the initial normals, and least squares
    then gives rho_s ~ 0: started there, the fit brightened a diffuse albedo to take the highlights
    and stayed in that minimum (held-out PSNR ~27 dB instead of ~35 with some learned M = 4 sets;
    1e-3 was the previous value)."""
    initial_roughness: float = 0.5
    """Starting perceptual roughness of every basis."""
    min_roughness: float = 0.05
    """Lower bound of the roughness parameterisation r = r_min + (1 - r_min) sigmoid(theta)."""
    initial_weight: float = 0.9
    """Starting weight of a pixel's own cluster (the rest shared by the other bases); softmax weights
    cannot be exactly one-hot, and a softer start lets pixels change cluster."""
    normal_search_at: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6)
    """Fractions of the fit at which badly fitted pixels search their normal globally
    (``search_normals``); empty for none. With few patterns and sharp lobes a pixel's error has
    local minima that Adam cannot leave (a start 15 degrees off can be stuck there)."""
    search_residual_ratio: float = 2.0
    """A pixel searches when its RMSE exceeds this many times the median pixel RMSE."""
    search_max_fraction: float = 0.1
    """At most this fraction of the pixels (the worst fitted) searches per round, to bound its cost."""
    search_candidates: int = 128
    """Normals of the coarse search grid over the visible hemisphere (about 13 degrees apart);
    the best is refined by a quarter as many within ``search_refine_deg``."""
    search_refine_deg: float = 10.0
    """Half-angle of the refinement cap around the best coarse normal, degrees."""
    saturation_threshold: float = 0.999
    """Captures at or above this count as saturated (only a lower bound on the rendering)."""
    seed: int = 0
    """Seed of k-means and of the pixel batches."""

    def __post_init__(self):
        if self.num_basis < 1:
            raise InputError(f"num_basis must be at least 1, got {self.num_basis}")
        if self.iterations < 0 or self.batch_pixels < 1:
            raise InputError("iterations must be >= 0 and batch_pixels >= 1")
        if not all(value > 0 for value in (self.normal_lr, self.weight_lr, self.brdf_lr, self.specular_lr, self.initial_specular)):
            raise InputError("learning rates and initial_specular must be positive")
        if not 0 < self.final_lr_fraction <= 1:
            raise InputError(f"final_lr_fraction must be in (0, 1], got {self.final_lr_fraction}")
        if self.tv_weight < 0:
            raise InputError(f"tv_weight must be non-negative, got {self.tv_weight}")
        if not 0 < self.min_roughness < self.initial_roughness < 1:
            raise InputError("need 0 < min_roughness < initial_roughness < 1")
        if not all(0 <= at < 1 for at in self.normal_search_at):
            raise InputError("normal_search_at fractions must lie in [0, 1)")
        if not 0 < self.search_max_fraction <= 1:
            raise InputError(f"search_max_fraction must be in (0, 1], got {self.search_max_fraction}")
        if self.search_candidates < 4 or self.search_residual_ratio <= 0 or not 0 < self.search_refine_deg < 90:
            raise InputError("search_candidates >= 4, search_residual_ratio > 0 and 0 < search_refine_deg < 90 needed")
        if not 0 < self.initial_weight < 1:
            raise InputError(f"initial_weight must be in (0, 1), got {self.initial_weight}")


@dataclass(frozen=True, eq=False)
class InitialEstimate:
    """Per-pixel starting point shared by all candidate models of one scene.

    Attributes:
        normal: (N, 3) unit normals from analytic photometric stereo, camera frame.
        albedo: (N, 3) diffuse albedo rho_d = pi * a (PS albedo a absorbs the 1 / pi).
        valid: (N,) bool, the PS solution is usable.
        seconds: wall time of the estimate.
    """

    normal: torch.Tensor
    albedo: torch.Tensor
    valid: torch.Tensor
    seconds: float


def olat_least_squares(captures, plan: EmissionPlan, points, lights, falloff, shadow_threshold: float = 1e-5,
                       saturation_threshold: float = 0.999, reweight_steps: int = 3, chunk_pixels: int = 4096):
    """Near-field Woodham photometric stereo for captures that light one superpixel per pattern.

    Per pixel, y[m, c] = I[m, c] / E[m, k_m, c] = a_c f_m (l_m . n) on lit equations. The
    channel-mean of y is fitted by least squares for g = mean(a) n over equations that are lit
    (above ``shadow_threshold``: attached shadows read 0) and unsaturated; iteratively reweighted
    least squares with Cauchy weights then discounts specular highlights (large positive
    residuals). Finally a_c = sum_m w y s / sum_m w s^2 with s = f (l . n)+ and the final weights w.
    An equation counts as lit when at least one channel is above the threshold.

    Args:
        captures: (M, N, 3) captures in [0, 1].
        plan: emission plan of an OLAT-style emission (``plan.gain`` is not None).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff, positive and finite over the scene (else ``InputError``).
        shadow_threshold: captures at or below this are shadowed. Deliberately tiny: with auto
            exposure set by specular highlights, the diffuse captures of a glossy object are dim
            (1e-4..1e-3) but carry the normal; a cut near 1e-3 leaves only highlights (40 degrees
            error on a glossy blob against 11 with this default).
        saturation_threshold: captures at or above this are saturated.
        reweight_steps: IRLS steps after the plain least squares.
        chunk_pixels: pixels solved at once.

    Returns:
        normal (N, 3) unit, albedo a (N, 3) (rho / pi), valid (N,) bool.
    """
    count = captures.shape[1]
    normal = torch.empty((count, 3), dtype=torch.float64)
    albedo = torch.empty((count, 3), dtype=torch.float64)
    valid = torch.empty(count, dtype=torch.bool)
    gain = plan.gain.detach().double()  # (M, 3)
    plan_lights = lights.double()[plan.light_index]
    for start in range(0, count, chunk_pixels):
        block = slice(start, start + chunk_pixels)
        observed = captures[:, block].double().permute(1, 0, 2)  # (B, M, 3)
        light_dirs, distance = light_geometry(points[block].double(), plan_lights, 1e-3)
        values = torch.as_tensor(falloff(distance), dtype=torch.float64)
        check_falloff_values(values, distance)
        lighting = light_dirs * values[..., None]  # f l, (B, M, 3)
        positive_gain = gain > 0
        ratio = torch.where(positive_gain, observed / gain.clamp_min(1e-30), torch.zeros((), dtype=torch.float64))  # y, (B, M, 3)
        grey = ratio.sum(-1) / positive_gain.sum(-1).clamp_min(1)
        # Lit in at least one channel (a saturated red object reads 0 in green and blue), none saturated.
        usable = ((observed > shadow_threshold).any(-1) & (observed < saturation_threshold).all(-1)).double()
        weight = usable
        solution = torch.zeros((observed.shape[0], 3), dtype=torch.float64)
        for step in range(reweight_steps + 1):
            system = torch.einsum("bm,bmi,bmj->bij", weight, lighting, lighting)
            rhs = torch.einsum("bm,bm,bmi->bi", weight, grey, lighting)
            damping = 1e-9 * system.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(1e-30) / 3
            system = system + damping[:, None, None] * torch.eye(3, dtype=torch.float64)
            solution = torch.linalg.solve(system, rhs[..., None]).squeeze(-1)
            if step == reweight_steps:
                break
            residual = grey - (lighting * solution[:, None]).sum(-1)
            scale = (residual.abs() * usable).sum(-1, keepdim=True) / usable.sum(-1, keepdim=True).clamp_min(1)
            weight = usable / (1.0 + (residual / (2.0 * scale + 1e-30)).square())
        length = solution.norm(dim=-1)
        unit = solution / length[:, None].clamp_min(1e-30)
        shading = (lighting * unit[:, None]).sum(-1).clamp_min(0.0) * usable  # (B, M)
        # The final IRLS weights keep specular highlights out of the per-channel albedo too (it
        # seeds the clustering of materials).
        weighted_shading = weight * shading
        channel_albedo = (ratio * weighted_shading[..., None]).sum(1) / (weighted_shading * shading).sum(1)[:, None].clamp_min(1e-30)
        good = (usable.sum(-1) >= 3) & (length > 0) & torch.isfinite(unit).all(-1)
        normal[block] = torch.where(good[:, None], unit, torch.zeros((), dtype=torch.float64))
        albedo[block] = torch.where(good[:, None], channel_albedo.clamp_min(0.0), torch.zeros((), dtype=torch.float64))
        valid[block] = good
    view = view_directions(points.double(), _EPS)
    valid &= (normal * view).sum(-1) > 0
    return normal, albedo, valid


def fill_from_neighbours(values: torch.Tensor, known: torch.Tensor, pixel_index: torch.Tensor, height: int, width: int,
                         max_rounds: int = 1000) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill unknown pixels with the mean of their known 4-neighbours, growing inwards round by round.

    Args:
        values: (N, D) per-pixel values.
        known: (N,) bool, pixels whose values are trusted.
        pixel_index: (N,) flat indices of the pixels in the H x W image.
        height, width: image size.
        max_rounds: cap on rounds (each fills the unknown pixels next to known ones).

    Returns:
        filled values (N, D) and the (N,) bool of pixels that now have a value (unreachable
        pixels, in mask components without any known pixel, keep their value and stay False).
    """
    right_down = grid_neighbours(pixel_index, height, width)
    count = values.shape[0]
    pairs = torch.cat([torch.stack([torch.arange(count), right_down[:, i]], 1) for i in range(2)])
    pairs = pairs[pairs[:, 1] >= 0]
    source = torch.cat([pairs[:, 0], pairs[:, 1]])  # both directions: left/up are the reverse pairs
    target = torch.cat([pairs[:, 1], pairs[:, 0]])
    values, known = values.clone(), known.clone()
    for _ in range(max_rounds):
        if bool(known.all()):
            break
        usable = known[source] & ~known[target]
        if not bool(usable.any()):
            break
        total = torch.zeros_like(values).index_add_(0, target[usable], values[source[usable]])
        hits = torch.zeros(count, dtype=values.dtype).index_add_(0, target[usable], torch.ones(int(usable.sum()), dtype=values.dtype))
        newly = hits > 0
        values[newly] = total[newly] / hits[newly, None]
        known = known | newly
    return values, known


def into_visible_hemisphere(normal: torch.Tensor, view: torch.Tensor, margin: float) -> torch.Tensor:
    """Tilt unit normals (N, 3) towards the view (N, 3) until n . v >= margin, keeping their azimuth.

    A start with n . v <= 0 sits where the specular lobe is masked to zero (the surface is not
    seen), so it has no specular gradient to leave by.
    """
    cosine = (normal * view).sum(-1, keepdim=True)
    tangent = normal - cosine * view
    length = tangent.norm(dim=-1, keepdim=True)
    tilted = margin * view + math.sqrt(1.0 - margin * margin) * tangent / length.clamp_min(1e-12)
    return torch.where((cosine < margin) & (length > 1e-6), tilted, torch.where(cosine < margin, view, normal))


def initial_estimate(captures, emission, points, lights, falloff, ps_config: PSConfig = PSConfig(),
                     pixel_index: torch.Tensor | None = None, height: int | None = None, width: int | None = None,
                     visible_margin: float = 0.2) -> InitialEstimate:
    """Analytic photometric stereo as the starting point (DESIGN section 4).

    Multiplexed patterns use ``reconstruct.photometric_stereo.solve_ps``; emissions that light one
    superpixel per pattern (OLAT stacks) use ``olat_least_squares`` (Woodham), which is exact for
    them and much faster than treating M = K one-hot patterns as a multiplexed set. Invalid pixels
    (dark, ill-conditioned...) take the mean normal and albedo of valid 4-neighbours, grown inwards
    (``fill_from_neighbours``) when the image grid is given; otherwise, or where no valid pixel is
    reachable, they face the camera with the median albedo. Every normal is then tilted into
    n . v >= ``visible_margin`` (``into_visible_hemisphere``). The solve does not depend on the
    emission's units.

    Args:
        captures: (M, N, 3) captures in [0, 1].
        emission: (M, K, 3) effective emission.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff.
        ps_config: photometric-stereo settings (multiplexed patterns).
        pixel_index: optional (N,) flat indices of the pixels in the H x W image.
        height, width: image size (with ``pixel_index``).
        visible_margin: least n . v of a starting normal.

    Returns:
        InitialEstimate (float32); ``valid`` marks the pixels photometric stereo solved itself.
    """
    start = time.perf_counter()
    check_array("emission", emission, ("M", "K", 3), value_range=(0.0, math.inf))
    if emission.shape[0] == 0:
        raise InputError("initial_estimate needs at least one pattern")
    # Solve with an emission peak near one (a power of two: exact), so that float32 moments
    # neither under- nor overflow whatever its units; the albedo scales back exactly.
    maximum = float(emission.detach().amax())
    peak = 2.0 ** math.frexp(maximum)[1] if maximum > 0 else 1.0
    emission = (emission.double() / peak).to(emission.dtype)
    with torch.no_grad():
        plan = EmissionPlan(emission.detach())
        if plan.gain is not None:
            normal, albedo, valid = olat_least_squares(captures.detach(), plan, points, lights, falloff,
                                                       saturation_threshold=ps_config.saturation_threshold)
        else:
            result = solve_ps(captures.detach(), emission.detach(), points, lights, falloff, ps_config)
            normal, albedo, valid = result.normal, result.albedo, result.valid
    valid = valid & torch.isfinite(normal).all(-1) & torch.isfinite(albedo).all(-1)
    points = points.float()
    view = view_directions(points, _EPS)
    normal = torch.where(valid[:, None], normal.float(), view)
    albedo = torch.where(valid[:, None], math.pi * albedo.float(), torch.zeros((), dtype=torch.float32))
    filled = valid
    if pixel_index is not None and bool(valid.any()):
        both, filled = fill_from_neighbours(torch.cat([normal, albedo], 1), valid, pixel_index.long(), height, width)
        normal = torch.where(filled[:, None], both[:, :3], view)
        albedo = both[:, 3:]
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    fill = albedo[valid].median(0).values if bool(valid.any()) else torch.full((3,), 0.5)
    albedo = torch.where(filled[:, None], albedo, fill)
    normal = into_visible_hemisphere(normal, view, visible_margin)
    return InitialEstimate(normal, (albedo.double() / peak).float(), valid, time.perf_counter() - start)


def hue_saturation_features(albedo: torch.Tensor) -> np.ndarray:
    """(N, 2) colour-wheel coordinates (s cos h, s sin h) of RGB albedos (N, 3) (brightness-free).

    Hue is an angle, so it is clustered as a point on the colour wheel, not as a number that wraps.
    """
    from kornia.color import rgb_to_hsv

    scaled = albedo.detach().float().clamp_min(0.0)
    scaled = scaled / scaled.max().clamp_min(1e-12)
    hsv = rgb_to_hsv(scaled.T.reshape(1, 3, -1, 1)).reshape(3, -1)  # hue in [0, 2 pi], saturation in [0, 1]
    hue, saturation = hsv[0], hsv[1]
    return torch.stack([saturation * torch.cos(hue), saturation * torch.sin(hue)], dim=1).numpy().astype(np.float64)


def cluster_albedo(albedo: torch.Tensor, valid: torch.Tensor, num_basis: int, seed: int = 0,
                   restarts: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """k-means on hue and saturation: cluster labels and per-cluster diffuse albedos.

    Args:
        albedo: (N, 3) pseudo-diffuse albedo rho_d.
        valid: (N,) bool, pixels whose albedo is trusted (others are assigned to the nearest centre).
        num_basis: J clusters.
        seed: k-means seed (k-means++ initialisation); restart r uses seed + r.
        restarts: k-means runs; the one with the least within-cluster sum of squares is kept.

    Returns:
        labels: (N,) long in [0, J).
        centres: (J, 3) median rho_d of each cluster (the overall median for an empty cluster).
    """
    from scipy.cluster.vq import kmeans2, vq

    features = hue_saturation_features(albedo)
    trusted = features[valid.numpy()] if bool(valid.any()) else features
    overall = albedo[valid].median(0).values if bool(valid.any()) else albedo.median(0).values
    if num_basis == 1 or len(trusted) <= num_basis:
        labels = np.zeros(len(features), dtype=np.int64) if num_basis == 1 or len(trusted) == 0 else np.arange(len(features)) % num_basis
    else:
        best_distortion, centroids = math.inf, None
        for attempt in range(restarts):  # k-means++ lands in local minima: keep the tightest of a few
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # an empty cluster is handled below
                candidate, _ = kmeans2(trusted, num_basis, iter=20, minit="++", seed=seed + attempt)
            distortion = float(np.square(vq(trusted, candidate)[1]).sum())
            if distortion < best_distortion:
                best_distortion, centroids = distortion, candidate
        labels, _ = vq(features, centroids)
    labels = torch.as_tensor(labels, dtype=torch.int64)
    centres = torch.empty((num_basis, 3), dtype=albedo.dtype)
    for j in range(num_basis):
        members = (labels == j) & valid
        if not bool(members.any()):
            members = labels == j
        centres[j] = albedo[members].median(0).values if bool(members.any()) else overall
    return labels, centres.clamp_min(1e-4)


def least_squares_albedos(captures, emission, points, lights, falloff, normal, labels, num_basis: int, specular: bool,
                          roughness: float, saturation_threshold: float = 0.999, max_pixels: int = 16384, seed: int = 0):
    """Basis albedos that best explain the captures at fixed normals, hard labels and roughness.

    With normals, one-hot weights and roughness fixed, the images are linear in the albedos of
    each cluster j: I[m, n, c] = rho_d[j, c] A[m, n, c] + rho_s[j] S[m, n, c], A the image of a
    unit diffuse albedo and S that of a unit specular albedo. Each cluster's 4 x 4 (or, for
    Lambertian bases, per-channel 1 x 1) normal equations are solved over unsaturated equations of
    up to ``max_pixels`` random pixels; a negative rho_s is set to 0 and rho_d re-solved alone.

    Args:
        captures: (M, N, 3) captures.
        emission: (M, K, 3) effective emission.
        points, lights, falloff: geometry (see ``render_under_patterns``).
        normal: (N, 3) unit normals.
        labels: (N,) long cluster of each pixel in [0, J).
        num_basis: J.
        specular: also solve rho_s.
        roughness: the roughness the specular images are rendered with.
        saturation_threshold: captures at or above this are left out.
        max_pixels: pixels used (a seeded random subset when there are more).
        seed: seed of that subset.

    Returns:
        diffuse (J, 3) >= 0, specular (J,) >= 0 (zeros when ``specular`` is False), and
        ``solved`` (J,) bool: False for clusters without pixels, whose albedos are 0 and mean
        nothing (the caller keeps its own start there).
    """
    count = captures.shape[1]
    if count > max_pixels:
        subset = torch.randperm(count, generator=torch.Generator().manual_seed(seed))[:max_pixels]
        captures, points, normal, labels = captures[:, subset], points[subset], normal[subset], labels[subset]
    with torch.no_grad():
        ones = torch.ones((normal.shape[0], 1))
        unit_diffuse = render_under_patterns(normal, points, lights, emission, ones, torch.ones((1, 3)), None,
                                             torch.ones(1), falloff)
        unit_specular = None
        if specular:
            unit_specular = render_under_patterns(normal, points, lights, emission, ones, torch.zeros((1, 3)), torch.ones(1),
                                                  torch.full((1,), roughness), falloff)
    usable = (captures < saturation_threshold).to(captures.dtype)  # (M, N, 3)

    def per_cluster(values):  # (M, N, 3) -> (J, 3) sums over patterns and pixels of each cluster
        return torch.zeros((num_basis, 3), dtype=torch.float64).index_add_(0, labels, values.double().sum(0))

    a_a, a_i = per_cluster(usable * unit_diffuse**2), per_cluster(usable * unit_diffuse * captures)
    diffuse = a_i / a_a.clamp_min(1e-30)
    rho_s = torch.zeros(num_basis, dtype=torch.float64)
    if specular:
        a_s = per_cluster(usable * unit_diffuse * unit_specular)
        s_s = per_cluster(usable * unit_specular**2).sum(1)
        s_i = per_cluster(usable * unit_specular * captures).sum(1)
        # Eliminate rho_d per channel: (S.S - sum_c (A.S)_c^2 / (A.A)_c) rho_s = S.I - sum_c (A.S)_c (A.I)_c / (A.A)_c.
        ratio = a_s / a_a.clamp_min(1e-30)
        reduced = (s_s - (ratio * a_s).sum(1)).clamp_min(1e-30)
        rho_s = ((s_i - (ratio * a_i).sum(1)) / reduced).clamp_min(0.0)
        diffuse = (a_i - rho_s[:, None] * a_s) / a_a.clamp_min(1e-30)
    solved = torch.bincount(labels, minlength=num_basis) > 0
    return diffuse.clamp_min(0.0).float(), rho_s.float(), solved


class BasisModel(torch.nn.Module):
    """Unconstrained parameters of normals, simplex weights and J basis BRDFs.

    normals = raw / |raw|; weights = softmax(logits); rho_d = exp(log_diffuse); rho_s =
    exp(log_specular) (absent for Lambertian bases); r = r_min + (1 - r_min) sigmoid(theta).
    """

    def __init__(self, normal, labels, centres, config: FitConfig, specular_init: torch.Tensor | None = None):
        super().__init__()
        count, num_basis = normal.shape[0], config.num_basis
        self.min_roughness = config.min_roughness
        self.normal_raw = torch.nn.Parameter(normal.detach().float().clone())
        # Logit L for the own cluster so that its softmax weight is initial_weight.
        own = math.log(config.initial_weight * max(num_basis - 1, 1) / (1.0 - config.initial_weight)) if num_basis > 1 else 0.0
        logits = torch.zeros((count, num_basis))
        logits[torch.arange(count), labels] = own
        self.weight_logits = torch.nn.Parameter(logits)
        self.log_diffuse = torch.nn.Parameter(centres.detach().float().clamp_min(1e-4).log())
        if specular_init is None:
            specular_init = torch.full((num_basis,), config.initial_specular)
        floor = config.initial_specular * config.specular_floor
        self.log_specular = torch.nn.Parameter(specular_init.float().clamp_min(floor).log()) if config.specular else None
        fraction = (config.initial_roughness - config.min_roughness) / (1.0 - config.min_roughness)
        self.roughness_logit = torch.nn.Parameter(torch.full((num_basis,), math.log(fraction / (1.0 - fraction))))

    @classmethod
    def from_result(cls, result: "InverseRenderResult", config: FitConfig) -> "BasisModel":
        """A model whose parameters reproduce ``result`` (weights floored at 1e-6 before the log)."""
        count = result.normal.shape[0]
        model = cls(result.normal, torch.zeros(count, dtype=torch.int64), result.diffuse.clamp_min(1e-4), config,
                    result.specular if result.specular_enabled else None)
        with torch.no_grad():
            model.weight_logits.copy_(result.weights.float().clamp_min(1e-6).log())
            if model.log_specular is not None:
                model.log_specular.copy_(result.specular.float().clamp_min(1e-8).log())
            fraction = ((result.roughness.float() - config.min_roughness) / (1.0 - config.min_roughness)).clamp(1e-4, 1 - 1e-4)
            model.roughness_logit.copy_(torch.log(fraction / (1.0 - fraction)))
        return model

    def normals(self, index=None) -> torch.Tensor:
        raw = self.normal_raw if index is None else self.normal_raw[index]
        return raw / raw.norm(dim=-1, keepdim=True).clamp_min(_EPS)

    def weights(self, index=None) -> torch.Tensor:
        logits = self.weight_logits if index is None else self.weight_logits[index]
        return torch.softmax(logits, dim=-1)

    def diffuse(self) -> torch.Tensor:
        return self.log_diffuse.exp()

    def specular(self) -> torch.Tensor | None:
        return None if self.log_specular is None else self.log_specular.exp()

    def roughness(self) -> torch.Tensor:
        return self.min_roughness + (1.0 - self.min_roughness) * torch.sigmoid(self.roughness_logit)


@dataclass(frozen=True, eq=False)
class InverseRenderResult:
    """A fitted basis-BRDF scene (float32, detached).

    Attributes:
        normal: (N, 3) unit normals, camera frame.
        weights: (N, J) basis weights on the simplex.
        diffuse: (J, 3) basis diffuse albedos rho_d (scene radiometric units).
        specular: (J,) basis specular albedos rho_s (zeros for a Lambertian model).
        roughness: (J,) basis perceptual roughness.
        specular_enabled: False for a Lambertian model (no lobes are rendered).
        far_field: the model was fitted with far-field shading.
        loss_history: per-step total loss.
        rmse_history: per-step RMSE data term (full scale 1).
        seconds: wall time of the optimisation (without the initial estimate), setup included.
        setup_seconds: the part of ``seconds`` before the first step (clusters, least-squares
            albedos, shading constants).
        normals_searched: pixels whose normal the global search changed (all rounds).
    """

    normal: torch.Tensor
    weights: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor
    roughness: torch.Tensor
    specular_enabled: bool
    far_field: bool
    loss_history: list = field(default_factory=list)
    rmse_history: list = field(default_factory=list)
    seconds: float = 0.0
    setup_seconds: float = 0.0
    normals_searched: int = 0

    @property
    def num_basis(self) -> int:
        return int(self.diffuse.shape[0])

    def render(self, points, lights, emission, falloff, chunk_pixels: int = RENDER_CHUNK_PIXELS) -> torch.Tensor:
        """(M, N, 3) noise-free, unclipped images of the fitted scene under ``emission`` (M, K, 3)."""
        with torch.no_grad():
            return render_under_patterns(
                self.normal, points.float(), lights.float(), emission.float(), self.weights, self.diffuse,
                self.specular if self.specular_enabled else None, self.roughness, falloff, self.far_field, chunk_pixels,
            )

    def describe(self) -> dict:
        """JSON-ready basis BRDF parameters."""
        return {
            "J": self.num_basis,
            "specular": self.specular_enabled,
            "far_field": self.far_field,
            "diffuse_albedo": self.diffuse.tolist(),
            "specular_albedo": self.specular.tolist(),
            "roughness": self.roughness.tolist(),
        }


# ----------------------------------------------------------------------------------------------
# Fit
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class FitProblem:
    """What a fit is fitted to: captures under known emission, and the geometry they were taken of.

    One object serves the final fit, every candidate of model selection and its scoring, so the
    eight inputs travel together instead of being repeated through every signature.

    Attributes:
        captures: (M, N, 3) captures of the masked pixels in [0, 1] (1 = saturated).
        emission: (M, K, 3) effective emission (see ``fit_inverse_render``).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff (positive and finite over the scene).
        pixel_index: (N,) flat indices of the pixels in the H x W image.
        height, width: image size.
    """

    captures: torch.Tensor
    emission: torch.Tensor
    points: torch.Tensor
    lights: torch.Tensor
    falloff: Callable
    pixel_index: torch.Tensor
    height: int
    width: int

    def patterns(self, index: torch.Tensor) -> "FitProblem":
        """The same scene with only the patterns (captures and emission rows) ``index``."""
        return FitProblem(self.captures[index], self.emission[index], self.points, self.lights, self.falloff,
                          self.pixel_index, self.height, self.width)

    def initial_estimate(self) -> "InitialEstimate":
        """``initial_estimate`` of these captures, with the image grid for filling invalid pixels."""
        return initial_estimate(self.captures, self.emission, self.points, self.lights, self.falloff,
                                pixel_index=self.pixel_index, height=self.height, width=self.width)

    def fit(self, config: "FitConfig" = None, initial: "InitialEstimate | None" = None, log=None,
            warm_start: "InverseRenderResult | None" = None) -> "InverseRenderResult":
        """``fit_inverse_render`` of this problem."""
        return fit_inverse_render(self.captures, self.emission, self.points, self.lights, self.falloff, self.pixel_index,
                                  self.height, self.width, FitConfig() if config is None else config, initial, log, warm_start)

    def relight(self, result: "InverseRenderResult", emission: torch.Tensor) -> torch.Tensor:
        """(V, N, 3) noise-free, unclipped images of a fitted ``result`` under other ``emission`` (V, K, 3)."""
        return result.render(self.points, self.lights, emission, self.falloff)


def grid_neighbours(pixel_index: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Right and lower neighbours of masked pixels in the image grid.

    Args:
        pixel_index: (N,) flat indices into the H * W image of the masked pixels.
        height, width: image size.

    Returns:
        (N, 2) long: position (0..N-1) of the right and the lower neighbour, -1 where that
        neighbour is outside the image or the mask.
    """
    position = torch.full((height * width,), -1, dtype=torch.int64)
    position[pixel_index] = torch.arange(pixel_index.numel())
    row, col = pixel_index // width, pixel_index % width
    right = torch.where(col + 1 < width, position[(pixel_index + 1).clamp_max(height * width - 1)], torch.full_like(pixel_index, -1))
    down = torch.where(row + 1 < height, position[(pixel_index + width).clamp_max(height * width - 1)], torch.full_like(pixel_index, -1))
    return torch.stack([right, down], dim=1)


def capture_residual(rendered: torch.Tensor, captures: torch.Tensor, saturated: torch.Tensor) -> torch.Tensor:
    """Rendered minus captured, except that a saturated capture only penalises a darker rendering.

    Args:
        rendered, captures: linear images of one layout, e.g. (N, M, 3) or (M, N, 3), full scale 1.
        saturated: bool, the same shape: the capture reached the saturation threshold.

    Returns:
        The residual, the same shape.
    """
    residual = rendered - captures
    return torch.where(saturated, residual.clamp_max(0.0), residual)


def _check_fit_inputs(captures, emission, points, lights, pixel_index, height, width):
    check_array("captures", captures, ("M", "N", 3))
    check_array("emission", emission, (captures.shape[0], "K", 3), value_range=(0.0, math.inf))
    check_array("points", points, (captures.shape[1], 3))
    check_array("lights", lights, (emission.shape[1], 3))
    check_array("pixel_index", pixel_index, (captures.shape[1],))
    if captures.shape[1] == 0:
        raise InputError("captures hold no pixels")
    if captures.shape[0] == 0 or not bool((torch.as_tensor(emission) > 0).any()):
        raise InputError("the inverse renderer needs at least one pattern with some emitted light")
    if not (isinstance(captures, torch.Tensor) and captures.is_floating_point()):
        raise InputError("captures must be a floating-point torch tensor")
    index = torch.as_tensor(pixel_index)
    if index.is_floating_point() or index.dtype == torch.bool or index.unique().numel() != index.numel():
        raise InputError("pixel_index must hold distinct integer pixel indices")
    if int(pixel_index.min()) < 0 or int(pixel_index.max()) >= height * width:
        raise InputError(f"pixel_index must lie in [0, {height * width}) for a {height} x {width} image")


def fit_inverse_render(
    captures: torch.Tensor,
    emission: torch.Tensor,
    points: torch.Tensor,
    lights: torch.Tensor,
    falloff: Callable,
    pixel_index: torch.Tensor,
    height: int,
    width: int,
    config: FitConfig = FitConfig(),
    initial: InitialEstimate | None = None,
    log: Callable[[int, dict], None] | None = None,
    warm_start: InverseRenderResult | None = None,
) -> InverseRenderResult:
    """Recover normals, basis weights and J basis BRDFs from captures under known patterns.

    Args:
        captures: (M, N, 3) captures of the masked pixels in [0, 1] (1 = saturated).
        emission: (M, K, 3) effective emission E = exposure * scale * (P + B) ** gamma, so that
            noise-free I = sum_k E O; for an OLAT stack, exposure times one-hot rows. Any units
            with a peak in EMISSION_RANGE: the fit runs in albedo units scaled by a power of two
            (``albedo_unit``), so that its settings in albedo units (``initial_specular``, the
            floors) mean the same whatever the emission's units, and returns albedos in the
            caller's units.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff (positive and finite over the scene).
        pixel_index: (N,) flat indices of the pixels in the H x W image (for the TV neighbours).
        height, width: image size.
        config: fit settings.
        initial: the photometric-stereo starting point (computed here when None).
        log: optional callback ``log(step, scalars)`` called every 10 steps and at the end.
        warm_start: start from this result's parameters instead of the photometric-stereo and
            k-means initialisation (its J and specular setting must match ``config``).

    Returns:
        InverseRenderResult.

    Raises:
        InputError: wrong shapes, non-finite inputs, or an emission peak outside EMISSION_RANGE.
    """
    _check_fit_inputs(captures, emission, points, lights, pixel_index, height, width)
    points, lights = points.float(), lights.float()
    captures, emission = captures.detach().float(), emission.detach().float()
    peak = float(emission.amax())
    if not EMISSION_RANGE[0] <= peak <= EMISSION_RANGE[1]:
        raise InputError(f"emission peak {peak:.3g} lies outside [{EMISSION_RANGE[0]:g}, {EMISSION_RANGE[1]:g}], where "
                         "the inverse renderer's float32 albedos stay representable; rescale the emission")
    if warm_start is not None:
        if warm_start.num_basis != config.num_basis or warm_start.specular_enabled != config.specular:
            raise InputError("warm_start must have the same J and specular setting as the config")
        if warm_start.normal.shape[0] != captures.shape[1]:
            raise InputError("warm_start has a different number of pixels than the captures")
        unit = albedo_unit(torch.cat([warm_start.diffuse.flatten(), warm_start.specular.flatten()]))
    else:
        if initial is None:
            initial = initial_estimate(captures, emission, points, lights, falloff, pixel_index=pixel_index, height=height, width=width)
        unit = albedo_unit(initial.albedo[initial.valid].amax(-1) if bool(initial.valid.any()) else initial.albedo.amax(-1))
    # Fit in albedo units near one (the settings and floors are in such units), whatever the
    # emission's units; images are unchanged, the albedos are scaled back below.
    emission = emission * unit
    start = time.perf_counter()
    if warm_start is not None:
        model = BasisModel.from_result(scale_albedos(warm_start, 1.0 / unit), config)
    else:
        model = _initial_model(captures, emission, points, lights, falloff, dataclasses.replace(initial, albedo=initial.albedo / unit), config)
    result = _optimise(model, captures, emission, points, lights, falloff, pixel_index, height, width, config, log, start)
    return scale_albedos(result, unit)


EMISSION_RANGE = (1e-30, 1e30)
"""Emission peaks the inverse renderer accepts (albedos scale inversely and must fit float32)."""
TYPICAL_ALBEDO = 0.5
"""The fit runs in albedo units where the 90th percentile albedo is near this."""


def albedo_unit(albedo: torch.Tensor) -> float:
    """The power of two u that brings the 90th percentile of albedos (any shape) nearest to
    TYPICAL_ALBEDO: the fit runs on albedo / u and emission * u. Albedo is relative to the
    emission, so emission in other units (a raw exposure, another radiometric unit) shifts it by
    the same factor; in units of u the fit's settings in albedo units (``initial_specular``, the
    floors) mean the same for every scene. 1 for physical albedos of a typical bright object."""
    values = albedo.detach().double().flatten()
    values = values[torch.isfinite(values) & (values > 0)]
    if values.numel() == 0:
        return 1.0
    return 2.0 ** round(math.log2(float(values.quantile(0.9)) / TYPICAL_ALBEDO))


def scale_albedos(result: "InverseRenderResult", factor: float) -> "InverseRenderResult":
    """``result`` with its diffuse and specular albedos multiplied by ``factor``."""
    if factor == 1.0:
        return result
    return dataclasses.replace(result, diffuse=result.diffuse * factor, specular=result.specular * factor)


def _initial_model(captures, emission, points, lights, falloff, initial: InitialEstimate, config: FitConfig) -> "BasisModel":
    """k-means clusters and (least-squares) basis albedos at the photometric-stereo start."""
    labels, centres = cluster_albedo(initial.albedo, initial.valid, config.num_basis, config.seed)
    specular_init = None
    if config.least_squares_init:
        diffuse_ls, specular_ls, solved = least_squares_albedos(
            captures, emission, points, lights, falloff, initial.normal, labels, config.num_basis, config.specular,
            config.initial_roughness, config.saturation_threshold, seed=config.seed,
        )
        # The photometric-stereo albedo explains all reflected light as diffuse, so a cluster's
        # diffuse albedo should not exceed it. A least-squares value above it means the specular
        # images at the initial normals and roughness could not take the highlights (weakly
        # constrained by some pattern sets): starting there, the fit settled in a minimum with an
        # over-bright basis (held-out PSNR ~28 dB instead of ~36 with some learned M = 4 sets).
        centres = torch.where(solved[:, None], torch.minimum(diffuse_ls, centres), centres)
        specular_init = specular_ls if config.specular else None
    return BasisModel(initial.normal, labels, centres, config, specular_init)


def cap_directions(count: int, min_cosine: float) -> torch.Tensor:
    """(count, 3) unit vectors spread evenly (Fibonacci spiral) over the cap z >= min_cosine."""
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - index / count * (1.0 - min_cosine)
    azimuth = index * math.pi * (3.0 - math.sqrt(5.0))
    radius = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    return torch.stack([radius * torch.cos(azimuth), radius * torch.sin(azimuth), z], dim=1).float()


def _frames(axis: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) orthonormal frames whose third row is the unit ``axis`` (B, 3)."""
    helper = torch.where(axis[:, :1].abs() < 0.9, torch.tensor([1.0, 0.0, 0.0]), torch.tensor([0.0, 1.0, 0.0]))
    first = torch.linalg.cross(helper.expand_as(axis), axis)
    first = first / first.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    return torch.stack([first, torch.linalg.cross(axis, first), axis], dim=1)


def _candidate_errors(candidates, index, geometry, plan, captures, saturated, weights, diffuse, specular, roughness):
    """Sum of squared residuals (B, C) of candidate unit normals (B, C, 3) of the pixels ``index``."""
    batch, count = candidates.shape[:2]
    repeated = index.repeat_interleave(count)
    rendered = shade_and_contract(candidates.reshape(-1, 3), geometry.take(repeated), plan,
                                  weights[repeated], diffuse, specular, roughness)  # (M, B * C, 3)
    rendered = rendered.reshape(rendered.shape[0], batch, count, 3).permute(1, 2, 0, 3)
    residual = capture_residual(rendered, captures[index][:, None], saturated[index][:, None])
    return residual.square().sum((2, 3))


def search_normals(model: "BasisModel", index: torch.Tensor, geometry: ShadingGeometry, plan: EmissionPlan,
                   pixels_first: torch.Tensor, saturated: torch.Tensor, config: FitConfig, min_cosine: float = 0.1,
                   work: int = 8192) -> torch.Tensor:
    """Global normal search for the pixels ``index`` at the model's current BRDFs and weights.

    Coarse: ``search_candidates`` normals over the visible hemisphere (n . v >= ``min_cosine``,
    in each pixel's view frame) plus the current normal; fine: a quarter as many within
    ``search_refine_deg`` of the best. The lowest sum of squared residuals wins, so no pixel
    gets worse. Changes ``model.normal_raw`` in place.

    Args:
        model: the fit's parameters (normals of all N pixels).
        index: (B,) long, the pixels to search.
        geometry, plan: shading geometry of all N pixels and the patterns' emission.
        pixels_first: (N, M, 3) captures, pixel-major.
        saturated: (N, M, 3) bool, saturated captures (``capture_residual``).
        config: search settings (``search_candidates``, ``search_refine_deg``).
        min_cosine: smallest n . v of a candidate.
        work: candidate renderings per batch (bounds the temporaries).

    Returns:
        (B,) bool, the pixels whose normal changed.
    """
    with torch.no_grad():
        weights, diffuse, specular, roughness = model.weights(), model.diffuse(), model.specular(), model.roughness()
        coarse = cap_directions(config.search_candidates, min_cosine)
        fine = cap_directions(max(config.search_candidates // 4, 4), math.cos(math.radians(config.search_refine_deg)))
        changed = torch.zeros(index.numel(), dtype=torch.bool)
        per_chunk = max(1, work // (config.search_candidates + 1))
        for start in range(0, index.numel(), per_chunk):
            chunk = index[start : start + per_chunk]
            current = model.normals(chunk)
            view = geometry.view if geometry.far_field else geometry.view[chunk]
            arguments = (chunk, geometry, plan, pixels_first, saturated, weights, diffuse, specular, roughness)
            best = current
            for directions, axis in ((coarse, view.expand_as(current)), (fine, None)):
                frame = _frames(best if axis is None else axis)
                candidates = torch.cat([best[:, None], torch.einsum("cd,bde->bce", directions, frame)], dim=1)
                errors = _candidate_errors(candidates, *arguments)
                best = candidates[torch.arange(chunk.numel()), errors.argmin(1)]
            moved = (best - current).norm(dim=-1) > 1e-6
            model.normal_raw[chunk[moved]] = best[moved]
            changed[start : start + chunk.numel()] = moved
    return changed


def pixel_rmse(model: "BasisModel", geometry: ShadingGeometry, plan: EmissionPlan, pixels_first, saturated, chunk_pixels: int = 4096) -> torch.Tensor:
    """(N,) RMSE of every pixel's rendering at the model's current parameters, in capture units.

    ``pixels_first`` (N, M, 3) are the captures, pixel-major, and ``saturated`` (N, M, 3) bool
    their saturated entries (``capture_residual``); pixels are rendered ``chunk_pixels`` at a time.
    """
    count = pixels_first.shape[0]
    errors = torch.empty(count)
    with torch.no_grad():
        weights, diffuse, specular, roughness = model.weights(), model.diffuse(), model.specular(), model.roughness()
        for start in range(0, count, chunk_pixels):
            index = torch.arange(start, min(start + chunk_pixels, count))
            rendered = shade_and_contract(model.normals(index), geometry.take(index), plan, weights[index], diffuse, specular, roughness)
            residual = capture_residual(rendered.permute(1, 0, 2), pixels_first[index], saturated[index])
            errors[index] = residual.square().mean((1, 2)).sqrt()
    return errors


def search_round(model: "BasisModel", geometry: ShadingGeometry, plan: EmissionPlan, pixels_first, saturated, config: FitConfig) -> torch.Tensor:
    """One round of normal search: pixels whose RMSE exceeds ``search_residual_ratio`` times the
    median (at most ``search_max_fraction`` of them, worst first) search their normal.
    ``pixels_first`` (N, M, 3) and ``saturated`` (N, M, 3) as in ``pixel_rmse``.

    Returns:
        (S,) long indices of the pixels whose normal changed.
    """
    errors = pixel_rmse(model, geometry, plan, pixels_first, saturated)
    stuck = torch.nonzero(errors > config.search_residual_ratio * errors.median()).squeeze(1)
    limit = max(1, int(config.search_max_fraction * errors.numel()))
    if stuck.numel() > limit:
        stuck = stuck[torch.topk(errors[stuck], limit).indices]
    if stuck.numel() == 0:
        return stuck
    return stuck[search_normals(model, stuck, geometry, plan, pixels_first, saturated, config)]


def _optimise(model, captures, emission, points, lights, falloff, pixel_index, height, width, config: FitConfig, log, start) -> InverseRenderResult:
    """Adam on random pixel batches: RMSE data term plus TV on the normals (module docstring)."""
    plan = EmissionPlan(emission)
    geometry = shading_geometry(points, lights[plan.light_index], falloff, far_field=config.far_field)
    pixels_first = captures.permute(1, 0, 2).contiguous()  # (N, M, 3): batches gather rows
    saturated_all = pixels_first >= config.saturation_threshold
    neighbours = grid_neighbours(pixel_index.long(), height, width)

    groups = [
        {"params": [model.normal_raw], "lr": config.normal_lr},
        {"params": [model.weight_logits], "lr": config.weight_lr},
        {"params": [model.log_diffuse, model.roughness_logit], "lr": config.brdf_lr},
    ]
    if model.log_specular is not None:
        groups.append({"params": [model.log_specular], "lr": config.specular_lr})
    optimiser = torch.optim.Adam(groups, fused=True)
    decay = config.final_lr_fraction ** (1.0 / max(config.iterations, 1))
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimiser, decay)
    generator = torch.Generator().manual_seed(config.seed)
    count = captures.shape[1]
    batch = min(config.batch_pixels, count)
    order = torch.randperm(count, generator=generator)
    cursor = 0
    loss_history, rmse_history = [], []
    search_steps = {int(round(at * config.iterations)) for at in config.normal_search_at}
    searched = 0
    setup_seconds = time.perf_counter() - start
    for step in range(config.iterations):
        # ---- global normal search for pixels stuck far above the typical error
        if step in search_steps:
            moved = search_round(model, geometry, plan, pixels_first, saturated_all, config)
            searched += int(moved.numel())
            if moved.numel():
                state = optimiser.state.get(model.normal_raw, {})
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key][moved] = 0.0  # stale momentum would pull the pixel back

        # ---- batch: the next slice of a random permutation, so every pixel is seen once per epoch
        if batch == count:
            index = None
        else:
            if cursor + batch > count:
                order, cursor = torch.randperm(count, generator=generator), 0
            index = order[cursor : cursor + batch]
            cursor += batch
        batch_geometry = geometry if index is None else geometry.take(index)
        batch_captures = pixels_first if index is None else pixels_first[index]
        batch_saturated = saturated_all if index is None else saturated_all[index]

        # ---- data term: RMSE of the rendered captures
        normal = model.normals(index)
        rendered = shade_and_contract(normal, batch_geometry, plan, model.weights(index), model.diffuse(), model.specular(), model.roughness())
        residual = capture_residual(rendered.permute(1, 0, 2), batch_captures, batch_saturated)
        rmse = torch.sqrt(residual.square().mean() + 1e-12)

        # ---- regulariser: total variation of the normals over right and lower neighbours
        loss = rmse
        if config.tv_weight > 0:
            pairs = neighbours if index is None else neighbours[index]
            present = pairs >= 0
            if bool(present.any()):
                neighbour_normals = model.normals(pairs.clamp_min(0).reshape(-1)).reshape(-1, 2, 3)
                difference = (normal[:, None, :] - neighbour_normals).abs().sum(-1)
                tv = (difference * present).sum() / present.sum()
                loss = loss + config.tv_weight * tv

        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        scheduler.step()
        loss_history.append(float(loss.detach()))
        rmse_history.append(float(rmse.detach()))
        if log is not None and (step % 10 == 0 or step == config.iterations - 1):
            scalars = {"loss/total": loss_history[-1], "loss/rmse": rmse_history[-1]}
            with torch.no_grad():
                for j, value in enumerate(model.roughness().tolist()):
                    scalars[f"basis_{j}/roughness"] = value
                for j, value in enumerate((model.specular() if config.specular else torch.zeros(config.num_basis)).tolist()):
                    scalars[f"basis_{j}/specular_albedo"] = value
                for j, value in enumerate(model.diffuse().mean(1).tolist()):
                    scalars[f"basis_{j}/diffuse_albedo_mean"] = value
            log(step, scalars)

    with torch.no_grad():
        specular = model.specular()
        return InverseRenderResult(
            normal=model.normals().detach().clone(),
            weights=model.weights().detach().clone(),
            diffuse=model.diffuse().detach().clone(),
            specular=specular.detach().clone() if specular is not None else torch.zeros(config.num_basis),
            roughness=model.roughness().detach().clone(),
            specular_enabled=config.specular,
            far_field=config.far_field,
            loss_history=loss_history,
            rmse_history=rmse_history,
            seconds=time.perf_counter() - start,
            setup_seconds=setup_seconds,
            normals_searched=searched,
        )
