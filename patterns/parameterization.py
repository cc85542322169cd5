"""Unconstrained logits for learning pattern values, and back.

Learning optimises logits z with P = sigmoid(z), which keeps every set value in (0, 1) without
projection. Exact 0 or 1 values (OLAT, binary halves, the default lo = 0 / hi = 1) would map to
infinite logits whose gradient sigmoid'(z) is zero, so an optimiser could never move them (the
published code had this problem); they are first clamped to [eps, 1 - eps]. During learning the
logits are kept within +-``LOGIT_LIMIT`` (``keep_movable``): in float32 sigmoid'(z) is exactly 0
from |z| = 17, where a value would freeze again.
"""
from __future__ import annotations

import torch

from capture_sim.errors import InputError, check_array


LOGIT_LIMIT = 16.0
"""Largest |logit| kept during learning: the largest whole number whose float32 sigmoid gradient
is not 0 (sigmoid'(16) = 1.2e-7, which Adam rescales to a normal step; sigmoid(17) rounds to 1 and
its gradient to exactly 0). Values barely change: sigmoid(16) = 1 - 1.2e-7 in float32, two
float32 steps below 1 (far below one level of a 16-bit display frame)."""


def keep_movable(logits: torch.Tensor) -> None:
    """Clamp learnable logits to +-LOGIT_LIMIT in place (call after each optimiser step)."""
    with torch.no_grad():
        logits.clamp_(-LOGIT_LIMIT, LOGIT_LIMIT)


def patterns_to_logits(patterns: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Logits of set values, with values clamped to [eps, 1 - eps] so every logit stays movable.

    Args:
        patterns: (M, R, C, 3) (or any shape) display set values in [0, 1], float tensor or array.
        eps: clamp margin in (0, 0.5); 1e-3 gives logits within about +-6.9.

    Returns:
        Logits z = log(p / (1 - p)) of the clamped values, same shape; float32 unless the input is
        float64 (tensor or array).

    Example:
        >>> patterns_to_logits(torch.tensor([0.0, 0.5, 1.0]))
        tensor([-6.9068,  0.0000,  6.9068])
    """
    check_array("patterns", patterns, value_range=(0.0, 1.0))
    if not 0.0 < eps < 0.5:
        raise InputError(f"eps must lie in (0, 0.5), got {eps}")
    values = torch.as_tensor(patterns)
    if not values.is_floating_point() or values.dtype not in (torch.float32, torch.float64):
        values = values.to(torch.float32)
    if eps < torch.finfo(values.dtype).eps:  # 1 - eps could round to 1: an infinite logit
        raise InputError(f"eps {eps:g} is below the resolution of {values.dtype} near 1")
    return torch.logit(values.clamp(eps, 1.0 - eps))


def logits_to_patterns(logits: torch.Tensor) -> torch.Tensor:
    """Set values sigmoid(z) in (0, 1) from logits (any shape, e.g. (M, R, C, 3)); same shape."""
    check_array("logits", logits)
    values = torch.as_tensor(logits)
    if values.dtype not in (torch.float32, torch.float64):
        values = values.to(torch.float32)
    return torch.sigmoid(values)
