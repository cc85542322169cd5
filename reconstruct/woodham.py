"""Woodham least-squares photometric stereo with calibrated near-field lights (DESIGN section 4).

Per pixel and channel c, g_c = a_c n solves the linear least squares
    I[m, c] = b[m, c] . g_c,    b[m, c] = sum_k E[m, k, c] f_k s_k l_k
over the patterns m whose superpixels light the point (s_k = [l_k . n > 0]); the normal is the
normalised sum of the three g_c, the albedo a_c = |g_c|. For an OLAT stack E is diagonal and b
reduces to e f_k l_k, so the stack is processed light by light without building (K, K) emission.
Attached shadows are re-estimated from the current normal a few times, starting from the lights
that visibly lit the pixel. The reference method for OLAT stacks (M = K).
"""
from __future__ import annotations

import torch

from capture_sim.errors import InputError, check_array
from reconstruct.photometric_stereo import FLAG_NAMES, PSResult

CHUNK = 8192
SHADOW_ITERATIONS = 4
CONDITION_LIMIT = 1e4
DARK_LEVEL = 1e-3
SATURATION_LEVEL = 0.999


def _solve_channels(system: torch.Tensor, rhs: torch.Tensor, damping: float = 1e-9):
    """Damped closed-form solve of (N, 3, 3) systems for (N, 3 channels, 3) right-hand sides."""
    scale = system.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(1e-30) / 3.0
    eye = torch.eye(3, dtype=system.dtype)
    damped = system + (damping * scale)[:, None, None] * eye
    solution = torch.linalg.solve(damped, rhs.transpose(1, 2)).transpose(1, 2)  # (N, 3ch, 3)
    eigen = torch.linalg.eigvalsh(damped)
    condition = eigen[:, -1].clamp_min(1e-30) / eigen[:, 0].clamp_min(1e-30 * scale)
    return solution, condition


def _result(g: torch.Tensor, condition: torch.Tensor, captures: torch.Tensor, points: torch.Tensor) -> PSResult:
    """Normals, albedo, validity and flags from per-channel solutions g (N, 3, 3)."""
    summed = g.sum(1)
    length = summed.norm(dim=-1)
    normal = summed / length.clamp_min(1e-30)[:, None]
    view = -points / points.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    brightest = captures.amax(dim=(0, 2))
    flags = {name: torch.zeros(points.shape[0], dtype=torch.bool) for name in FLAG_NAMES}
    flags["dark"] = brightest < DARK_LEVEL
    flags["saturated"] = (captures >= SATURATION_LEVEL).any(dim=(0, 2))
    flags["ill_conditioned"] = ~(condition < CONDITION_LIMIT)
    flags["back_facing"] = (normal * view).sum(-1) <= 0
    flags["bad_geometry"] = points[:, 2] <= 1e-3
    valid = ~(flags["dark"] | flags["ill_conditioned"] | flags["back_facing"] | flags["bad_geometry"] | (length <= 0))
    fallback = torch.tensor([0.0, 0.0, -1.0], dtype=normal.dtype)
    normal = torch.where(valid[:, None], normal, fallback)
    albedo = torch.where(valid[:, None], (g * normal[:, None, :]).sum(-1).clamp_min(0.0), torch.zeros_like(summed))
    condition = torch.nan_to_num(condition, nan=1e30, posinf=1e30).clamp(1.0, 1e30)
    return PSResult(normal=normal, albedo=albedo, valid=valid, condition=condition, flags=flags)


def _geometry(points: torch.Tensor, lights: torch.Tensor, falloff):
    offset = lights[None] - points[:, None]
    distance = offset.norm(dim=-1).clamp_min(1e-3)
    return offset / distance[..., None], falloff(distance)


def solve_woodham_olat(captures: torch.Tensor, points: torch.Tensor, lights: torch.Tensor, falloff, exposure: float = 1.0) -> PSResult:
    """Woodham least squares on an OLAT stack.

    Args:
        captures: (K, N, 3) OLAT captures in [0, 1] of N pixels, image k lit by superpixel k alone
            at unit intensity times ``exposure`` (backlight removed).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
        exposure: exposure e of the captures.

    Returns:
        PSResult of (N, ...) tensors; albedo in units of the OLAT stack (a = rho / pi).
    """
    check_array("captures", captures, (lights.shape[0], "N", 3), value_range=(0.0, float("inf")))
    check_array("points", points, (captures.shape[1], 3))
    results = []
    for start in range(0, captures.shape[1], CHUNK):
        block = slice(start, start + CHUNK)
        intensity = captures[:, block].permute(1, 0, 2).double()  # (n, K, 3)
        light_dirs, fall = _geometry(points[block].double(), lights.double(), falloff)
        grey = intensity.mean(-1)
        usable = intensity.amax(-1) < SATURATION_LEVEL
        lit = (grey > 0.02 * grey.amax(-1, keepdim=True)) & usable
        for _ in range(SHADOW_ITERATIONS):
            weight = lit.double() * exposure * fall  # (n, K): b_k = e f_k l_k
            system = torch.einsum("nk,nki,nkj->nij", weight * weight, light_dirs, light_dirs)
            rhs = torch.einsum("nk,nkc,nki->nci", weight, intensity, light_dirs)
            g, condition = _solve_channels(system, rhs)
            normal = g.sum(1) / g.sum(1).norm(dim=-1, keepdim=True).clamp_min(1e-30)
            lit = ((light_dirs * normal[:, None]).sum(-1) > 0) & usable
        results.append(_result(g, condition, captures[:, block].double(), points[block].double()))
    return _concatenate(results, captures.dtype)


def solve_woodham(captures: torch.Tensor, emission: torch.Tensor, points: torch.Tensor, lights: torch.Tensor, falloff) -> PSResult:
    """Woodham least squares for M >= 3 patterns, per channel (needs rank 3 in every channel).

    Args:
        captures: (M, N, 3) captures in [0, 1].
        emission: (M, K, 3) effective emission (exposure included).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.

    Returns:
        PSResult of (N, ...) tensors.
    """
    check_array("captures", captures, ("M", "N", 3), value_range=(0.0, float("inf")))
    check_array("emission", emission, (captures.shape[0], lights.shape[0], 3), value_range=(0.0, float("inf")))
    if captures.shape[0] < 3:
        raise InputError(f"Woodham needs at least 3 patterns, got {captures.shape[0]}")
    results = []
    for start in range(0, captures.shape[1], CHUNK):
        block = slice(start, start + CHUNK)
        intensity = captures[:, block].permute(1, 0, 2).double()  # (n, M, 3)
        light_dirs, fall = _geometry(points[block].double(), lights.double(), falloff)
        usable = (intensity < SATURATION_LEVEL).double()
        lit = (light_dirs * -points[block].double()[:, None]).sum(-1) > 0  # start: lights the camera side sees
        for _ in range(SHADOW_ITERATIONS):
            b = torch.einsum("nk,mkc,nki->nmci", lit.double() * fall, emission.double(), light_dirs)
            weighted = b * usable[..., None]
            system = torch.einsum("nmci,nmcj->ncij", weighted, b)  # per-channel normal equations
            rhs = torch.einsum("nmc,nmci->nci", intensity * usable, b)
            solutions = [_solve_channels(system[:, c], rhs[:, c : c + 1]) for c in range(3)]
            g = torch.cat([solution for solution, _ in solutions], dim=1)
            condition = torch.stack([cond for _, cond in solutions]).amax(0)
            normal = g.sum(1) / g.sum(1).norm(dim=-1, keepdim=True).clamp_min(1e-30)
            lit = (light_dirs * normal[:, None]).sum(-1) > 0
        results.append(_result(g, condition, captures[:, block].double(), points[block].double()))
    return _concatenate(results, captures.dtype)


def _concatenate(results: list[PSResult], dtype) -> PSResult:
    return PSResult(
        normal=torch.cat([r.normal for r in results]).to(dtype),
        albedo=torch.cat([r.albedo for r in results]).to(dtype),
        valid=torch.cat([r.valid for r in results]),
        condition=torch.cat([r.condition for r in results]).to(dtype),
        flags={name: torch.cat([r.flags[name] for r in results]) for name in FLAG_NAMES},
    )
