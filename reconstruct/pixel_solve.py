"""Per-pixel least squares of the Lambertian model I[m, c] = a_c b[m, c] . n, pixels last.

Every function works on all pixels of a block at once with pixels on the last axis: a normal is
(3, N), an albedo (3, N), per-channel symmetric moments B_c (3, 6, N) (channel, entry of
``SYMMETRIC_PAIRS``, pixel). Explicit formulas on the 6 entries replace batched 3x3 products.

Symbols: B_c = sum_m q b b^T and r_c = sum_m q I b are the per-channel moments (q the equation
weights), a the albedo, n the normal. One alternation Phi of the published method, iterated here
to convergence:
    normal given albedo:  (sum_c a_c^2 B_c + lambda I) n ~ sum_c a_c r_c,  n normalised,
                          lambda = damping * trace(sum_c a_c^2 B_c) / 3 (relative damping)
    albedo given normal:  a_c = max(0, n . r_c / (n^T B_c n + mu_c)),  mu_c = damping * trace(B_c) / 3
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from capture_sim.errors import InputError
from reconstruct.lighting import lighting_moments

CONDITION_CAP = 1e12
"""Reported condition numbers are capped here (singular systems report exactly this value)."""
JACOBIAN_BLOCK = 32768
"""Pixels per block when ``implicit_step`` forms the per-pixel Jacobians (bounds temporaries)."""
ABSOLUTE_DAMPING = 1e-12
"""Added to albedo denominators, in per-pixel normalised units where systems are of order one."""


def _tiny(dtype) -> float:
    return torch.finfo(dtype).tiny ** 0.5


def unit(vectors: torch.Tensor) -> torch.Tensor:
    """Normalise (3, N) vectors along axis 0; a zero vector stays zero, with a finite gradient."""
    return vectors * torch.rsqrt((vectors * vectors).sum(0, keepdim=True) + _tiny(vectors.dtype))


def length(vectors: torch.Tensor, dim: int = 0) -> torch.Tensor:
    """Euclidean lengths of 3-vectors along axis ``dim`` (size 3) of any tensor, that axis removed.

    Three products and a square root: torch's norm over a leading axis of size 3 took ~90x as
    long ((3, 313 344): 46 ms against 0.5 ms; (4, 3, 3, 8192) over axis 2: 15 ms against 0.2 ms)."""
    if vectors.dim() == 0 or vectors.shape[dim] != 3:
        raise InputError(f"length: axis {dim} of a {tuple(vectors.shape)} tensor does not hold 3-vectors")
    x, y, z = vectors.unbind(dim)
    return torch.sqrt(x * x + y * y + z * z)


def cross(first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """Cross products of (3, N) vectors along axis 0."""
    return torch.linalg.cross(first, second, dim=0)


def symmetric_trace(moment: torch.Tensor) -> torch.Tensor:
    """Trace of symmetric matrices (..., 6, N) -> (..., N)."""
    return moment[..., 0, :] + moment[..., 1, :] + moment[..., 2, :]


def quadratic_form(moment: torch.Tensor, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """u^T B v for symmetric B (..., 6, N) and vectors u, v (3, N) -> (..., N)."""
    xx, yy, zz, xy, xz, yz = moment.unbind(-2)
    u0, u1, u2 = first.unbind(0)
    v0, v1, v2 = second.unbind(0)
    return xx * (u0 * v0) + yy * (u1 * v1) + zz * (u2 * v2) + xy * (u0 * v1 + u1 * v0) + xz * (u0 * v2 + u2 * v0) + yz * (u1 * v2 + u2 * v1)


def damped_direction(system: torch.Tensor, rhs: torch.Tensor, damping: float) -> torch.Tensor:
    """Unit direction of the damped solution of symmetric positive semi-definite 3x3 systems.

    Solves (A / s + damping I) x = rhs / s with s = trace(A) / 3 and returns x / |x|. The damped
    matrix is positive definite, so its determinant is positive and x / |x| is the direction of
    adj(A / s + damping I) rhs: no division by a determinant, so values and gradients stay finite
    for singular or all-zero systems (which give a zero vector).

    Args:
        system: (6, N) symmetric positive semi-definite matrices A (entries of SYMMETRIC_PAIRS).
        rhs: (3, N).
        damping: relative damping (> 0).

    Returns:
        (3, N) unit vectors (zero where the solution is zero).
    """
    scale = (symmetric_trace(system) / 3).clamp_min(_tiny(system.dtype))
    xx, yy, zz, xy, xz, yz = (system / scale).unbind(0)
    a00, a11, a22, a01, a02, a12 = symmetric_adjugate(xx + damping, yy + damping, zz + damping, xy, xz, yz)
    r0, r1, r2 = rhs.unbind(0)
    solution = torch.stack([a00 * r0 + a01 * r1 + a02 * r2, a01 * r0 + a11 * r1 + a12 * r2, a02 * r0 + a12 * r1 + a22 * r2])
    return unit(solution)


def symmetric_adjugate(xx, yy, zz, xy, xz, yz):
    """Entries (00, 11, 22, 01, 02, 12) of the adjugate of [[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]
    (symmetric, so is its adjugate); every argument a tensor of per-pixel values."""
    return (yy * zz - yz * yz, xx * zz - xz * xz, xx * yy - xy * xy,
            xz * yz - xy * zz, xy * yz - yy * xz, xy * xz - xx * yz)


def damped_solve(system: torch.Tensor, rhs: torch.Tensor, damping: float) -> torch.Tensor:
    """Solutions x (..., 3, N) of (A + damping * trace(A) / 3 * I) x = rhs for symmetric PSD A (..., 6, N).

    The determinant of the scaled, damped matrix is at least damping^3, so the division is safe.
    Normal equations with an all-zero A have an all-zero rhs too (A = sum b b^T, rhs = sum I b)
    and give x = 0; an inconsistent pair (A = 0, rhs != 0) gives a large finite x.
    """
    scale = (symmetric_trace(system) / 3).clamp_min(_tiny(system.dtype))
    xx, yy, zz, xy, xz, yz = (system / scale[..., None, :]).unbind(-2)
    xx, yy, zz = xx + damping, yy + damping, zz + damping
    a00, a11, a22, a01, a02, a12 = symmetric_adjugate(xx, yy, zz, xy, xz, yz)
    det = xx * a00 + xy * a01 + xz * a02
    r0, r1, r2 = (rhs / scale[..., None, :]).unbind(-2)
    adjugate_rhs = torch.stack([a00 * r0 + a01 * r1 + a02 * r2, a01 * r0 + a11 * r1 + a12 * r2, a02 * r0 + a12 * r1 + a22 * r2], dim=-2)
    return adjugate_rhs / det.clamp_min(damping**3)[..., None, :]


def adjugate(matrix: torch.Tensor) -> torch.Tensor:
    """Adjugate of general (3, 3, N) matrices: adj(A) A = det(A) I, finite for singular A."""
    rows = matrix.unbind(0)
    cofactors = torch.stack([cross(rows[1], rows[2]), cross(rows[2], rows[0]), cross(rows[0], rows[1])], dim=0)
    return cofactors.transpose(0, 1)


def determinant(matrix: torch.Tensor) -> torch.Tensor:
    """Determinant of general (3, 3, N) matrices -> (N,)."""
    return (matrix[0] * cross(matrix[1], matrix[2])).sum(0)


def tangent_basis(normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two (3, N) unit vectors orthogonal to each unit normal (3, N) (zero for a zero normal)."""
    helper = torch.zeros_like(normal)
    use_x = normal[0].abs() < 0.6
    helper[0] = use_x.to(normal.dtype)
    helper[1] = (~use_x).to(normal.dtype)
    first = unit(cross(normal, helper))
    return first, cross(normal, first)


@dataclass(frozen=True, eq=False)
class Moments:
    """Per-pixel moments in normalised units (b / lighting_scale, I / capture_scale), pixels last.

    The solution is exactly equivariant to these per-pixel scales (all damping is relative up to
    ABSOLUTE_DAMPING), so they are constants for differentiation; they only keep every 3x3 system
    of order one in any dtype.

    Attributes:
        moment: (3, 6, N) symmetric B_c, channel first.
        projection: (3, 3, N) r_c.
        capture_energy: (3, N) sum_m q I^2.
        lighting_scale: (N,) RMS size of the raw lighting vectors (detached).
        capture_scale: (N,) max |I| of the pixel (detached).
        vectors: (M, 3, 3, N) raw lighting vectors b the moments came from, kept when the caller
            needs them later (gradients), else None.
    """

    moment: torch.Tensor
    projection: torch.Tensor
    capture_energy: torch.Tensor
    lighting_scale: torch.Tensor
    capture_scale: torch.Tensor
    vectors: torch.Tensor | None = None

    _FIELDS = ("moment", "projection", "capture_energy", "lighting_scale", "capture_scale")

    def subset(self, index, keep_vectors: bool = False) -> "Moments":
        """Moments of the pixels ``index`` ((n,) long indices or (N,) bool mask); the vectors
        are carried along only with ``keep_vectors``."""
        if index.dtype == torch.bool:
            index = torch.nonzero(index).squeeze(1)
        vectors = take_pixels(self.vectors, index) if keep_vectors and self.vectors is not None else None
        return Moments(*(take_pixels(getattr(self, name), index) for name in self._FIELDS), vectors)

    def to(self, dtype: torch.dtype) -> "Moments":
        """The moments in ``dtype`` (without the vectors)."""
        return Moments(*(getattr(self, name).to(dtype) for name in self._FIELDS))

    def assign(self, index: torch.Tensor, other: "Moments") -> None:
        """Overwrite the pixels ``index`` ((n,) long) with ``other`` (in place)."""
        for name in self._FIELDS:
            put_pixels(getattr(self, name), index, getattr(other, name))
        if self.vectors is not None:
            put_pixels(self.vectors, index, other.vectors)

    def detach(self) -> "Moments":
        return Moments(*(getattr(self, name).detach() for name in self._FIELDS))

    @staticmethod
    def empty(count: int, dtype, num_patterns: int | None = None) -> "Moments":
        """Uninitialised moments of ``count`` pixels (with room for vectors of ``num_patterns``)."""
        return Moments(
            torch.empty((3, 6, count), dtype=dtype),
            torch.empty((3, 3, count), dtype=dtype),
            torch.empty((3, count), dtype=dtype),
            torch.empty(count, dtype=dtype),
            torch.empty(count, dtype=dtype),
            None if num_patterns is None else torch.empty((num_patterns, 3, 3, count), dtype=dtype),
        )

    def write(self, start: int, stop: int, other: "Moments", vectors: torch.Tensor | None = None) -> None:
        """Copy ``other`` (and ``vectors`` if this keeps them) into the pixels start:stop."""
        for name in self._FIELDS:
            getattr(self, name)[..., start:stop] = getattr(other, name)
        if self.vectors is not None:
            self.vectors[..., start:stop] = vectors


def take_pixels(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """values[..., index] for pixels-last tensors, via a 2-D index_select (much faster on CPU)."""
    return values.reshape(-1, values.shape[-1]).index_select(1, index).reshape(*values.shape[:-1], index.numel())


def put_pixels(values: torch.Tensor, index: torch.Tensor, source: torch.Tensor) -> None:
    """values[..., index] = source in place, for contiguous pixels-last tensors."""
    if index.numel() == 0:
        return
    values.view(-1, values.shape[-1]).index_copy_(1, index, source.reshape(-1, index.numel()))


def normalised_moments(lighting_vectors, captures, equation_weight, capture_scale) -> Moments:
    """Moments of lighting vectors (M, 3, 3, N) and captures (M, 3, N) with weights (M, 3, N).

    ``capture_scale`` (N,) is the per-pixel capture normalisation (see ``Moments``).
    """
    lighting_scale = lighting_vectors.detach().square().mean(dim=(0, 1, 2)).sqrt().clamp_min(_tiny(lighting_vectors.dtype))
    moment, projection, energy = lighting_moments(lighting_vectors / lighting_scale, captures / capture_scale, equation_weight)
    return Moments(moment, projection, energy, lighting_scale, capture_scale)


def scaled_moments(moment, projection, energy, capture_scale) -> Moments:
    """Moments from raw per-channel moments (3, 6, N), projections (3, 3, N) and energy (3, N).

    The lighting scale comes from the moments' traces (used where no b vectors are formed).
    """
    squared_scale = (symmetric_trace(moment).detach().sum(0) / 9).clamp_min(_tiny(moment.dtype) ** 2)
    lighting_scale = squared_scale.sqrt()
    return Moments(moment / squared_scale, projection / (lighting_scale * capture_scale), energy / capture_scale**2, lighting_scale, capture_scale)


def normal_step(albedo: torch.Tensor, moments: Moments, damping: float) -> torch.Tensor:
    """Unit normals (3, N) given albedo (3, N): the damped least-squares solve, normalised."""
    system = (albedo.square()[:, None] * moments.moment).sum(0)
    rhs = (albedo[:, None] * moments.projection).sum(0)
    return damped_direction(system, rhs, damping)


def _fit_terms(normal: torch.Tensor, moments: Moments) -> tuple[torch.Tensor, torch.Tensor]:
    """(3, N) n . r_c and n^T B_c n: the per-channel least-squares albedo is their ratio."""
    return (normal[None] * moments.projection).sum(1), quadratic_form(moments.moment, normal, normal)


def _albedo_terms(normal: torch.Tensor, moments: Moments, damping: float) -> tuple[torch.Tensor, torch.Tensor]:
    numerator, shading = _fit_terms(normal, moments)
    return numerator, shading + damping * symmetric_trace(moments.moment) / 3 + ABSOLUTE_DAMPING


def albedo_step(normal: torch.Tensor, moments: Moments, damping: float) -> torch.Tensor:
    """Least-squares albedo (3, N) >= 0 given normals (3, N), in the moments' units."""
    numerator, denominator = _albedo_terms(normal, moments, damping)
    return torch.relu(numerator / denominator)


def residual(normal: torch.Tensor, moments: Moments, damping: float) -> torch.Tensor:
    """(N,) squared residual of the best albedo >= 0 for normals (3, N), in normalised units.

    Independent of the lighting scale, so residuals of different shadow masks compare.
    """
    numerator, denominator = _albedo_terms(normal, moments, damping)
    return (moments.capture_energy - torch.relu(numerator).square() / denominator).sum(0)


def relative_residual(normal: torch.Tensor, moments: Moments) -> torch.Tensor:
    """(N,) RMS residual of the least-squares Lambertian fit of normals (3, N), relative to the RMS
    capture, in [0, 1]: 0 for a perfect fit, 1 when the model explains none of the captures (and
    for pixels without captured light). ``moments`` must be built from the normals' own shadow
    masks.

    Undamped, unlike the solver's objective (``residual``), whose damping adds a floor of order
    sqrt(damping); the cancellation left costs a few sqrt(eps) of the dtype (~1e-3 in float32). A
    confidence measure: specular highlights, noise and wrong shadow masks all raise it.
    """
    normal = normal.detach()
    tiny = torch.finfo(normal.dtype).tiny
    projection, shading = _fit_terms(normal, moments.detach())
    explained = torch.where(shading > tiny, torch.relu(projection).square() / shading.clamp_min(tiny), torch.zeros_like(shading))
    energy = moments.capture_energy.detach().sum(0)
    unexplained = (energy - explained.sum(0)).clamp_min(0)
    ratio = (unexplained / energy.clamp_min(tiny)).clamp_max(1.0)
    return torch.where(energy > 0, ratio.sqrt(), torch.ones_like(ratio))


def alternation(albedo: torch.Tensor, moments: Moments, damping: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Phi: albedo -> normal given albedo -> albedo given that normal.

    ``albedo`` (3, N) per channel and pixel; returns the new albedo (3, N) and the unit normal
    (3, N), camera frame (``moments``: the N pixels' moments, ``damping``: relative damping)."""
    normal = normal_step(albedo, moments, damping)
    return albedo_step(normal, moments, damping), normal


WIDE_ALTERNATIONS = 10
"""Cap on the float64 alternations of ``alternate``'s pixels that stop on rounding noise below
float64: such pixels contract by about 5x per alternation, so 10 take a move of 0.05 deg below the
default tolerance; a pixel that needs more is slow in any precision."""


def alternate(albedo: torch.Tensor, moments: Moments, damping: float, tolerance_deg: float, max_alternations: int):
    """Iterate Phi for fixed moments until the normals stop moving.

    A pixel stops when its normal moves by at most ``tolerance_deg`` (converged), or when a move
    fails to shrink. A non-shrinking move no larger than the rounding level sqrt(eps) of the dtype
    (about 0.02 deg in float32; below the default tolerance in float64) is rounding noise of an
    ill-conditioned float32 solve that further steps cannot remove: converged. A larger one means
    progress too slow to finish (nearly rank-deficient systems, where the alternation would run to
    ``max_alternations`` without getting anywhere useful): the pixel stops, not converged, so
    callers flag it and the shadow search may restart it. Below float64, such pixels are first
    iterated on in float64 from where they stopped, on the same moments (at most
    ``WIDE_ALTERNATIONS`` more): in float32 the moves of
    slowly contracting pixels (condition numbers of some hundreds) jitter around 0.01 to 0.05 deg,
    so a move fails to shrink long before progress does (measured: a third of the pixels of a
    noise-free Lambertian sphere under initial_tri_random_4 stopped so, none in float64). Only
    pixels still moving are iterated.

    Args:
        albedo: (3, N) starting albedo.
        moments: the pixels' moments.
        damping: relative damping.
        tolerance_deg: convergence tolerance on the normal, degrees.
        max_alternations: cap on alternations (>= 1).

    Returns:
        (albedo (3, N), normal (3, N), converged (N,) bool) with albedo = A(normal).
    """
    tolerance = math.radians(tolerance_deg)  # chord length ~ angle for small angles
    rounding = torch.finfo(albedo.dtype).eps ** 0.5
    albedo, normal = alternation(albedo, moments, damping)
    if max_alternations < 2:
        return albedo, normal, torch.zeros(albedo.shape[1], dtype=torch.bool)
    # The second alternation runs on every pixel without gathering.
    new_albedo, new_normal = alternation(albedo, moments, damping)
    previous_move = (new_normal - normal).square().sum(0).sqrt()
    albedo, normal = new_albedo, new_normal
    converged = previous_move <= tolerance
    active = torch.nonzero(~converged).squeeze(1)
    stopped = [active[:0]]  # pixels that stopped on a non-shrinking move above the rounding level
    for _ in range(max_alternations - 2):
        if active.numel() == 0:
            break
        new_albedo, new_normal = alternation(albedo[:, active], moments.subset(active), damping)
        move = (new_normal - normal[:, active]).square().sum(0).sqrt()
        stalled = move >= previous_move[active]
        done = (move <= tolerance) | stalled
        finished = (move <= tolerance) | (stalled & (move <= rounding))
        albedo[:, active], normal[:, active], previous_move[active] = new_albedo, new_normal, move
        converged[active[finished]] = True
        stopped.append(active[done & ~finished])
        active = active[~done]
    widen_stopped(alternate, albedo, normal, converged, torch.cat(stopped), moments, damping, tolerance_deg, max_alternations)
    return albedo, normal, converged


def widen_stopped(solve, albedo, normal, converged, stopped, moments: Moments, damping: float, tolerance_deg: float, max_alternations: int) -> None:
    """``alternate``'s float64 pass, in place: below float64, the pixels ``stopped`` (S,) (indices
    of pixels that stopped on a non-shrinking move) of albedo (3, N), normal (3, N) and converged
    (N,) are iterated on by ``solve`` (``alternate`` or a compiled equal) in float64 from where
    they stopped, at most ``WIDE_ALTERNATIONS`` more; other arguments as ``alternate``'s."""
    if stopped.numel() == 0 or albedo.dtype == torch.float64:
        return
    wide_albedo, wide_normal, wide_converged = solve(albedo[:, stopped].double(), moments.subset(stopped).to(torch.float64),
                                                     damping, tolerance_deg, min(max_alternations, WIDE_ALTERNATIONS))
    albedo[:, stopped], normal[:, stopped] = wide_albedo.to(albedo.dtype), wide_normal.to(normal.dtype)
    converged[stopped] = wide_converged


def symmetric_apply(matrix: torch.Tensor, vector: torch.Tensor) -> torch.Tensor:
    """S v for symmetric S (..., 6, N) (entries of SYMMETRIC_PAIRS) and v (..., 3, N), broadcasting."""
    s00, s11, s22, s01, s02, s12 = matrix.unbind(-2)
    v0, v1, v2 = vector.unbind(-2)
    return torch.stack([s00 * v0 + s01 * v1 + s02 * v2, s01 * v0 + s11 * v1 + s12 * v2, s02 * v0 + s12 * v1 + s22 * v2], dim=-2)


def symmetric_cofactors(first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """The symmetric bilinear form C(U, V) with C(A, A) = adj(A) for symmetric A, entries (..., 6, N).

    The adjugate is quadratic in A, so its derivative is d adj(A) = 2 C(A, dA): a polynomial, with
    no division by the determinant (finite for singular A).
    """
    u00, u11, u22, u01, u02, u12 = first.unbind(-2)
    v00, v11, v22, v01, v02, v12 = second.unbind(-2)
    return torch.stack([
        (u11 * v22 + u22 * v11) / 2 - u12 * v12,
        (u00 * v22 + u22 * v00) / 2 - u02 * v02,
        (u00 * v11 + u11 * v00) / 2 - u01 * v01,
        (u02 * v12 + u12 * v02 - u01 * v22 - u22 * v01) / 2,
        (u01 * v12 + u12 * v01 - u11 * v02 - u02 * v11) / 2,
        (u01 * v02 + u02 * v01 - u00 * v12 - u12 * v00) / 2,
    ], dim=-2)


def alternation_jacobian(albedo: torch.Tensor, moments: Moments, damping: float) -> torch.Tensor:
    """J[i, j] = d Phi_i / d a_j of one alternation ``alternation`` at ``albedo``, moments constant.

    Phi(a) = A(n(a)). The normal step forms T = S / s + damping I and r' = r / s from
    S = sum_c a_c^2 B_c, r = sum_c a_c r_c, s = trace(S) / 3, and n = unit(adj(T) r'); the albedo
    step is A_c = relu(n . r_c / (n^T B_c n + mu_c)). Differentiated in closed form: dT and dr' by
    the quotient rule, d adj(T) = 2 C(T, dT) (``symmetric_cofactors``), the derivative of ``unit``
    and that of the albedo quotient (zero where the relu clamps). It equals autograd's Jacobian of
    ``alternation`` to rounding, at a fraction of the cost, and is as finite: nothing divides by
    the determinant of T.

    Args:
        albedo: (3, N) albedo a (constant).
        moments: the pixels' moments (constants).
        damping: relative damping.

    Returns:
        (3, 3, N) Jacobians, pixels last.
    """
    tiny = _tiny(albedo.dtype)
    moment, projection = moments.moment, moments.projection  # (3c, 6, N), (3c, 3, N)
    system = (albedo.square()[:, None] * moment).sum(0)
    rhs = (albedo[:, None] * projection).sum(0)
    trace = symmetric_trace(system) / 3
    scale = trace.clamp_min(tiny)
    # d s / d a_j (zero where the scale is clamped, as in autograd's clamp).
    scale_rate = (2 / 3) * albedo * symmetric_trace(moment) * (trace >= tiny).to(albedo.dtype)  # (3j, N)
    normalised, scaled_rhs = system / scale, rhs / scale
    shifted = normalised + torch.tensor([damping, damping, damping, 0.0, 0.0, 0.0], dtype=albedo.dtype)[:, None]
    system_rate = (2 * albedo[:, None] * moment - normalised[None] * scale_rate[:, None]) / scale  # dT / da_j: (3j, 6, N)
    rhs_rate = (projection - scaled_rhs[None] * scale_rate[:, None]) / scale  # dr' / da_j: (3j, 3, N)
    direction = symmetric_apply(symmetric_cofactors(shifted, shifted), scaled_rhs)  # adj(T) r'
    direction_rate = 2 * symmetric_apply(symmetric_cofactors(shifted, system_rate), scaled_rhs) + symmetric_apply(
        symmetric_cofactors(shifted, shifted), rhs_rate
    )  # (3j, 3, N)
    inverse_length = torch.rsqrt(direction.square().sum(0) + tiny)
    normal = direction * inverse_length
    # d unit(y) = q (dy - q^2 y (y . dy)), q = (|y|^2 + tiny)^-1/2
    normal_rate = inverse_length * (direction_rate - normal * (normal[None] * direction_rate).sum(1, keepdim=True))  # (3j, 3, N)
    numerator, denominator = _albedo_terms(normal, moments, damping)
    value = numerator / denominator
    # d A_c / d n = [A_c > 0] (r_c - 2 A_c B_c n) / den_c
    albedo_gradient = (projection - 2 * value[:, None] * symmetric_apply(moment, normal[None])) * ((value > 0).to(albedo.dtype) / denominator)[:, None]
    return (albedo_gradient[:, None] * normal_rate[None]).sum(2)


def implicit_step(albedo: torch.Tensor, moments: Moments, damping: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable Newton step at the fixed point a* = Phi(a*) (implicit differentiation).

    Computes a_out = a* + (I - J)^-1 (Phi(a*) - a*) with J = dPhi/da at a*, where a* and J are
    constants and Phi is evaluated with the (differentiable) ``moments``. At a fixed point the value
    is a*, and the derivative is (I - J)^-1 dPhi/dtheta, the exact derivative of the fixed point
    (implicit function theorem). Where I - J is nearly singular (the fixed point is not locally
    unique, e.g. a single pattern) the plain step Phi(a*) is used.

    Args:
        albedo: (3, N) converged albedo a* (detached).
        moments: moments carrying gradients.
        damping: relative damping.

    Returns:
        (albedo (3, N), normal (3, N)) carrying gradients.
    """
    albedo = albedo.detach()
    count = albedo.shape[1]
    inverse = torch.empty((3, 3, count), dtype=albedo.dtype)
    identity = torch.eye(3, dtype=albedo.dtype)[:, :, None]
    with torch.no_grad():
        # J in cache-sized blocks of pixels (its temporaries are a few (3, 6, n) tensors).
        for start in range(0, count, JACOBIAN_BLOCK):
            block = slice(start, min(start + JACOBIAN_BLOCK, count))
            constant = Moments(*(getattr(moments, name)[..., block] for name in Moments._FIELDS))
            residual_map = identity - alternation_jacobian(albedo[:, block], constant, damping)  # I - J
            det = determinant(residual_map)
            regular = det.abs() > 1e-3
            inverse[..., block] = torch.where(regular, adjugate(residual_map) / torch.where(regular, det, torch.ones_like(det)), identity)
    mapped, _ = alternation(albedo, moments, damping)
    albedo_out = albedo + (inverse * (mapped - albedo)[None]).sum(1)
    return albedo_out, normal_step(albedo_out, moments, damping)


def normal_condition(normal: torch.Tensor, albedo: torch.Tensor, moment: torch.Tensor) -> torch.Tensor:
    """Condition number of the normal estimate of the model I[m, c] = a_c b[m, c] . n.

    The Gauss-Newton matrix of the least-squares fit over the normal's two tangent directions
    (T = [t1 t2]), with the albedo re-optimised (Schur complement), is the 2 x 2 matrix
        S = sum_c a_c^2 (T^T B_c T - (T^T B_c n)(n^T B_c T) / (n^T B_c n)).
    The condition number is (trace(sum_c a_c^2 B_c) / 3) / lambda_min(S): the mean eigenvalue of
    the albedo-weighted lighting moment over the information on the worst normal direction, i.e.
    the squared noise amplification of the normal. It is infinite (capped at CONDITION_CAP) when
    a normal direction is unconstrained: a single pattern, identical or black patterns, too few
    lit superpixels. Unlike the condition number of the 3x3 normal system, it sees the albedo
    ambiguity (e.g. one colour pattern: three equations, five unknowns).

    Args:
        normal: (3, N) unit normals.
        albedo: (3, N) albedo, in the units of ``moment``.
        moment: (3, 6, N) per-channel symmetric moments B_c.

    Returns:
        (N,) condition numbers in [1, CONDITION_CAP].
    """
    energy, s11, s12, s22 = (term.sum(0) for term in _schur_terms(normal, albedo.square(), moment))
    return _condition(energy / 3, s11, s12, s22)


def channel_normal_conditions(normal: torch.Tensor, moment: torch.Tensor) -> torch.Tensor:
    """(3, N) condition numbers of each channel's own fit g_c = a_c n at the normals (3, N): the
    ``normal_condition`` of one channel's moments (3, 6, N) with its albedo free (Woodham). A
    channel with fewer than three independent equations gets CONDITION_CAP in float64, but only
    about 1e6 to 1e7 in float32 (rounding leaves a small eigenvalue)."""
    energy, s11, s12, s22 = _schur_terms(normal, torch.ones((), dtype=moment.dtype), moment)
    return _condition(energy / 3, s11, s12, s22)


def _schur_terms(normal, weight, moment):
    """Per-channel (3, N) terms of ``normal_condition``: weight * trace(B_c) and the entries s11,
    s12, s22 of weight * S_c, with the tangent basis formed once for all channels."""
    tiny = _tiny(moment.dtype)
    first, second = tangent_basis(normal)
    normal_energy = quadratic_form(moment, normal, normal).clamp_min(tiny)
    coupling_first, coupling_second = quadratic_form(moment, normal, first), quadratic_form(moment, normal, second)
    return (weight * symmetric_trace(moment),
            weight * (quadratic_form(moment, first, first) - coupling_first.square() / normal_energy),
            weight * (quadratic_form(moment, first, second) - coupling_first * coupling_second / normal_energy),
            weight * (quadratic_form(moment, second, second) - coupling_second.square() / normal_energy))


def _condition(scale, s11, s12, s22):
    """Condition numbers scale / lambda_min of the 2 x 2 matrices [[s11, s12], [s12, s22]], in
    [1, CONDITION_CAP] (the cap where lambda_min is negligible or the scale is zero)."""
    smallest = ((s11 + s22) / 2 - torch.sqrt(((s11 - s22) / 2).square() + s12.square())).clamp_min(0)
    singular = (smallest * CONDITION_CAP <= scale) | (scale <= _tiny(scale.dtype))
    condition = scale / torch.where(singular, torch.ones_like(smallest), smallest)
    return torch.where(singular, torch.full_like(condition, CONDITION_CAP), condition.clamp(1.0, CONDITION_CAP))
