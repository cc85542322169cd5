"""Fixed-iteration analytic photometric stereo for learning: fast, vectorised, unrolled gradients.

Same model as ``reconstruct.photometric_stereo`` (DESIGN section 4):
    I[m, c] = a_c * b[m, c] . n,     b[m, c] = sum_k E[m, k, c] f_k s_k l_k,   s_k = [l_k . n > 0]
but with fixed iteration counts and no per-pixel restarts, so that a training step over ~10^5
sampled pixels costs a few matrix products and wide elementwise operations:
- pixels lie on the last, contiguous axis of every tensor, and each 3x3 system is kept as its six
  unique entries, so that every per-pixel operation (moments, 3x3 solves by the adjugate, dot
  products) is a handful of elementwise operations over (.., N) rows instead of reductions over
  tiny trailing axes;
- b for all pixels comes from matrix products on a ``LightField`` over the precomputed weights
  ``light_reach``: with u_kn = s_kn f_kn / d_kn and l_kn = (p_k - X_n) / d_kn,
  b[m, c, :, n] = sum_k E[m, k, c] u_kn p_k - X_n sum_k E[m, k, c] u_kn, i.e. (N, K) @ (K, 12 M)
  in cache-sized blocks of pixels;
- the shadow masks and the alternations run a fixed number of times, without gradient; a pixel
  that sees every light keeps the b and moments of its all-ones mask between mask updates;
- gradients come from ``grad_alternations`` alternations (``reconstruct.unrolled_alternation``, whose
  backward is written out) unrolled from the detached solution with the final masks: a truncated
  implicit gradient, cheap in memory (the (N, K) weights are kept once; the shadowed ones are
  formed again in the backward pass, for the pixels with lights behind them only).
With the default (small) iteration counts the values are not converged: on noise-free data they
are typically within a degree or two of the full solver's, more on silhouettes. Training uses
this, evaluation uses ``solve_ps`` (convergence, validity flags, restarts, exact implicit gradients).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from capture_sim.errors import InputError, check_array, check_field_types
from capture_sim.rig import check_falloff, falloff_at
from reconstruct.lighting import LightField, differentiable_vectors, emission_scale, finite_albedo, lighting_matrix, lighting_moments
from reconstruct.pixel_solve import put_pixels, take_pixels
from reconstruct.unrolled_alternation import alternate, dot3


@dataclass(frozen=True)
class UnrolledPSConfig:
    """Iteration counts of ``solve_ps_unrolled``.

    The defaults are the cheapest counts found that learn as well as more iterations: on the
    demo's training set with the uncapped angular loss, (2, 3, 2) learned patterns with held-out
    MAE 10.41 / 10.54 deg (M = 2, seeds 0 / 1) and 9.58 / 9.53 (M = 4), against 10.78 / 11.02 and
    9.62 / 9.56 with (3, 5, 3), in 0.72x the step time (`displex train` runs on the demo scenes,
    `displex evaluate` MAE)."""

    shadow_iterations: int = 2
    """Attached-shadow mask updates (each followed by ``alternations`` alternations)."""
    alternations: int = 3
    """Albedo/normal alternations per mask, without gradient."""
    grad_alternations: int = 2
    """Alternations unrolled with gradient from the detached solution. With ``alternations = 0``
    and one shadow iteration the start no longer depends on the inputs and the gradient is exact
    (used by the gradient test)."""
    damping: float = 1e-6
    """Tikhonov damping relative to each 3x3 system's trace / 3."""
    saturation_threshold: float = 0.999
    """Captures at or above this get zero weight."""
    chunk_pixels: int = 8192
    """Pixels per block of the per-pixel algebra on lighting vectors (the (pixels x lights) products
    run in cache-sized sub-blocks of it). A speed setting: results change only by rounding."""

    def __post_init__(self):
        check_field_types(self)
        if not 0 < self.saturation_threshold <= 1:
            raise InputError(f"UnrolledPSConfig: saturation_threshold must lie in (0, 1], got {self.saturation_threshold!r}")
        if self.shadow_iterations < 1 or self.alternations < 0 or self.grad_alternations < 0 or self.chunk_pixels < 1:
            raise InputError("UnrolledPSConfig: shadow_iterations and chunk_pixels must be >= 1, alternation counts >= 0")
        if not 0 < self.damping <= 1:  # relative to the system's scale: above 1 it outweighs the data
            raise InputError(f"UnrolledPSConfig.damping must lie in (0, 1], got {self.damping!r}")


class _ShadowState:
    """Lighting vectors and moments under the current attached-shadow masks, without gradient.

    A pixel whose mask was all ones at the last update and still is keeps its vectors and moments
    (most pixels facing the display): only the others are formed again. The first update forms
    every pixel.

    Attributes (None before the first update):
        vectors: (M, 3, 3, N) effective lighting vectors b.
        moments: (3, 6, N) per-channel B_c, ``lighting_moments`` layout.
        rhs_moments: (3, 3, N) per-channel r_c.
        whole: (N,) bool, the stored mask of the pixel is all ones.
    """

    def __init__(self, num_pixels: int):
        self.vectors = self.moments = self.rhs_moments = None
        self.whole = torch.zeros(num_pixels, dtype=torch.bool)

    def update(self, field: LightField, normal, lighting, intensity, equation_weight) -> None:
        """Form the masks of ``normal`` (3, N); ``lighting`` (K, 12 M), ``intensity`` and
        ``equation_weight`` (M, 3, N) as ``solve_ps_unrolled`` has them."""
        whole = field.sees_all(None, normal)
        stale = ~(whole & self.whole)
        index = None if bool(stale.all()) else torch.nonzero(stale).squeeze(1)  # None: every pixel, no gathers
        self.whole = whole

        def pick(values):
            return values if index is None else take_pixels(values, index)

        vectors = normal.new_empty((lighting.shape[1] // 12, 3, 3, stale.shape[0] if index is None else index.numel()))
        for _ in field.vector_blocks(index, pick(normal), lighting, pick(whole), out=vectors):
            pass  # each block is written into ``vectors``
        moments, rhs_moments, _ = lighting_moments(vectors, pick(intensity), pick(equation_weight))
        if index is None:
            self.vectors, self.moments, self.rhs_moments = vectors, moments, rhs_moments
        else:
            for stored, fresh in ((self.vectors, vectors), (self.moments, moments), (self.rhs_moments, rhs_moments)):
                put_pixels(stored, index, fresh)


def light_reach(points: torch.Tensor, lights: torch.Tensor, falloff) -> torch.Tensor:
    """f(d) / d for every light and point: with (p_k - X_n) it gives f_k l_k.

    It depends on the geometry only, so callers that solve the same pixels repeatedly (learning)
    compute it once and pass it to ``solve_ps_unrolled``.

    Args:
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.

    Returns:
        (K, N) tensor in 1 / metres (times the falloff's unit), points' dtype; distances are
        clamped to >= 1 mm as in the full solver. Stored pixel-major (the transpose of a
        contiguous (N, K) tensor), so that a window of pixels is a block of memory and the
        solver's gathers of pixels copy whole rows.

    Raises:
        InputError: the falloff is not positive and finite at every distance.
    """
    check_falloff(falloff)
    if not (isinstance(points, torch.Tensor) and isinstance(lights, torch.Tensor)):
        raise InputError("points and lights must be torch tensors")
    check_array("points", points, ("N", 3))
    check_array("lights", lights, ("K", 3))
    lights = lights.to(points.dtype)
    square = torch.cdist(points, lights).square().clamp_min(1e-6)
    if getattr(falloff, "kind", None) == "inverse_square":
        inverse = torch.rsqrt(square)
        return (inverse * inverse * inverse).T  # f / d = d^-3 without a square root or pow
    distance = square.sqrt()
    reach = falloff_at(falloff, distance) / distance
    # DESIGN section 3: a fitted falloff can have a pole and change sign inside the working range.
    if not bool((torch.isfinite(reach) & (reach > 0)).all()):
        raise InputError(f"falloff is not positive and finite over light distances {float(distance.min()):.3f}..{float(distance.max()):.3f} m")
    return reach.T


def solve_ps_unrolled(captures, emission, points, lights, falloff, config: UnrolledPSConfig = UnrolledPSConfig(), reach: torch.Tensor | None = None):
    """Analytic photometric stereo with fixed iterations (see module docstring).

    Args:
        captures: (M, N, 3) captures in [0, 1].
        emission: (M, K, 3) effective emission (exposure included).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
        config: iteration counts and damping.
        reach: optional (K, N) ``light_reach(points, lights, falloff)``, precomputed (any strides).

    Returns:
        normal (N, 3) unit normals facing the camera, albedo (N, 3) >= 0; finite, differentiable
        in ``captures`` and ``emission`` (no gradient flows to points or lights). As in
        ``solve_ps``, the albedo's gradient in the emission grows as 1 / (emission peak)^2 and
        overflows for tiny emission (float32 at a peak of about 1e-19, float64 below about
        1e-154): give emission in units near 1.
    """
    check_array("captures", captures, ("M", "N", 3))
    check_array("lights", lights, ("K", 3))
    check_array("emission", emission, (captures.shape[0], lights.shape[0], 3), value_range=(0.0, float("inf")))
    check_array("points", points, (captures.shape[1], 3))
    if not all(isinstance(value, torch.Tensor) for value in (captures, emission, points, lights)):
        raise InputError("captures, emission, points and lights must be torch tensors")
    if not (captures.is_floating_point() and emission.is_floating_point()):
        raise InputError("captures and emission must be floating-point tensors")
    if 0 in (captures.shape[0], lights.shape[0]):
        raise InputError(f"need at least one pattern and one light, got M = {captures.shape[0]}, K = {lights.shape[0]}")
    num_pixels = captures.shape[1]
    # One working dtype, at least float32 (float16 moments overflow).
    dtype = torch.promote_types(torch.promote_types(captures.dtype, emission.dtype), torch.float32)
    captures, emission = captures.to(dtype), emission.to(dtype)
    if num_pixels == 0:
        empty = captures[0] * 0 + emission.sum() * 0  # (0, 3), on both inputs' graphs (zero gradients, not None)
        return empty, empty.clone()
    # Geometry is a constant, as in ``solve_ps``: a caller's lights that require grad would
    # otherwise get a partial gradient through the lighting matrix (its p_k term only).
    points, lights = points.detach().to(dtype), lights.detach().to(dtype)
    if reach is None:
        reach = light_reach(points, lights, falloff)
    # Shape only: reach is geometry from ``light_reach`` (finite by construction), and a finiteness
    # scan of its K x N values would cost more than a tenth of a training step.
    check_array("reach", reach, (lights.shape[0], num_pixels), finite=False)
    if not (isinstance(reach, torch.Tensor) and reach.is_floating_point()):
        raise InputError("reach must be a floating-point torch tensor (from light_reach)")
    # The light field keeps the weights pixel-major, as ``light_reach`` stores them (a view then).
    field = LightField.from_weights(points, lights, reach.to(dtype).T.contiguous(), config.chunk_pixels)
    scale = emission_scale(emission)  # keeps the squared terms in range whatever the radiance units
    lighting = lighting_matrix(emission / scale, lights)  # (K, 12 M)
    intensity = captures.permute(0, 2, 1).contiguous()  # (M, 3c, N); pixels contiguous for the gathers
    equation_weight = (intensity < config.saturation_threshold).to(dtype)
    with torch.no_grad():
        # Start facing the camera; a point at the camera centre has no view direction: -z there.
        normal = field.view.T.contiguous()
        normal[2] = torch.where(normal.abs().amax(0) > 0, normal[2], -1.0)
        albedo = torch.ones(3, num_pixels, dtype=dtype)
        state = _ShadowState(num_pixels)
        for _ in range(config.shadow_iterations):
            state.update(field, normal, lighting, intensity, equation_weight)
            normal, albedo = alternate(normal, albedo, state.moments, state.rhs_moments, config.damping, config.alternations)
        state.update(field, normal, lighting, intensity, equation_weight)
    # Gradients: the final masks' vectors as a function of the lighting (the (pixels x lights)
    # weights are re-formed in the backward pass, not kept), then the moments and alternations.
    vectors = differentiable_vectors(field, normal, lighting, state.vectors, state.whole)
    moments, rhs_moments, _ = lighting_moments(vectors, intensity, equation_weight, known=(state.moments, state.rhs_moments))
    normal, albedo = alternate(normal, albedo, moments, rhs_moments, config.damping, config.grad_alternations)
    view = field.view.T
    # Return camera-facing normals: a back-facing solution (specular or unconverged pixels) is
    # flipped; its albedo is left as solved.
    facing = torch.where(dot3(normal, view) < 0, -1.0, 1.0).to(dtype)
    return (normal * facing).T, finite_albedo(albedo / scale).T
