"""Woodham least-squares photometric stereo with calibrated near-field lights (the reference method).

Per pixel and colour channel c the Lambertian model is linear in g_c = a_c n:
    I[m, c] = b[m, c] . g_c,     b[m, c] = sum_k E[m, k, c] f_k s_k l_k
(DESIGN section 4; a absorbs the BRDF's 1 / pi). Each channel is solved on its own from the
normal equations B_c g_c = r_c (B_c = sum_m q b b^T, r_c = sum_m q I b), the normal is the
direction of sum_c g_c over the channels that determine it, and the albedo the least-squares a_c
for that normal. A channel with fewer than three independent equations (saturated captures
dropped, a colour pattern set) has no unique g_c: its damped solve returns some vector of the
family and would bias the sum, so it is left out of the normal (and still gets its albedo). The
condition number is that of the best channel (``woodham_condition``): a pixel no channel
determines on its own is flagged ill_conditioned, even where the channels together would fix
the normal (the analytic solver, ``photometric_stereo``, couples them through the shared normal).

Two kinds of input:
- an OLAT stack (M = K captures, emission diagonal: capture k lit by superpixel k alone): the
  per-light terms enter directly, b[k, c] = e_kc f_k l_k, without forming any b vector
  (``lighting.olat_moments``), so a full 144-light stack is processed block by block without being
  copied; lights darker than ``shadow_threshold`` times the pixel's brightest OLAT value in that
  channel are dropped as shadowed;
- any M >= 3 patterns (typically grey), through the same effective lighting vectors as
  ``photometric_stereo``.
In both cases saturated captures are dropped and attached shadows (l_k . n <= 0) are removed by the
same damped shadow search as the analytic method (``reconstruct.shadow_search``). With three
grey patterns every self-consistent shadow mask fits exactly: such pixels are searched from every
start and flagged ill_conditioned where two answers fit or where the answer sits on a lit
superpixel's tangent plane (``photometric_stereo.PSResult``). The solver runs without gradients.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from capture_sim.errors import InputError, check_array
from reconstruct.lighting import LightField, emission_scale, lighting_matrix, olat_moments
from reconstruct.photometric_stereo import (
    MAX_PIXELS_PER_SOLVE,
    PatternEvaluator,
    PSResult,
    SolverSettings,
    capture_flags,
    check_image_inputs,
    check_masked_inputs,
    check_solver_inputs,
    concatenate_results,
    finalise,
    image_pixels,
    scatter_result,
    unscale_albedo,
    working_config,
)
from reconstruct.pixel_solve import Moments, albedo_step, channel_normal_conditions, damped_solve, relative_residual, scaled_moments, unit
from reconstruct.shadow_search import restarted_search


@dataclass(frozen=True, kw_only=True)
class WoodhamConfig(SolverSettings):
    """Settings of the Woodham least-squares solver (``solve_woodham``): the shared ones
    (``SolverSettings``; the damping applies to each channel's 3x3 system) and the OLAT shadow cut."""

    shadow_threshold: float = 0.01
    """OLAT only: captures below this fraction of the pixel's brightest OLAT capture (per channel)
    are treated as shadowed and dropped."""

    def __post_init__(self):
        super().__post_init__()
        if not 0 <= self.shadow_threshold < 1:
            raise InputError(f"WoodhamConfig: shadow_threshold must lie in [0, 1), got {self.shadow_threshold!r}")


def woodham_condition(normal: torch.Tensor, albedo: torch.Tensor, moment: torch.Tensor) -> torch.Tensor:
    """(N,) condition numbers of Woodham's normals (3, N): that of the best-determined channel
    (``pixel_solve.channel_normal_conditions``; the albedo (3, N) is not needed: each channel's is
    free). In float32 a ``condition_threshold`` of 1e6 or more lets rank-deficient channels in."""
    return channel_normal_conditions(normal, moment).amin(dim=0)


def woodham_fit(moments: Moments, damping: float, condition_threshold: float):
    """Per-channel least squares g_c = B_c^-1 r_c, normal = direction of the sum of g_c over the
    channels whose condition number is within ``condition_threshold``
    (``pixel_solve.channel_normal_conditions``; every channel where none is: such a pixel is
    flagged ill_conditioned anyway).

    Returns (albedo (3, N), normal (3, N), converged (N,) all True), the shadow-search fit.
    """
    per_channel = damped_solve(moments.moment, moments.projection, damping)  # (3, 3, N)
    usable = channel_normal_conditions(unit(per_channel.sum(0)), moments.moment) <= condition_threshold  # (3, N)
    usable |= ~usable.any(dim=0, keepdim=True)
    normal = unit((per_channel * usable[:, None]).sum(0))
    return albedo_step(normal, moments, damping), normal, torch.ones(normal.shape[1], dtype=torch.bool)


class _OlatEvaluator:
    """Shadow-search evaluator for an OLAT stack, gathering capture blocks on demand.

    Args:
        light_field: geometry of the N solved pixels.
        light_emission: (K, 3) emission of light k in capture k.
        captures: (K, P, 3) OLAT captures (any float dtype; not copied).
        pixel_index: (N,) long rows of ``captures`` solved, or None for all P = N.
        config: WoodhamConfig.
        dtype: working dtype.
    """

    def __init__(self, light_field: LightField, light_emission, captures, pixel_index, config, dtype):
        self.field, self.light_emission, self.captures = light_field, light_emission, captures
        self.pixel_index, self.config, self.dtype = pixel_index, config, dtype
        self._flags = None

    def _block(self, rows):
        """Channel-major captures (3, n, K), equation weights (3, n, K) and capture scale (n,)."""
        source = rows if self.pixel_index is None else self.pixel_index[rows]
        # One contiguous copy of the block: reductions over lights in the strided view are slow.
        captures = self.captures[:, source].permute(2, 1, 0).to(self.dtype).contiguous()
        brightest = captures.amax(dim=2, keepdim=True)
        weight = (captures < self.config.saturation_threshold) & (captures > self.config.shadow_threshold * brightest)
        scale = captures.abs().amax(dim=(0, 2)).clamp_min(torch.finfo(self.dtype).tiny ** 0.5)
        return captures, weight.to(self.dtype), scale

    def capture_flags(self):
        """dark (N,) and saturated (N,) bool over the whole stack, recorded by the first full
        ``evaluate`` (which reads every capture anyway)."""
        if self._flags is None:
            self.evaluate(None, self.field.view.T)
        return self._flags

    def masks_differ(self, index, first, second):
        return self.field.masks_differ(index, first, second)

    def evaluate(self, index, normal):
        moments = Moments.empty(normal.shape[1], self.dtype)
        record = index is None and self._flags is None
        if record:
            dark = torch.empty(normal.shape[1], dtype=torch.bool)
            saturated = torch.empty_like(dark)
        whole = self.field.sees_all(index, normal)
        for start, stop, rows in self.field.block_rows(index):
            weight = self.field.shadowed_weights(rows, normal[:, start:stop], whole[start:stop])
            captures, equation_weight, scale = self._block(rows)
            raw = olat_moments(weight, self.light_emission, captures, equation_weight, self.field.points[rows], self.field.lights)
            moments.write(start, stop, scaled_moments(*raw, scale))
            if record:
                dark[start:stop] = captures.amax(dim=(0, 2)) < self.config.dark_threshold
                saturated[start:stop] = (captures >= self.config.saturation_threshold).any(dim=2).any(dim=0)
        if record:
            self._flags = (dark, saturated)
        return moments


def _solve_block(evaluator, light_field: LightField, config, dark_and_saturated=None) -> PSResult:
    """Search and finalise; without ``dark_and_saturated`` the (OLAT) evaluator provides them."""

    def fit(albedo, moments):
        return woodham_fit(moments, config.damping, config.condition_threshold)

    count = light_field.num_pixels
    view = light_field.view.T.contiguous()
    # Few captures per channel (patterns) can fit wrong masks well channel by channel: poor fits of
    # the shared normal are restarted (on a noise-free sphere under tri_gradient M = 3, 71 of 2000
    # pixels were valid and 12-137 deg off; 20 after, all below the poor-fit residual). OLAT
    # stacks overdetermine each channel; their poor fits are specular, which restarts do not help.
    patterns = isinstance(evaluator, PatternEvaluator)
    restart_residual = config.residual_threshold if patterns else None
    exactly_determined = evaluator.exactly_determined() if patterns else None
    state, condition = restarted_search(evaluator, fit, torch.ones((3, count), dtype=view.dtype), view, config, woodham_condition, restart_residual,
                                        exactly_determined)
    if patterns:  # OLAT stacks leave shadowed equations out of the moments already
        condition = evaluator.lit_condition(state.normal, state.albedo, condition, config.kink_tolerance_deg, woodham_condition)
        condition = evaluator.kink_condition(state.normal, exactly_determined, condition, config.kink_tolerance_deg)
    dark, saturated = evaluator.capture_flags() if dark_and_saturated is None else dark_and_saturated
    albedo = state.albedo * (state.moments.capture_scale / state.moments.lighting_scale)
    flags = {"dark": dark, "saturated": saturated, "not_converged": ~state.converged}
    return finalise(state.normal.T, albedo.T, condition, relative_residual(state.normal, state.moments), flags, light_field, config)


def _diagonal_light_emission(emission: torch.Tensor):
    """(K, 3) per-light emission if ``emission`` (M, K, 3) is one-light-at-a-time, else None."""
    num_patterns, num_lights, _ = emission.shape
    if num_patterns != num_lights:
        return None
    # A structural test: comparing sums would leave float32 rounding residues.
    off_diagonal = ~torch.eye(num_lights, dtype=torch.bool)
    if bool((emission[off_diagonal] != 0).any()):
        return None
    return torch.diagonal(emission, dim1=0, dim2=1).T  # (K, 3)


def _check_inputs(captures, emission, points, lights, config, chunk_size):
    check_solver_inputs(captures, emission, points, lights, config, chunk_size, WoodhamConfig, min_patterns=3, solver="Woodham photometric stereo")


@torch.no_grad()
def _solve(captures, emission, points, pixel_index, lights, falloff, config, chunk_size, light_emission=None) -> PSResult:
    """Shared driver; ``light_emission`` (K, 3) selects the OLAT path directly (``emission`` unused)."""
    if light_emission is None:
        light_emission = _diagonal_light_emission(emission.detach())
    dtype = torch.promote_types(torch.promote_types(captures.dtype, (emission if light_emission is None else light_emission).dtype), torch.float32)
    points = torch.as_tensor(points).detach().to(dtype)
    lights = torch.as_tensor(lights).detach().to(dtype)
    config = working_config(config, dtype)
    if light_emission is not None:
        light_emission = light_emission.to(dtype)
        scale = emission_scale(light_emission)
        light_emission, lighting = light_emission / scale, None
    else:
        emission = emission.detach().to(dtype)
        scale = emission_scale(emission)
        lighting = lighting_matrix(emission / scale, lights)
    count = points.shape[0] if pixel_index is None else pixel_index.numel()
    results = []
    for start in range(0, count, MAX_PIXELS_PER_SOLVE):
        if pixel_index is None:
            rows = slice(start, start + MAX_PIXELS_PER_SOLVE)
            block_index = None if count <= MAX_PIXELS_PER_SOLVE else torch.arange(start, min(count, start + MAX_PIXELS_PER_SOLVE))
        else:
            rows = block_index = pixel_index[start : start + MAX_PIXELS_PER_SOLVE]
        light_field = LightField(points[rows], lights, falloff, config.min_distance, chunk_size)
        if light_emission is not None:
            evaluator = _OlatEvaluator(light_field, light_emission, captures.detach(), block_index, config, dtype)
            results.append(_solve_block(evaluator, light_field, config))
        else:
            block_captures = captures[:, rows].detach().to(dtype).permute(0, 2, 1).contiguous()
            equation_weight, capture_scale, dark, saturated = capture_flags(block_captures, config)
            evaluator = PatternEvaluator(light_field, lighting, block_captures, equation_weight, capture_scale)
            results.append(_solve_block(evaluator, light_field, config, (dark, saturated)))
    return unscale_albedo(concatenate_results(results, dtype), scale)


def solve_woodham(captures, emission, points, lights, falloff, config: WoodhamConfig = WoodhamConfig(), chunk_size: int = 8192) -> PSResult:
    """Woodham least-squares photometric stereo of a set of pixels (see the module docstring).

    Args:
        captures: (M, N, 3) linear captures with full scale 1 (``config``'s dark and saturation
            thresholds are in these units), M >= 3: an OLAT stack (M = K, e.g. a scene's ``olat``
            times an exposure e, with ``emission`` e times the identity) or captures under M
            patterns; float16 stacks are read block by block without a full copy.
        emission: (M, K, 3) effective emission E >= 0 (exposure included). A diagonal one (capture
            k lit by superpixel k alone) selects the OLAT path.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor, e.g. ``capture_sim.rig.Falloff``.
        config: solver settings.
        chunk_size: pixels per block of (pixels x lights) work.

    Returns:
        PSResult (no gradients) with (N, 3) normals and albedo (rho / pi), (N,) valid, condition,
        residual and flags, as ``solve_ps``.

    Raises:
        InputError: wrong shapes, non-finite inputs, negative emission (captures may be slightly
            negative), fewer than 3 captures, or a falloff that is not positive and finite over
            the light distances.

    Example:
        >>> olat = scene_olat.reshape(144, -1, 3)  # doctest: +SKIP
        >>> e = auto_exposure(olat)  # raw OLAT values come in any units; put them at full scale 1
        >>> eye = e * torch.eye(144)[:, :, None].expand(144, 144, 3)  # doctest: +SKIP
        >>> result = solve_woodham(e * olat, eye, points, rig.lights(), rig.falloff)  # doctest: +SKIP
    """
    _check_inputs(captures, emission, points, lights, config, chunk_size)
    return _solve(captures, emission, points, None, lights, falloff, config, chunk_size)


def solve_woodham_olat(
    captures, points, lights, falloff, exposure: float = 1.0, config: WoodhamConfig = WoodhamConfig(), chunk_size: int = 8192
) -> PSResult:
    """Woodham least squares on an OLAT stack (capture k lit by superpixel k alone at unit intensity).

    Args:
        captures: (K, N, 3) OLAT captures of N pixels with full scale 1 (e.g. a scene's OLAT stack
            times ``exposure``, or simulated OLAT captures with the backlight removed), not copied.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
        exposure: exposure e of the captures (the effective emission of light k is e).
        config: solver settings.
        chunk_size: pixels per block of (pixels x lights) work.

    Returns:
        PSResult of (N, ...) tensors, as ``solve_woodham``; albedo a = rho / pi in the stack's units.
    """
    check_array("lights", lights, ("K", 3))
    check_array("captures", captures, (lights.shape[0], "N", 3))
    if not (isinstance(captures, torch.Tensor) and captures.is_floating_point()):
        raise InputError("captures must be a floating-point torch tensor")
    dtype = torch.promote_types(captures.dtype, torch.float32)
    try:
        if isinstance(exposure, bool):
            raise TypeError("a bool")
        exposure = float(exposure)
    except (TypeError, ValueError):
        raise InputError(f"exposure must be a positive number, got {exposure!r}") from None
    if not 0 < exposure <= torch.finfo(dtype).max:
        raise InputError(f"exposure must be a positive number within {dtype}'s range, got {exposure!r}")
    emission = torch.full((lights.shape[0], 3), exposure, dtype=dtype)
    _check_inputs(captures, emission[None].expand(lights.shape[0], -1, -1), points, lights, config, chunk_size)
    return _solve(captures, None, points, None, lights, falloff, config, chunk_size, light_emission=emission)


def solve_woodham_image(
    captures, emission, points, mask, lights, falloff, config: WoodhamConfig = WoodhamConfig(), chunk_size: int = 8192
) -> PSResult:
    """``solve_woodham`` on images: solves the pixels inside ``mask``.

    Args:
        captures: (M, H, W, 3) linear captures (e.g. a (K, H, W, 3) OLAT stack; not copied).
        emission: (M, K, 3) effective emission (the identity for a scene's OLAT stack).
        points: (H, W, 3) surface points, metres, camera frame.
        mask: (H, W) bool, pixels to solve.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
        config: solver settings.
        chunk_size: pixels per block of (pixels x lights) work.

    Returns:
        PSResult with (H, W, 3) normals and albedo and (H, W) valid, condition, residual and flags; pixels
        outside the mask are invalid with normal (0, 0, -1) and albedo 0.
    """
    check_image_inputs(captures, points, mask)
    flat_captures, flat_points, pixel_index = image_pixels(captures, points, mask)
    check_masked_inputs(_check_inputs, flat_captures, emission, flat_points, pixel_index, lights, config, chunk_size)
    result = _solve(flat_captures, emission, flat_points, pixel_index, lights, falloff, config, chunk_size)
    return scatter_result(result, pixel_index, captures.shape[1], captures.shape[2])
