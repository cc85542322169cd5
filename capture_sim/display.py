"""Display model: what a superpixel emits for a set value (DESIGN section 3).

    L = s * (P + B) ** gamma

P is the set value in [0, 1], B the per-superpixel backlight (the panel is never fully black),
gamma the display non-linearity and s a global scale.
"""
from __future__ import annotations

import math

import torch

from capture_sim.errors import InputError, check_array


def display_emission(patterns: torch.Tensor, backlight: torch.Tensor, gamma: float, scale: float = 1.0) -> torch.Tensor:
    """Emitted intensity of every superpixel under every pattern.

    Args:
        patterns: (M, R, C, 3) or (M, K, 3) set values in [0, 1].
        backlight: (R, C) or (K,) backlight B, same for all channels.
        gamma: display non-linearity (reference 2.2).
        scale: global display scale s.

    Returns:
        (M, K, 3) emitted intensity L in light order k = r * C + c, differentiable in ``patterns``.
    """
    check_array("patterns", patterns, ("...", 3), value_range=(0.0, 1.0))
    if len(patterns.shape) not in (3, 4):
        raise InputError(f"patterns: expected shape (M, R, C, 3) or (M, K, 3), got {tuple(patterns.shape)}")
    if not (0 < gamma < math.inf and 0 < scale < math.inf):
        raise InputError(f"display gamma and scale must be positive and finite, got {gamma!r}, {scale!r}")
    flat = torch.as_tensor(patterns).reshape(patterns.shape[0], math.prod(patterns.shape[1:-1]), 3)  # M = 0 too
    light_backlight = torch.as_tensor(backlight, dtype=flat.dtype).reshape(1, -1, 1)
    check_array("backlight", light_backlight, (1, flat.shape[1], 1), value_range=(0.0, 1.0))
    level = flat + light_backlight
    # The floor keeps the gradient finite at a black, backlight-free superpixel when gamma < 1
    # (d/dx x^gamma is infinite at 0); it must not emit: auto exposure would lift tiny^gamma of an
    # all-black set to 0.9 of full scale.
    powered = level.clamp_min(torch.finfo(flat.dtype).tiny) ** gamma
    return scale * torch.where(level > 0, powered, torch.zeros_like(powered))
