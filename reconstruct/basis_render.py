"""Rendering of basis-BRDF scenes under display patterns, the inverse renderer's forward model.

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
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
from torch.utils.checkpoint import checkpoint

from capture_sim.brdf import MIN_ALPHA
from capture_sim.errors import InputError, check_array
from capture_sim.geometry import light_geometry, view_directions
from capture_sim.rig import checked_falloff

RENDER_CHUNK_PIXELS = 4096
"""Pixels shaded at once by ``render_under_patterns``: a few (4096, K) temporaries of ~2.4 MB each."""

NORM_FLOOR = 1e-6
"""Smallest norm (or cosine) a direction, normal or lobe term is divided by (shared by the inverse
renderer's modules)."""


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
        view = view_directions(anchor, NORM_FLOOR)
        for start in range(0, rows, chunk_pixels):
            block = slice(start, start + chunk_pixels)
            light_dirs, distance = light_geometry(anchor[block], lights, min_distance)
            inverse_distance[block] = 1.0 / distance
            # narrow dtypes keep the largest value they hold where a light is millimetres away
            falloff_values[block] = checked_falloff(falloff, distance).clamp(max=torch.finfo(points.dtype).max)
            inverse_half_norm[block] = 1.0 / (light_dirs + view[block, None, :]).norm(dim=-1).clamp_min(NORM_FLOOR)
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
    n_dot_v_safe = n_dot_v.clamp_min(NORM_FLOOR)
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
    # Long vectors are scaled to components of at most 1 first (the norm of a float32 vector of
    # length 1e20 overflows); shorter ones are left exactly as they are.
    scaled = normals / normals.detach().abs().amax(-1, keepdim=True).clamp_min(1.0)
    unit_normals = scaled / scaled.norm(dim=-1, keepdim=True).clamp_min(NORM_FLOOR)

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
    if not chunks:  # no pixels: an empty result that is still on the inputs' graph (backward works)
        inputs = sum(t.sum() * 0 for t in (normals, emission, weights, *basis))
        return normals.new_zeros((emission.shape[0], 0, 3)) + inputs.to(dtype)
    return torch.cat(chunks, dim=1)
