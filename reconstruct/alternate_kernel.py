"""The full solver's alternation to convergence (``pixel_solve.alternate``) as one compiled kernel.

``pixel_solve.alternate`` is the readable torch reference these kernels are tested against. It
runs each alternation as some sixty operations over whole (.., N) rows and gathers the pixels
still moving before the next one; the shadow search calls it for every mask update and restart.
Evaluation solves a few thousand pixels at a time, where each such operation costs more in
dispatch than in arithmetic: at 2500 pixels it took ~40% of a solve. Here every pixel iterates in
registers until it stops, with the same stopping rules, so nothing is gathered. Per pixel the
loop's length varies, so it runs scalar (no SIMD), in parallel over pixels.

The kernel runs the reference's float operations in the same order, without fused multiply-adds
(numba's default), so its values and flags equal the reference's bit for bit (tested).

Arrays are numpy views of contiguous CPU tensors, pixels on the last axis: moment (3, 6, N)
(entries in ``SYMMETRIC_PAIRS`` order), projection (3, 3, N), albedo (3, N). Scalars are passed
in the arrays' dtype, so that float32 arithmetic stays float32. Threads, forked processes and
caching: ``reconstruct.compiled`` (both versions here are cached: they are separate functions).
"""
from __future__ import annotations

import math
import operator

import numpy as np
import torch
from numba import njit, prange

from reconstruct.compiled import compile_kernel, forked, match_torch_threads
from reconstruct.pixel_solve import ABSOLUTE_DAMPING, Moments, widen_stopped
from reconstruct.pixel_solve import alternate as reference_alternate

MAX_ALTERNATIONS = 2 ** 62
"""Cap on ``max_alternations`` (the kernels count in 64-bit integers): no pixel gets there."""
NOT_CONVERGED, CONVERGED, STOPPED = 0, 1, 2
"""Per-pixel status the kernels return: STOPPED is a non-shrinking move above the rounding level
(``pixel_solve.alternate``: iterated again in float64 when the dtype is narrower)."""


@njit(inline="always", error_model="numpy")
def _albedo(moment, projection, n, c, n0, n1, n2, damping, absolute, three, zero):
    """Albedo given normal, channel c: max(0, n . r_c / (n^T B_c n + damping trace(B_c) / 3 + absolute))."""
    numerator = zero + n0 * projection[c, 0, n] + n1 * projection[c, 1, n] + n2 * projection[c, 2, n]
    b00, b11, b22 = moment[c, 0, n], moment[c, 1, n], moment[c, 2, n]
    b01, b02, b12 = moment[c, 3, n], moment[c, 4, n], moment[c, 5, n]
    shading = (b00 * (n0 * n0) + b11 * (n1 * n1) + b22 * (n2 * n2) + b01 * (n0 * n1 + n1 * n0)
               + b02 * (n0 * n2 + n2 * n0) + b12 * (n1 * n2 + n2 * n1))
    ratio = numerator / (shading + damping * (b00 + b11 + b22) / three + absolute)
    return zero if ratio < zero else ratio  # torch's relu: NaN stays NaN


@njit(inline="always", error_model="numpy")
def _alternation(moment, projection, n, a0, a1, a2, damping, tiny, absolute, three):
    """Phi at pixel n (``pixel_solve.alternation``): albedo -> normal -> albedo."""
    # Normal given albedo: (S / s + damping I) x = v / s, S = sum_c a_c^2 B_c, v = sum_c a_c r_c.
    # The sums start from +0 as torch's do, so that a sum of -0.0 terms is +0.0 here too.
    zero = tiny - tiny
    q0, q1, q2 = a0 * a0, a1 * a1, a2 * a2
    s00 = zero + q0 * moment[0, 0, n] + q1 * moment[1, 0, n] + q2 * moment[2, 0, n]
    s11 = zero + q0 * moment[0, 1, n] + q1 * moment[1, 1, n] + q2 * moment[2, 1, n]
    s22 = zero + q0 * moment[0, 2, n] + q1 * moment[1, 2, n] + q2 * moment[2, 2, n]
    s01 = zero + q0 * moment[0, 3, n] + q1 * moment[1, 3, n] + q2 * moment[2, 3, n]
    s02 = zero + q0 * moment[0, 4, n] + q1 * moment[1, 4, n] + q2 * moment[2, 4, n]
    s12 = zero + q0 * moment[0, 5, n] + q1 * moment[1, 5, n] + q2 * moment[2, 5, n]
    v0 = zero + a0 * projection[0, 0, n] + a1 * projection[1, 0, n] + a2 * projection[2, 0, n]
    v1 = zero + a0 * projection[0, 1, n] + a1 * projection[1, 1, n] + a2 * projection[2, 1, n]
    v2 = zero + a0 * projection[0, 2, n] + a1 * projection[1, 2, n] + a2 * projection[2, 2, n]
    scale = (s00 + s11 + s22) / three
    if scale < tiny:
        scale = tiny
    xx, yy, zz = s00 / scale + damping, s11 / scale + damping, s22 / scale + damping
    xy, xz, yz = s01 / scale, s02 / scale, s12 / scale
    c00, c11, c22 = yy * zz - yz * yz, xx * zz - xz * xz, xx * yy - xy * xy
    c01, c02, c12 = xz * yz - xy * zz, xy * yz - yy * xz, xy * xz - xx * yz
    x0 = c00 * v0 + c01 * v1 + c02 * v2
    x1 = c01 * v0 + c11 * v1 + c12 * v2
    x2 = c02 * v0 + c12 * v1 + c22 * v2
    inverse = (three / three) / np.sqrt(x0 * x0 + x1 * x1 + x2 * x2 + tiny)  # a zero solution stays zero
    n0, n1, n2 = x0 * inverse, x1 * inverse, x2 * inverse
    a0 = _albedo(moment, projection, n, 0, n0, n1, n2, damping, absolute, three, zero)
    a1 = _albedo(moment, projection, n, 1, n0, n1, n2, damping, absolute, three, zero)
    a2 = _albedo(moment, projection, n, 2, n0, n1, n2, damping, absolute, three, zero)
    return a0, a1, a2, n0, n1, n2


@njit(inline="always", error_model="numpy")
def _pixel(moment, projection, albedo, n, damping, tiny, absolute, three, tolerance, rounding, max_alternations, albedo_out, normal_out, status):
    """Pixel n of ``pixel_solve.alternate`` before its float64 pass: writes the albedo, the
    normal and the status."""
    a0, a1, a2, n0, n1, n2 = _alternation(moment, projection, n, albedo[0, n], albedo[1, n], albedo[2, n], damping, tiny, absolute, three)
    state = NOT_CONVERGED
    previous = np.inf  # the first move (second alternation) has none before it to stall against
    for _ in range(max_alternations - 1):
        a0, a1, a2, m0, m1, m2 = _alternation(moment, projection, n, a0, a1, a2, damping, tiny, absolute, three)
        move = np.sqrt((m0 - n0) * (m0 - n0) + (m1 - n1) * (m1 - n1) + (m2 - n2) * (m2 - n2))
        stalled = move >= previous  # never for the first: unit or NaN normals move by at most 2 or NaN
        n0, n1, n2, previous = m0, m1, m2, move
        if move <= tolerance or (stalled and move <= rounding):
            state = CONVERGED
            break
        if stalled:
            state = STOPPED
            break
    albedo_out[0, n], albedo_out[1, n], albedo_out[2, n] = a0, a1, a2
    normal_out[0, n], normal_out[1, n], normal_out[2, n] = n0, n1, n2
    status[n] = state


def _parallel(moment, projection, albedo, damping, tiny, absolute, three, tolerance, rounding, max_alternations, albedo_out, normal_out, status):
    for n in prange(albedo.shape[1]):
        _pixel(moment, projection, albedo, n, damping, tiny, absolute, three, tolerance, rounding, max_alternations, albedo_out, normal_out, status)


def _serial(moment, projection, albedo, damping, tiny, absolute, three, tolerance, rounding, max_alternations, albedo_out, normal_out, status):
    for n in range(albedo.shape[1]):
        _pixel(moment, projection, albedo, n, damping, tiny, absolute, three, tolerance, rounding, max_alternations, albedo_out, normal_out, status)


_PARALLEL = compile_kernel(_parallel, parallel=True)
_SERIAL = compile_kernel(_serial, parallel=False, cache=True)
_KINDS = {torch.float32: np.float32, torch.float64: np.float64}


def kernel_applies(albedo: torch.Tensor, moments: Moments) -> bool:
    """Whether the kernels take these inputs: CPU float32 or float64 of one dtype, albedo (3, N),
    moment (3, 6, N) and projection (3, 3, N) (compiled code has no bounds checks)."""
    count = albedo.shape[-1] if albedo.dim() == 2 else -1
    tensors = (albedo, moments.moment, moments.projection)
    return (albedo.dtype in _KINDS and all(value.dtype == albedo.dtype and value.device.type == "cpu" for value in tensors)
            and tuple(albedo.shape) == (3, count) and tuple(moments.moment.shape) == (3, 6, count)
            and tuple(moments.projection.shape) == (3, 3, count))


def alternate(albedo: torch.Tensor, moments: Moments, damping: float, tolerance_deg: float, max_alternations: int):
    """``pixel_solve.alternate`` (same arguments and results), compiled where ``kernel_applies``
    and without gradient (the shadow search's fits); the reference elsewhere.

    Returns:
        (albedo (3, N), normal (3, N), converged (N,) bool) with albedo = A(normal).
    """
    needs_graph = torch.is_grad_enabled() and any(value.requires_grad for value in (albedo, moments.moment, moments.projection))
    if needs_graph or not kernel_applies(albedo, moments):
        return reference_alternate(albedo, moments, damping, tolerance_deg, max_alternations)
    dtype = albedo.dtype
    kind = _KINDS[dtype]
    count = albedo.shape[1]
    albedo_out, normal_out = torch.empty((3, count), dtype=dtype), torch.empty((3, count), dtype=dtype)
    status = torch.empty(count, dtype=torch.int8)
    if forked():
        kernel = _SERIAL
    else:
        match_torch_threads()
        kernel = _PARALLEL
    kernel(*(value.detach().contiguous().numpy() for value in (moments.moment, moments.projection, albedo)),
           kind(damping), kind(torch.finfo(dtype).tiny ** 0.5), kind(ABSOLUTE_DAMPING), kind(3.0), kind(math.radians(tolerance_deg)),
           kind(torch.finfo(dtype).eps ** 0.5), min(operator.index(max_alternations), MAX_ALTERNATIONS), albedo_out.numpy(), normal_out.numpy(), status.numpy())
    converged = status == CONVERGED
    widen_stopped(alternate, albedo_out, normal_out, converged, torch.nonzero(status == STOPPED).squeeze(1), moments, damping, tolerance_deg, max_alternations)
    return albedo_out, normal_out, converged
