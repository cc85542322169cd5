"""The published single-alternation multiplexed photometric stereo, rebuilt as a baseline.

Choi et al. (CVPR 2024) solve each pixel once, without attached shadows, damping or validity
flags (DESIGN section 4): with the (N, K, 3) incident field g_k = f_k l_k precomputed,
1. albedo a_c = max_m I[m, c];
2. normal: batched least squares of the 3M equations a_c (sum_k E[m, k, c] g_k) . n = I[m, c]
   (``torch.linalg.lstsq``), normalised;
3. albedo of each channel: least squares of a_c (sum_k E[m, k, c] max(eps, g_k . n)) = I[m, c].

It is rebuilt here from that description, in the same array layout (an (N, K, 3) tensor and
batched LAPACK solves), so that benchmarks can time the published computation in the same process
as ours (``displex bench``) and tests can check that it reproduces the published accuracy. Use
``reconstruct.photometric_stereo.solve_ps`` for reconstruction.
"""
from __future__ import annotations

import torch

from capture_sim.errors import check_array
from capture_sim.geometry import light_geometry

FORESHORTENING_FLOOR = 1e-8
"""The published albedo step clamps g_k . n to at least this instead of zero."""


def incident_field(points: torch.Tensor, lights: torch.Tensor, falloff) -> torch.Tensor:
    """(N, K, 3) falloff-weighted unit directions f(d_k) l_k from N points to K superpixels.

    Args:
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
    """
    directions, distance = light_geometry(points, lights)
    return directions * falloff(distance.clamp_min(1e-3))[..., None]


def solve_published(captures: torch.Tensor, emission: torch.Tensor, incident: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """One alternation of the published method (see the module docstring).

    Args:
        captures: (M, N, 3) linear captures.
        emission: (M, K, 3) effective emission (exposure included).
        incident: (N, K, 3) from ``incident_field``.

    Returns:
        normal (N, 3) and albedo (N, 3), differentiable in ``captures`` and ``emission``. As
        published, nothing is flagged and rank-deficient pixels give arbitrary values.
    """
    check_array("captures", captures, ("M", "N", 3))
    check_array("emission", emission, (captures.shape[0], "K", 3))
    check_array("incident", incident, (captures.shape[1], emission.shape[1], 3))
    num_patterns, num_pixels, _ = captures.shape
    # Equations are ordered channel-major: row c * M + m.
    radiance = emission.permute(2, 0, 1).reshape(3 * num_patterns, -1)  # (3M, K)
    observed = captures.permute(1, 2, 0).reshape(num_pixels, 3 * num_patterns, 1)  # (N, 3M, 1)
    lighting = radiance @ incident  # (N, 3M, 3)
    albedo = captures.amax(dim=0).repeat_interleave(num_patterns, dim=1)  # (N, 3M)
    normal = torch.linalg.lstsq(lighting * albedo[..., None], observed).solution.squeeze(-1)
    normal = normal / (normal.norm(dim=-1, keepdim=True) + 1e-8)
    foreshortening = (incident @ normal[..., None]).clamp_min(FORESHORTENING_FLOOR)  # (N, K, 1)
    channels = []
    for channel in range(3):
        rows = slice(channel * num_patterns, (channel + 1) * num_patterns)
        exposure = radiance[rows] @ foreshortening  # (N, M, 1)
        channels.append(torch.linalg.lstsq(exposure, observed[:, rows]).solution.reshape(num_pixels))
    return normal, torch.stack(channels, dim=-1)
