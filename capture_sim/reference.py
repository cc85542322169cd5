"""Plain, readable reference versions of the fast paths, used only by tests to check them.

Each follows DESIGN section 3 literally with numpy broadcasting in float64.
"""
from __future__ import annotations

import numpy as np


def simulate_noise_free_reference(
    patterns: np.ndarray,
    olat: np.ndarray,
    backlight: np.ndarray,
    gamma: float,
    scale: float,
    exposure: float,
) -> np.ndarray:
    """I_m = clip(e * sum_k s (P_mk + B_k)^gamma O_k) for tiny inputs.

    Args:
        patterns: (M, R, C, 3) set values.
        olat: (K, H, W, 3) OLAT stack, K = R * C.
        backlight: (R, C) backlight.
        gamma, scale, exposure: display and sensor scalars.

    Returns:
        (M, H, W, 3) float64 captures without noise or quantisation.
    """
    num_patterns = patterns.shape[0]
    emitted = scale * (patterns.reshape(num_patterns, -1, 3).astype(np.float64) + backlight.reshape(1, -1, 1)) ** gamma
    images = np.zeros((num_patterns,) + olat.shape[1:], dtype=np.float64)
    for m in range(num_patterns):
        for k in range(olat.shape[0]):
            images[m] += emitted[m, k][None, None, :] * olat[k].astype(np.float64)
    return np.clip(exposure * images, 0.0, 1.0)
