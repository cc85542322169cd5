"""The albedo/normal alternation of ``reconstruct.unrolled_ps``, with a hand-written backward.

One alternation maps a normal n (3, N) to (n', a) for per-channel moments B_c (3c, 6, N) (unique
entries in the order of ``reconstruct.lighting.SYMMETRIC_PAIRS``) and r_c (3c, 3, N):
    a_c = max(n . r_c / (n^T B_c n + tiny), 0)                          albedo given the normal
    T = S + lambda I,  S = sum_c a_c^2 B_c,  lambda = damping trace(S) / 3 + 1e-30
    y = adj(T) v / |det T|,  v = sum_c a_c r_c,   n' = y / |y|           normal given the albedo
(n' = n where y vanishes: a dark pixel keeps its normal, with no gradient). Learning runs eight of
these per step and backpropagates through two. Both passes run as compiled per-pixel kernels
(``reconstruct.alternation_kernels``): as ~100 torch operations over (.., N) rows, one alternation
took ~4 ms and its written-out backward ~9 ms at 100 000 pixels (2 threads), a sixth of a
training step. ``_step`` below is the readable torch version: the tests check the kernels'
values against it and their gradients against autograd's through it. Pixels lie on the last axis
of every tensor.
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
    xx, yy, zz, xy, xz, yz = system.unbind(0)
    a00, a11, a22, a01, a02, a12 = symmetric_adjugate(xx, yy, zz, xy, xz, yz)
    det = xx * a00 + xy * a01 + xz * a02
    solved = symmetric_apply(torch.stack([a00, a11, a22, a01, a02, a12]), rhs)
    return solved / det.abs().clamp_min(1e-30)


def _step(normal, moments, rhs_moments, damping: float, tiny):
    """One alternation in torch (module docstring): (new normal (3, N), albedo (3c, N)). The
    reference of the compiled kernels, differentiable by autograd."""
    denominator = dot3(symmetric_apply(moments, normal), normal) + tiny  # n^T B_c n + tiny: (3c, N)
    ratio = dot3(rhs_moments, normal) / denominator
    albedo = ratio.clamp_min(0.0)
    s00, s11, s22, s01, s02, s12 = ((albedo * albedo)[:, None, :] * moments).sum(0).unbind(0)  # (6, N)
    shift = damping * (s00 + s11 + s22) / 3.0 + 1e-30
    system = torch.stack([s00 + shift, s11 + shift, s22 + shift, s01, s02, s12])
    rhs = (albedo[:, None, :] * rhs_moments).sum(0)
    direction = symmetric_direction(system, rhs)
    # A zero direction (dark pixel) keeps the previous normal: no 0/0 in value or gradient.
    length2 = dot3(direction, direction)
    usable = length2 > 1e-30
    inverse_length = torch.rsqrt(torch.where(usable, length2, torch.ones_like(length2)))
    new_normal = torch.where(usable, direction, normal.detach()) * inverse_length
    return new_normal, albedo


class _Alternation(torch.autograd.Function):
    """One alternation with gradients to the normal and the moments, both passes compiled
    (``reconstruct.alternation_kernels``): the chain rule of ``_step`` in closed form; where the
    albedo's clamp or the floor of |det| is active, the gradient is zero, as autograd's of
    clamp_min. The backward recomputes the forward's per-pixel intermediates."""

    @staticmethod
    def forward(ctx, normal, moments, rhs_moments, damping, tiny):
        from reconstruct.alternation_kernels import alternation_forward

        ctx.damping, ctx.tiny = damping, tiny
        ctx.save_for_backward(normal, moments, rhs_moments)
        return alternation_forward(normal, moments, rhs_moments, damping, tiny)

    @staticmethod
    def backward(ctx, grad_normal, grad_albedo):
        from reconstruct.alternation_kernels import alternation_backward

        if torch.is_grad_enabled():  # create_graph=True: the kernels' gradients would be silent constants
            raise RuntimeError("the unrolled alternation has no second derivative (its backward is a compiled kernel): do not use create_graph=True")

        normal, moments, rhs_moments = ctx.saved_tensors
        if grad_normal is None:
            grad_normal = torch.zeros_like(normal)
        grads = alternation_backward(normal, moments, rhs_moments, ctx.damping, ctx.tiny, grad_normal, grad_albedo)
        return grads[0] if ctx.needs_input_grad[0] else None, grads[1], grads[2], None, None


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
    if steps == 0:
        return normal, albedo
    from reconstruct.alternation_kernels import alternation_forward  # numba: imported on first use

    # Relative floor, plus an absolute one well above the dtype's underflow for all-dark inputs.
    peak = moments.detach().abs().amax() if moments.numel() else moments.new_zeros(())
    tiny = float(1e-12 * peak + torch.finfo(moments.dtype).tiny ** 0.5)
    tracked = torch.is_grad_enabled() and any(value.requires_grad for value in (normal, moments, rhs_moments))
    for _ in range(steps):
        if tracked:
            normal, albedo = _Alternation.apply(normal, moments, rhs_moments, damping, tiny)
        else:
            normal, albedo = alternation_forward(normal, moments, rhs_moments, damping, tiny)
    return normal, albedo
