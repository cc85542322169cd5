"""Compiled per-pixel kernels (numba) of the unrolled alternation and of its backward pass.

One alternation (``reconstruct.unrolled_alternation``, whose ``_step`` is the readable torch
reference these kernels are tested against) is about a hundred elementwise operations per pixel on
3- and 6-vectors. As torch operations each reads and writes whole (.., N) rows: at 10^5 pixels one
alternation took ~4 ms and its written-out backward ~9 ms, a sixth of a training step. Here each
pixel's algebra runs in registers, in one pass over the moments: the forward is the same sequence
of float operations as the reference (equal values in float32 and float64; no fast-math, so no
contraction into fused multiply-adds), and the backward recomputes the forward's intermediates per
pixel instead of keeping a dozen (.., N) tensors from the forward pass.

Arrays are numpy views of contiguous CPU tensors, pixels on the last axis:
    normal (3, N), moments (C, 6, N) (unique entries in ``SYMMETRIC_PAIRS`` order), rhs (C, 3, N),
    albedo (C, N); C = 3 colour channels.
Scalars are passed in the arrays' dtype, so that float32 arithmetic stays float32 (a Python float
literal would be float64 in numba and change the rounding). Pixels are independent, so the result
does not depend on the thread count.

Speed: the forward's and the backward's per-pixel loops run in SIMD lanes (8 float32 pixels at a
time with AVX2; ``_moment_gradients`` stays scalar, ~1.3 ms of memory traffic). That takes
per-channel loops of constant length (``CHANNELS``), IEEE division (``error_model="numpy"``;
Python's model tests every divisor for zero in order to raise), and few stores per loop (hence the
backward's second kernel). At 10^5 pixels, float32, 2 threads, one alternation took 5.5 ms and its
backward 13 ms with a scalar loop; 0.6-0.9 ms and 3-4.5 ms vectorised (an AMD EPYC with AVX2).
Compiled code is cached on disk (``cache=True``: a few seconds on first use, per dtype).

Threads and caching (``reconstruct.compiled``): forked processes run the serial versions. Those
stay scalar (2-6x slower: numba tells the compiler that arrays do not overlap only in its parallel
loops) and are compiled in each process that uses them (not cached); so are all kernels where no
cache folder is writable (``NUMBA_CACHE_DIR`` names one).
"""
from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from reconstruct.compiled import compile_kernel, forked, match_torch_threads


CHANNELS = 3
"""Colour channels C. A constant, so that the compiler unrolls the per-channel loops: the pixel
loop is then the innermost one and can run in SIMD lanes."""


@njit(inline="always", error_model="numpy")
def _channel(moments, rhs, c, n, n0, n1, n2, tiny):
    """Channel c at pixel n for the normal (n0, n1, n2): its moments B_c (6 entries), r_c, B_c n,
    n^T B_c n + tiny and the unclamped albedo n . r_c / (n^T B_c n + tiny), summed in the
    reference's order."""
    b00, b11, b22 = moments[c, 0, n], moments[c, 1, n], moments[c, 2, n]
    b01, b02, b12 = moments[c, 3, n], moments[c, 4, n], moments[c, 5, n]
    r0, r1, r2 = rhs[c, 0, n], rhs[c, 1, n], rhs[c, 2, n]
    q0 = b00 * n0 + b01 * n1 + b02 * n2
    q1 = b01 * n0 + b11 * n1 + b12 * n2
    q2 = b02 * n0 + b12 * n1 + b22 * n2
    denominator = q0 * n0 + q1 * n1 + q2 * n2 + tiny
    ratio = (r0 * n0 + r1 * n1 + r2 * n2) / denominator
    return b00, b11, b22, b01, b02, b12, r0, r1, r2, q0, q1, q2, denominator, ratio


@njit(inline="always", error_model="numpy")
def _forward_pixel(normal, moments, rhs, n, damping, tiny, floor, one, three):
    """One pixel's alternation (``unrolled_alternation._step``): the new normal and the
    intermediates the backward needs. Nothing is written: values stay in registers."""
    n0, n1, n2 = normal[0, n], normal[1, n], normal[2, n]
    zero = floor - floor
    s00 = s11 = s22 = s01 = s02 = s12 = v0 = v1 = v2 = zero
    for c in range(CHANNELS):
        b00, b11, b22, b01, b02, b12, r0, r1, r2, _, _, _, _, ratio = _channel(moments, rhs, c, n, n0, n1, n2, tiny)
        a = zero if ratio < zero else ratio  # a_c = max(n . r_c / (n^T B_c n + tiny), 0); NaN stays NaN, as in torch
        # S = sum_c a_c^2 B_c, v = sum_c a_c r_c.
        square = a * a
        s00 += square * b00
        s11 += square * b11
        s22 += square * b22
        s01 += square * b01
        s02 += square * b02
        s12 += square * b12
        v0 += a * r0
        v1 += a * r1
        v2 += a * r2
    # T = S + lambda I, lambda = damping trace(S) / 3 + 1e-30; y = adj(T) v / max(|det T|, 1e-30).
    shift = damping * (s00 + s11 + s22) / three + floor
    xx, yy, zz = s00 + shift, s11 + shift, s22 + shift
    a00, a11, a22 = yy * zz - s12 * s12, xx * zz - s02 * s02, xx * yy - s01 * s01
    a01, a02, a12 = s02 * s12 - s01 * zz, s01 * s12 - yy * s02, s01 * s02 - xx * s12
    det = xx * a00 + s01 * a01 + s02 * a02
    u0 = a00 * v0 + a01 * v1 + a02 * v2
    u1 = a01 * v0 + a11 * v1 + a12 * v2
    u2 = a02 * v0 + a12 * v1 + a22 * v2
    scale = abs(det)
    if scale < floor:
        scale = floor
    d0, d1, d2 = u0 / scale, u1 / scale, u2 / scale
    length2 = d0 * d0 + d1 * d1 + d2 * d2
    if length2 > floor:
        usable = one
        inverse_length = one / np.sqrt(length2)
        m0, m1, m2 = d0 * inverse_length, d1 * inverse_length, d2 * inverse_length
    else:  # a dark pixel: it keeps its normal, with no gradient
        usable = zero
        inverse_length = one
        m0, m1, m2 = n0, n1, n2
    # All floats (usable is 1 or 0): numba's alias analysis takes a bool, or a tuple holding one,
    # for a possible array alias and then withholds "noalias" from the parallel loop's arrays.
    return (m0, m1, m2, usable, inverse_length, xx, yy, zz, s01, s02, s12, v0, v1, v2,
            a00, a11, a22, a01, a02, a12, det, scale, u0, u1, u2)


def _forward(normal, moments, rhs, damping, tiny, floor, one, three, new_normal, albedo):
    for n in prange(normal.shape[1]):
        terms = _forward_pixel(normal, moments, rhs, n, damping, tiny, floor, one, three)
        new_normal[0, n], new_normal[1, n], new_normal[2, n] = terms[0], terms[1], terms[2]
        n0, n1, n2 = normal[0, n], normal[1, n], normal[2, n]
        zero = floor - floor
        # The channel terms again, written out: the parallel kernel's compiler shares them with the
        # forward pixel's (its IR has the 8 divisions of one pass); the serial kernel computes them twice.
        for c in range(CHANNELS):
            ratio = _channel(moments, rhs, c, n, n0, n1, n2, tiny)[13]
            albedo[c, n] = zero if ratio < zero else ratio


def _backward(normal, moments, rhs, damping, damping_third, tiny, floor, one, three, grad_new_normal, grad_albedo,
              grad_normal, terms, grad_rhs):
    for n in prange(normal.shape[1]):
        (m0, m1, m2, usable, inverse_length, xx, yy, zz, xy, xz, yz, v0, v1, v2,
         a00, a11, a22, a01, a02, a12, det, scale, u0, u1, u2) = _forward_pixel(normal, moments, rhs, n, damping, tiny, floor, one, three)
        zero = floor - floor
        # n' = y / |y| where usable (else the input, detached): d n' = (dy - n' (n' . dy)) / |y|.
        g0, g1, g2 = grad_new_normal[0, n], grad_new_normal[1, n], grad_new_normal[2, n]
        if usable > zero:
            along = m0 * g0 + m1 * g1 + m2 * g2
            e0, e1, e2 = (g0 - m0 * along) * inverse_length, (g1 - m1 * along) * inverse_length, (g2 - m2 * along) * inverse_length
        else:
            e0 = e1 = e2 = zero
        # y = u / D with u = adj(T) v and D = max(|det T|, 1e-30).
        h0, h1, h2 = e0 / scale, e1 / scale, e2 / scale
        sign = zero
        if abs(det) >= floor:
            sign = one if det > zero else (-one if det < zero else zero)
        grad_det = -(e0 * (u0 / scale) + e1 * (u1 / scale) + e2 * (u2 / scale)) / scale * sign
        w0 = a00 * h0 + a01 * h1 + a02 * h2  # dL/dv = adj(T) dL/du
        w1 = a01 * h0 + a11 * h1 + a12 * h2
        w2 = a02 * h0 + a12 * h1 + a22 * h2
        # dL/d adj(T) (an off-diagonal entry appears twice in u) and det = xx a00 + xy a01 + xz a02.
        ga00, ga11, ga22 = h0 * v0 + grad_det * xx, h1 * v1, h2 * v2
        ga01 = h0 * v1 + h1 * v0 + grad_det * xy
        ga02 = h0 * v2 + h2 * v0 + grad_det * xz
        ga12 = h1 * v2 + h2 * v1
        gxx = ga11 * zz + ga22 * yy - ga12 * yz + grad_det * a00
        gyy = ga00 * zz + ga22 * xx - ga02 * xz
        gzz = ga00 * yy + ga11 * xx - ga01 * xy
        gxy = ga02 * yz + ga12 * xz - ga01 * zz - (ga22 + ga22) * xy + grad_det * a01
        gxz = ga01 * yz + ga12 * xy - ga02 * yy - (ga11 + ga11) * xz + grad_det * a02
        gyz = ga01 * xz + ga02 * xy - ga12 * xx - (ga00 + ga00) * yz
        diagonal = damping_third * (gxx + gyy + gzz)  # lambda = damping trace(S) / 3 + 1e-30
        t0, t1, t2 = gxx + diagonal, gyy + diagonal, gzz + diagonal  # dL/dS
        n0, n1, n2 = normal[0, n], normal[1, n], normal[2, n]
        p0 = p1 = p2 = q0 = q1 = q2 = zero
        for c in range(CHANNELS):
            b00, b11, b22, b01, b02, b12, r0, r1, r2, bn0, bn1, bn2, denominator, ratio = _channel(moments, rhs, c, n, n0, n1, n2, tiny)
            a = zero if ratio < zero else ratio
            # S = sum_c a_c^2 B_c and v = sum_c a_c r_c; a = max(p / (q + tiny), 0), p = n . r_c, q = n^T B_c n.
            total = ((a + a) * (b00 * t0 + b11 * t1 + b22 * t2 + b01 * gxy + b02 * gxz + b12 * gyz)
                     + (r0 * w0 + r1 * w1 + r2 * w2) + grad_albedo[c, n])
            through = total / denominator if ratio >= zero else zero
            quadratic = -through * ratio
            square = a * a
            terms[c, n] = square  # dL/dB_c = a_c^2 dL/dS + quadratic d(n^T B_c n)/dB_c
            terms[3 + c, n] = quadratic
            grad_rhs[c, 0, n] = a * w0 + through * n0
            grad_rhs[c, 1, n] = a * w1 + through * n1
            grad_rhs[c, 2, n] = a * w2 + through * n2
            p0 += through * r0
            p1 += through * r1
            p2 += through * r2
            q0 += quadratic * bn0
            q1 += quadratic * bn1
            q2 += quadratic * bn2
        terms[6, n], terms[7, n], terms[8, n], terms[9, n], terms[10, n], terms[11, n] = t0, t1, t2, gxy, gxz, gyz
        grad_normal[0, n] = p0 + (q0 + q0)
        grad_normal[1, n] = p1 + (q1 + q1)
        grad_normal[2, n] = p2 + (q2 + q2)


def _moment_gradients(normal, terms, grad_moments):
    """dL/dB_c (C, 6, N) from the backward's per-pixel ``terms`` (12, N): a_c^2 (rows 0-2), the
    coefficient of d(n^T B_c n)/dB_c (rows 3-5) and dL/dS (rows 6-11). A kernel of its own: with
    these 18 stores in the backward's loop the compiler's dependence analysis gave up on SIMD
    there (13 ms instead of 3-4.5 for the whole backward at 10^5 pixels, float32)."""
    for n in prange(normal.shape[1]):
        n0, n1, n2 = normal[0, n], normal[1, n], normal[2, n]
        o0, o1, o2 = n0 * n0, n1 * n1, n2 * n2  # d(n^T B n)/dB
        o3, o4, o5 = (n0 + n0) * n1, (n0 + n0) * n2, (n1 + n1) * n2
        t0, t1, t2, gxy, gxz, gyz = terms[6, n], terms[7, n], terms[8, n], terms[9, n], terms[10, n], terms[11, n]
        for c in range(CHANNELS):
            square, quadratic = terms[c, n], terms[3 + c, n]
            grad_moments[c, 0, n] = square * t0 + quadratic * o0
            grad_moments[c, 1, n] = square * t1 + quadratic * o1
            grad_moments[c, 2, n] = square * t2 + quadratic * o2
            grad_moments[c, 3, n] = square * gxy + quadratic * o3
            grad_moments[c, 4, n] = square * gxz + quadratic * o4
            grad_moments[c, 5, n] = square * gyz + quadratic * o5


_KERNELS = {
    (name, parallel): compile_kernel(function, parallel)
    for name, function in (("forward", _forward), ("backward", _backward), ("moment_gradients", _moment_gradients))
    for parallel in (True, False)
}
"""Compiled on first call: parallel, and serial for forked processes (module docstring)."""


def _kernel(name: str):
    """The kernel to run in this process, on torch's thread count (``--threads``)."""
    if forked():
        return _KERNELS[name, False]
    match_torch_threads()
    return _KERNELS[name, True]


def _array(value: torch.Tensor) -> np.ndarray:
    """A numpy view of a contiguous detached copy of ``value`` (no copy when it is one already)."""
    return value.detach().contiguous().numpy()


def _check_inputs(normal: torch.Tensor, moments: torch.Tensor, rhs_moments: torch.Tensor, *grads) -> None:
    """Shapes and dtypes the kernels rely on: compiled code has no bounds checks, so a short axis
    would read or write past an array."""
    count = normal.shape[-1] if normal.dim() == 2 else "N"
    expected = [("normal", normal, (3, count)), ("moments", moments, (CHANNELS, 6, count)), ("rhs", rhs_moments, (CHANNELS, 3, count))]
    expected += [(name, grad, (rows, count)) for name, grad, rows in zip(("grad_new_normal", "grad_albedo"), grads, (3, CHANNELS)) if grad is not None]
    for name, value, shape in expected:
        if tuple(value.shape) != shape or value.dtype != normal.dtype:
            raise ValueError(
                f"alternation kernels need normal (3, N), moments ({CHANNELS}, 6, N), rhs ({CHANNELS}, 3, N) and gradients "
                f"(3, N) / ({CHANNELS}, N) of one dtype: {name} is {tuple(value.shape)} {value.dtype}, not ({', '.join(map(str, shape))}) {normal.dtype}"
            )
    if normal.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"alternation kernels run in float32 or float64, got {normal.dtype}")


def _scalars(dtype: torch.dtype, damping: float, tiny: float):
    """The kernels' scalars in the working dtype: damping, tiny, the 1e-30 floor, 1, 3, damping / 3."""
    kind = {torch.float32: np.float32, torch.float64: np.float64}[dtype]
    return kind(damping), kind(tiny), kind(1e-30), kind(1.0), kind(3.0), kind(damping / 3.0)


def alternation_forward(normal: torch.Tensor, moments: torch.Tensor, rhs_moments: torch.Tensor, damping: float, tiny: float):
    """One alternation without gradient: (new normal (3, N), albedo (C, N)), inputs' dtype
    (float32 or float64). Same values as ``unrolled_alternation._step``."""
    _check_inputs(normal, moments, rhs_moments)
    damping_, tiny_, floor, one, three, _ = _scalars(normal.dtype, damping, tiny)
    new_normal, albedo = torch.empty_like(normal, memory_format=torch.contiguous_format), normal.new_empty((moments.shape[0], normal.shape[1]))
    _kernel("forward")(_array(normal), _array(moments), _array(rhs_moments), damping_, tiny_, floor, one, three, new_normal.numpy(), albedo.numpy())
    return new_normal, albedo


def alternation_backward(normal, moments, rhs_moments, damping: float, tiny: float, grad_new_normal, grad_albedo):
    """Gradients (normal (3, N), moments (C, 6, N), rhs_moments (C, 3, N)) of one alternation
    given those of its outputs (``grad_albedo`` None for none)."""
    _check_inputs(normal, moments, rhs_moments, grad_new_normal, grad_albedo)
    damping_, tiny_, floor, one, three, damping_third = _scalars(normal.dtype, damping, tiny)
    count = normal.shape[1]
    if grad_albedo is None:
        grad_albedo = normal.new_zeros((moments.shape[0], count))
    grad_normal, terms = normal.new_empty((3, count)), normal.new_empty((12, count))
    grad_moments, grad_rhs = normal.new_empty(moments.shape), normal.new_empty(rhs_moments.shape)
    normal_ = _array(normal)
    _kernel("backward")(normal_, _array(moments), _array(rhs_moments), damping_, damping_third, tiny_, floor, one, three,
              _array(grad_new_normal), _array(grad_albedo), grad_normal.numpy(), terms.numpy(), grad_rhs.numpy())
    _kernel("moment_gradients")(normal_, terms.numpy(), grad_moments.numpy())
    return grad_normal, grad_moments, grad_rhs
