"""The albedo/normal alternation of ``reconstruct.unrolled_ps``, with a hand-written backward.

One alternation maps a normal n (3, N) to (n', a) for per-channel moments B_c (3c, 6, N) (unique
entries in the order of ``reconstruct.lighting.SYMMETRIC_PAIRS``) and r_c (3c, 3, N):
    a_c = max(n . r_c / (n^T B_c n + tiny), 0)                          albedo given the normal
    T = S + lambda I,  S = sum_c a_c^2 B_c,  lambda = damping trace(S) / 3 + 1e-30
    y = adj(T) v / |det T|,  v = sum_c a_c r_c,   n' = y / |y|           normal given the albedo
(n' = n where y vanishes: a dark pixel keeps its normal, with no gradient). Learning backpropagates
through two of these per step. Autograd's backward through the ~100 small per-pixel operations
took about three times their forward (~12 ms per alternation at 100 000 pixels, 2 threads); the
chain rule written out below reuses the forward's intermediates and takes about 8 ms
(tests/test_unrolled_ps.py checks it against autograd's). Pixels lie on the last axis of every
tensor.
"""
from __future__ import annotations

import torch

from reconstruct.pixel_solve import symmetric_adjugate, symmetric_apply


def dot3(left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """Dot product over the size-3 axis -2 of (..., 3, N) tensors (broadcasting); (..., N)."""
    # unbind, not indexing: the backward of one unbind is one stack, while each indexed slice's
    # backward fills a zero tensor of the whole input.
    l0, l1, l2 = left.unbind(-2)
    r0, r1, r2 = right.unbind(-2)
    return l0 * r0 + l1 * r1 + l2 * r2


def symmetric_direction(system: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """S^-1 rhs up to a positive factor, for symmetric positive definite 3x3 systems S (6, N)
    (unique entries) and rhs (3, N); (3, N). Callers normalise the result.

    adj(S) rhs is divided by |det(S)|, not det(S): the determinant keeps the result of order one,
    and its sign, which rounding can make negative in float32, cannot flip the normal.
    """
    return _direction_terms(system, rhs)[-1]


def _direction_terms(system, rhs):
    """(adjugate (6, N), det (N,), adj(S) rhs (3, N), |det| floored (N,), direction (3, N))."""
    xx, yy, zz, xy, xz, yz = system.unbind(0)
    a00, a11, a22, a01, a02, a12 = symmetric_adjugate(xx, yy, zz, xy, xz, yz)
    det = xx * a00 + xy * a01 + xz * a02
    adjugate = torch.stack([a00, a11, a22, a01, a02, a12])
    solved = symmetric_apply(adjugate, rhs)
    scale = det.abs().clamp_min(1e-30)
    return adjugate, det, solved, scale, solved / scale


def _step(normal, moments, rhs_moments, damping: float, tiny):
    """One alternation and the intermediates its backward needs (module docstring)."""
    denominator = dot3(symmetric_apply(moments, normal), normal) + tiny  # n^T B_c n + tiny: (3c, N)
    ratio = dot3(rhs_moments, normal) / denominator
    albedo = ratio.clamp_min(0.0)
    s00, s11, s22, s01, s02, s12 = ((albedo * albedo)[:, None, :] * moments).sum(0).unbind(0)  # (6, N)
    shift = damping * (s00 + s11 + s22) / 3.0 + 1e-30
    system = torch.stack([s00 + shift, s11 + shift, s22 + shift, s01, s02, s12])
    rhs = (albedo[:, None, :] * rhs_moments).sum(0)
    adjugate, det, solved, scale, direction = _direction_terms(system, rhs)
    # A zero direction (dark pixel) keeps the previous normal: no 0/0 in value or gradient.
    length2 = dot3(direction, direction)
    usable = length2 > 1e-30
    inverse_length = torch.rsqrt(torch.where(usable, length2, torch.ones_like(length2)))
    new_normal = torch.where(usable, direction, normal.detach()) * inverse_length
    saved = (denominator, ratio, albedo, system, rhs, adjugate, det, solved, scale, usable, inverse_length, new_normal)
    return new_normal, albedo, saved


class _Alternation(torch.autograd.Function):
    """One alternation with gradients to the normal and the moments (the chain rule of ``_step``
    in closed form; where the albedo's clamp or the floor of |det| is active, the gradient is
    zero, as autograd's of clamp_min)."""

    @staticmethod
    def forward(ctx, normal, moments, rhs_moments, damping, tiny):
        new_normal, albedo, saved = _step(normal, moments, rhs_moments, damping, tiny)
        ctx.damping = damping
        ctx.save_for_backward(normal, moments, rhs_moments, *saved)
        return new_normal, albedo

    @staticmethod
    def backward(ctx, grad_normal, grad_albedo):
        normal, moments, rhs_moments, denominator, ratio, albedo, system, rhs, adjugate, det, solved, scale, usable, inverse_length, new_normal = ctx.saved_tensors
        # n' = y / |y| where usable (else the detached input): d n' = (dy - n' (n' . dy)) / |y|.
        # Masks select (where), not multiply: an overflowing term of a masked pixel stays out.
        grad_direction = torch.where(usable, (grad_normal - new_normal * dot3(new_normal, grad_normal)) * inverse_length, 0.0)
        # y = u / D with u = adj(T) v and D = max(|det T|, 1e-30).
        grad_solved = grad_direction / scale
        # dL/dD = -(dL/dy . y) / D, with y = u / D formed first: D^2 underflows in float32.
        grad_det = -dot3(grad_direction, solved / scale) / scale * torch.where(det.abs() >= 1e-30, det.sign(), 0.0)
        grad_rhs = symmetric_apply(adjugate, grad_solved)  # dL/dv = adj(T) dL/du (adj(T) symmetric)
        g0, g1, g2 = grad_solved.unbind(0)
        v0, v1, v2 = rhs.unbind(0)
        xx, yy, zz, xy, xz, yz = system.unbind(0)
        a00, a11, a22, a01, a02, a12 = adjugate.unbind(0)
        # dL/d adj(T) (unique entries: an off-diagonal one appears twice in u = adj(T) v), plus the
        # determinant's det = xx a00 + xy a01 + xz a02.
        ga00, ga11, ga22 = g0 * v0 + grad_det * xx, g1 * v1, g2 * v2
        ga01, ga02, ga12 = g0 * v1 + g1 * v0 + grad_det * xy, g0 * v2 + g2 * v0 + grad_det * xz, g1 * v2 + g2 * v1
        # Through the adjugate's entries (``symmetric_adjugate``) and the determinant's direct terms.
        gxx = ga11 * zz + ga22 * yy - ga12 * yz + grad_det * a00
        gyy = ga00 * zz + ga22 * xx - ga02 * xz
        gzz = ga00 * yy + ga11 * xx - ga01 * xy
        gxy = ga02 * yz + ga12 * xz - ga01 * zz - 2 * ga22 * xy + grad_det * a01
        gxz = ga01 * yz + ga12 * xy - ga02 * yy - 2 * ga11 * xz + grad_det * a02
        gyz = ga01 * xz + ga02 * xy - ga12 * xx - 2 * ga00 * yz
        # T = S + lambda I with lambda = damping trace(S) / 3 + 1e-30.
        diagonal = ctx.damping / 3.0 * (gxx + gyy + gzz)
        grad_system = torch.stack([gxx + diagonal, gyy + diagonal, gzz + diagonal, gxy, gxz, gyz])  # dL/dS (6, N)
        # S = sum_c a_c^2 B_c and v = sum_c a_c r_c.
        square = albedo * albedo
        grad_moments = square[:, None, :] * grad_system[None]
        grad_rhs_moments = albedo[:, None, :] * grad_rhs[None]
        grad_albedo_total = 2 * albedo * (moments * grad_system[None]).sum(1) + dot3(rhs_moments, grad_rhs[None])
        if grad_albedo is not None:
            grad_albedo_total = grad_albedo_total + grad_albedo
        # a = max(p / (q + tiny), 0) with p = n . r_c and q = n^T B_c n.
        through = torch.where(ratio >= 0, grad_albedo_total / denominator, 0.0)
        grad_projection, grad_quadratic = through, -through * ratio
        grad_rhs_moments += grad_projection[:, None, :] * normal[None]
        n0, n1, n2 = normal.unbind(0)
        outer = torch.stack([n0 * n0, n1 * n1, n2 * n2, 2 * n0 * n1, 2 * n0 * n2, 2 * n1 * n2])  # d(n^T B n)/dB
        grad_moments += grad_quadratic[:, None, :] * outer[None]
        grad_normal_in = None
        if ctx.needs_input_grad[0]:
            grad_normal_in = (grad_projection[:, None, :] * rhs_moments).sum(0) + 2 * (grad_quadratic[:, None, :] * symmetric_apply(moments, normal)).sum(0)
        return grad_normal_in, grad_moments, grad_rhs_moments, None, None


def alternate(normal, albedo, moments, rhs_moments, damping: float, steps: int):
    """``steps`` albedo/normal alternations (module docstring); differentiable in ``normal``,
    ``moments`` and ``rhs_moments`` when gradients are enabled (not in the incoming albedo, which
    the first alternation replaces).

    Args:
        normal: (3, N) unit normals; albedo: (3c, N), returned as is when ``steps`` is 0.
        moments: (3c, 6, N) per-channel B_c = sum_m w b b^T (unique entries).
        rhs_moments: (3c, 3, N) per-channel r_c = sum_m w I b.
        damping: Tikhonov damping relative to each system's trace / 3.

    Returns:
        normal (3, N) and albedo (3c, N).
    """
    # Relative floor, plus an absolute one well above the dtype's underflow for all-dark inputs.
    peak = moments.detach().abs().amax() if moments.numel() else moments.new_zeros(())
    tiny = 1e-12 * peak + torch.finfo(moments.dtype).tiny ** 0.5
    tracked = torch.is_grad_enabled() and any(value.requires_grad for value in (normal, moments, rhs_moments))
    for _ in range(steps):
        if tracked:
            normal, albedo = _Alternation.apply(normal, moments, rhs_moments, damping, tiny)
        else:
            normal, albedo, _ = _step(normal, moments, rhs_moments, damping, tiny)
    return normal, albedo
