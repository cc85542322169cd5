"""Fixed-iteration analytic photometric stereo for learning: fast, vectorised, unrolled gradients.

Same model as ``reconstruct.photometric_stereo`` (DESIGN section 4):
    I[m, c] = a_c * b[m, c] . n,     b[m, c] = sum_k E[m, k, c] f_k s_k l_k,   s_k = [l_k . n > 0]
but with fixed iteration counts and no per-pixel restarts, so that a training step over ~10^5
sampled pixels costs a few matrix products:
- b for all pixels comes from ONE matrix product: with u_nk = s_nk f_nk / d_nk and
  l_nk = (p_k - X_n) / d_nk, b[n, m, c] = sum_k u_nk E[m, k, c] p_k - X_n sum_k u_nk E[m, k, c],
  i.e. (N, K) @ (K, 4 * 3 * M);
- the shadow masks and the alternations run without gradient to (near) convergence;
- gradients come from ``grad_alternations`` alternations unrolled from the detached solution with
  the final masks: a truncated implicit gradient, cheap in memory ((N, K) is kept once).
The converged values equal the full solver's on well-posed pixels; training uses this, evaluation
uses ``solve_ps`` (validity flags, restarts, exact implicit gradients).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from capture_sim.errors import check_array


@dataclass(frozen=True)
class UnrolledPSConfig:
    """Iteration counts of ``solve_ps_unrolled``."""

    shadow_iterations: int = 3
    """Attached-shadow mask updates (each followed by ``alternations`` alternations)."""
    alternations: int = 5
    """Albedo/normal alternations per mask, without gradient."""
    grad_alternations: int = 3
    """Alternations unrolled with gradient from the detached solution. With ``alternations = 0``
    and one shadow iteration the start no longer depends on the inputs and the gradient is exact
    (used by the gradient test)."""
    damping: float = 1e-6
    """Tikhonov damping relative to each 3x3 system's trace / 3."""
    saturation_threshold: float = 0.999
    """Captures at or above this get zero weight."""


def _inverse_apply(system: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """Solve (N, 3, 3) symmetric systems for (N, 3) right-hand sides by the adjugate.

    For symmetric A with rows r0, r1, r2 the adjugate's columns are r1 x r2, r2 x r0, r0 x r1.
    """
    r0, r1, r2 = system.unbind(1)
    c0, c1, c2 = torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)
    det = (r0 * c0).sum(-1, keepdim=True)
    solution = c0 * rhs[:, :1] + c1 * rhs[:, 1:2] + c2 * rhs[:, 2:]
    # Callers normalise the result, so the determinant only needs a safe sign and size.
    safe = torch.where(det.abs() > 1e-30, det, torch.full_like(det, 1e-30))
    return solution / safe


def _lighting_vectors(weights: torch.Tensor, table: torch.Tensor, points: torch.Tensor, num_patterns: int) -> torch.Tensor:
    """b (N, M, 3 channels, 3) from u (N, K) and the (K, M * 3 * 4) table [E p_k, E]."""
    mixed = (weights @ table).reshape(-1, num_patterns, 3, 4)
    return mixed[..., :3] - points[:, None, None, :] * mixed[..., 3:]


def _alternate(normal, albedo, moments, rhs_moments, damping, steps):
    """``steps`` albedo/normal alternations on per-channel moments B_c (N,3,3,3), r_c (N,3,3)."""
    eye = torch.eye(3, dtype=normal.dtype)
    # Relative floor, plus an absolute one well above the dtype's underflow for all-dark inputs.
    tiny = 1e-12 * moments.detach().abs().amax() + torch.finfo(moments.dtype).tiny ** 0.5
    for _ in range(steps):
        projected = (moments * normal[:, None, None, :]).sum(-1)  # B_c n: (N, 3, 3); tiny batched matmuls are slower
        quadratic = (projected * normal[:, None, :]).sum(-1)
        albedo = ((rhs_moments * normal[:, None, :]).sum(-1) / (quadratic + tiny)).clamp_min(0.0)
        system = ((albedo * albedo)[..., None, None] * moments).sum(1)
        scale = system.diagonal(dim1=-2, dim2=-1).sum(-1) / 3.0
        system = system + (damping * scale + 1e-30)[:, None, None] * eye
        direction = _inverse_apply(system, (albedo[..., None] * rhs_moments).sum(1))
        # A zero direction (dark pixel) keeps the previous normal: no 0/0 in value or gradient.
        length2 = (direction * direction).sum(-1, keepdim=True)
        usable = length2 > 1e-30
        direction = torch.where(usable, direction, normal.detach())
        normal = direction * torch.rsqrt(torch.where(usable, length2, torch.ones_like(length2)))
    return normal, albedo


def solve_ps_unrolled(captures, emission, points, lights, falloff, config: UnrolledPSConfig = UnrolledPSConfig()):
    """Analytic photometric stereo with fixed iterations (see module docstring).

    Args:
        captures: (M, N, 3) captures in [0, 1].
        emission: (M, K, 3) effective emission (exposure included).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
        config: iteration counts and damping.

    Returns:
        normal (N, 3) unit normals facing the camera, albedo (N, 3) >= 0; finite, differentiable
        in ``captures`` and ``emission``.
    """
    check_array("captures", captures, ("M", "N", 3))
    check_array("emission", emission, (captures.shape[0], lights.shape[0], 3))
    num_patterns = captures.shape[0]
    dtype = captures.dtype
    points, lights = points.to(dtype), lights.to(dtype)
    distance = torch.cdist(points, lights).clamp_min(1e-3)  # (N, K)
    reach = falloff(distance) / distance  # f_k / d_k: with (p_k - X) it gives f_k l_k
    lights_h = torch.cat([lights, torch.ones_like(lights[:, :1])], dim=1)  # (K, 4)
    table = (emission.permute(1, 0, 2)[..., None] * lights_h[:, None, None, :]).reshape(lights.shape[0], -1)  # (K, M*3*4)
    intensity = captures.permute(1, 0, 2)  # (N, M, 3)
    equation_weight = (intensity < config.saturation_threshold).to(dtype)
    view = -points / points.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def moments_for(normal_mask, table_values, values):
        b = _lighting_vectors(reach * normal_mask, table_values, points, num_patterns)
        weighted = (b * equation_weight[..., None]).permute(0, 2, 3, 1)  # (N, 3c, 3, M)
        moments = weighted @ b.permute(0, 2, 1, 3)  # sum_m w b b^T: (N, 3c, 3, 3)
        rhs_moments = (weighted @ values.permute(0, 2, 1)[..., None]).squeeze(-1)  # (N, 3c, 3)
        return moments, rhs_moments

    def in_front(normal):
        # l_k . n > 0  <=>  p_k . n > X . n: one (N, 3) @ (3, K) product instead of (N, K, 3) work.
        return ((normal @ lights.T) > (normal * points).sum(-1, keepdim=True)).to(dtype)

    with torch.no_grad():
        normal = view.clone()
        albedo = torch.ones_like(normal)
        for _ in range(max(1, config.shadow_iterations)):
            lit = in_front(normal)
            moments, rhs_moments = moments_for(lit, table.detach(), intensity.detach())
            normal, albedo = _alternate(normal, albedo, moments, rhs_moments, config.damping, config.alternations)
        lit = in_front(normal)
    moments, rhs_moments = moments_for(lit, table, intensity)
    normal, albedo = _alternate(normal.detach(), albedo.detach(), moments, rhs_moments, config.damping, config.grad_alternations)
    # Keep the camera-facing sign (a flipped solution has the same residual once albedo absorbs it).
    facing = torch.where((normal * view).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(dtype)
    return normal * facing, albedo
