"""Cook-Torrance BRDF with a GGX normal distribution (DESIGN section 3).

    f(l, v) = rho_d / pi + rho_s * D(h) * F * G(l, v) / (4 (n.l) (n.v))

with alpha = roughness ** 2 (perceptual roughness, as in most renderers), D the GGX (Trowbridge-Reitz)
distribution, G the Smith masking-shadowing with the Schlick-GGX approximation k = alpha / 2, and
F either constant 1 (rho_s is then the specular albedo) or Schlick's approximation
F = F0 + (1 - F0) (1 - h.v)^5 of a dielectric, F0 = 0.04, with rho_s scaling the lobe. All inputs
broadcast; directions are unit vectors in any common frame.
"""
from __future__ import annotations

import math

import torch

from capture_sim.errors import InputError

_EPS = 1e-6


MIN_ALPHA = 1e-4
"""Smallest GGX width alpha = roughness^2: sharper lobes overflow float32 at their peak."""


def ggx_distribution(n_dot_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution D(h), in 1/sr.

    Args:
        n_dot_h: cos(theta_h) in [-1, 1], any shape.
        alpha: lobe width alpha = roughness^2 > 0, broadcastable with ``n_dot_h``.

    Returns:
        D, the broadcast shape of the inputs.
    """
    a2 = alpha * alpha
    # n.h^2 (a2 - 1) + 1 written without cancellation: in float32 a2 - 1 rounds to -1 for small
    # alpha, and the peak (n.h = 1) became 0 / 0 instead of 1 / (pi a2).
    denom = (1.0 - n_dot_h) * (1.0 + n_dot_h) + n_dot_h * n_dot_h * a2
    return a2 / (math.pi * denom * denom)


def smith_schlick_ggx(n_dot_l: torch.Tensor, n_dot_v: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking-shadowing G with the Schlick-GGX approximation, k = alpha / 2.

    Args:
        n_dot_l, n_dot_v: cosines to the light and the view, in [0, 1], broadcastable.
        alpha: lobe width alpha = roughness^2 > 0, broadcastable with them.

    Returns:
        G in [0, 1], unitless, the broadcast shape of the inputs.
    """
    k = alpha / 2.0
    return (n_dot_l / (n_dot_l * (1.0 - k) + k)) * (n_dot_v / (n_dot_v * (1.0 - k) + k))


FRESNEL_KINDS = ("constant", "schlick")
"""F = 1, or Schlick's approximation of a dielectric (F0 = 0.04)."""


def check_fresnel(fresnel) -> None:
    """Raise ``InputError`` unless ``fresnel`` names one of ``FRESNEL_KINDS``."""
    if fresnel not in FRESNEL_KINDS:
        raise InputError(f"fresnel must be one of {', '.join(FRESNEL_KINDS)}, got {fresnel!r}")


def cook_torrance_specular(
    normal: torch.Tensor,
    light_dir: torch.Tensor,
    view_dir: torch.Tensor,
    roughness: torch.Tensor,
    fresnel: str = "constant",
) -> torch.Tensor:
    """The specular lobe D F G / (4 (n.l)(n.v)) for unit specular albedo.

    Args:
        normal, light_dir, view_dir: (..., 3) unit vectors (broadcast).
        roughness: (...) perceptual roughness in (0, 1]; alpha = roughness ** 2.
        fresnel: ``"constant"`` (F = 1) or ``"schlick"`` (F0 = 0.04, dielectric).

    Returns:
        (...) lobe value per steradian; zero where the light or view is below the surface.
    """
    half = light_dir + view_dir
    half = half / half.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    n_dot_l = (normal * light_dir).sum(-1)
    n_dot_v = (normal * view_dir).sum(-1)
    n_dot_h = (normal * half).sum(-1).clamp(0.0, 1.0)
    alpha = (roughness * roughness).clamp_min(MIN_ALPHA)
    nl, nv = n_dot_l.clamp_min(_EPS), n_dot_v.clamp_min(_EPS)
    lobe = ggx_distribution(n_dot_h, alpha) * smith_schlick_ggx(nl, nv, alpha) / (4.0 * nl * nv)
    if fresnel == "schlick":
        v_dot_h = (view_dir * half).sum(-1).clamp(0.0, 1.0)
        lobe = lobe * (0.04 + 0.96 * (1.0 - v_dot_h) ** 5)
    else:
        check_fresnel(fresnel)
    visible = (n_dot_l > 0) & (n_dot_v > 0)
    return torch.where(visible, lobe, torch.zeros_like(lobe))
