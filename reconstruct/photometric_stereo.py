"""Analytic multiplexed RGB photometric stereo, iterated to convergence with attached shadows.

Model (DESIGN section 4; Lambertian, near-field), per pixel and equation (pattern m, channel c):
    I[m, c] = a_c * b[m, c] . n,     b[m, c] = sum_k E[m, k, c] f_k s_k l_k
with a the RGB albedo (it absorbs the Lambertian 1 / pi: a = rho / pi), n the unit normal, E the
effective emission (exposure included), f_k the falloff, l_k the unit direction to superpixel k and
s_k = [l_k . n > 0] the attached-shadow mask (superpixels behind the tangent plane add nothing).

Algorithm (all pixels at once; ``reconstruct.reference`` is a plain per-pixel version):
1. start from n = view direction, its shadow mask, and albedo a_c = max_m I[m, c];
2. for the current masks, alternate to convergence (the published method stops after one
   alternation and is biased; ``reconstruct.pixel_solve``):
     normal given albedo: (sum_c a_c^2 B_c + lambda I) n = sum_c a_c r_c with the per-channel
     moments B_c = sum_m b b^T, r_c = sum_m I b, solved in closed form, normalised, with
     damping lambda relative to the system's scale;
     albedo given normal: a_c = n . r_c / (n^T B_c n + mu_c), clamped at 0;
3. move to the new normal's own mask if that lowers the true residual (line search), repeat
   2-3 until the masks reproduce themselves; restart doubtful pixels from 12 other normals and keep
   the lowest residual (``reconstruct.shadow_search``).
Saturated equations get zero weight; where patterns leave superpixels exactly dark, the condition
number that flags ill-conditioned pixels leaves out zero captures at a kink (a shadow explains them
as well as superpixels on the tangent plane).
Quantities are rescaled per pixel so that every 3x3 system is of order one in any dtype.

Gradients (w.r.t. captures and emission; geometry and the shadow masks are constants) are exact
implicit-function-theorem gradients of the converged fixed point a* = Phi(a*) of one alternation
Phi (``pixel_solve.implicit_step``): after the search, one differentiable Newton step
    a_out = a* + (I - dPhi/da)^-1 (Phi(a*) - a*)      (a*, dPhi/da detached)
has the derivative (I - dPhi/da)^-1 dPhi/dtheta of the fixed point. Every pixel outputs the
searched value with that derivative, so values do not depend on gradient tracking. The cost is one
alternation plus the per-pixel 3x3 Jacobian dPhi/da in closed form
(``pixel_solve.alternation_jacobian``); the shadowed (pixels x lights) weights are re-formed
block by block in the backward pass instead of being kept. Unrolling a few alternations from a
detached start would be cheaper but biased. A not-converged pixel gets the derivative of the nearby fixed point, an approximation of its
returned value's (``NEAR_FIXED_POINT`` says how close), or none (zero) where its value lies far
from any fixed point: the step's derivative there can even have the wrong sign. The gradient is
the same in every configuration;
``torch.autograd.gradcheck`` needs tight convergence (tolerance_deg=1e-10, max_alternations=1000,
as in tests/test_photometric_stereo.py) because finite differences of the solver are otherwise
limited by its stopping tolerance.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from capture_sim.errors import InputError, check_array, check_field_types, is_whole_number
from reconstruct import alternate_kernel
from reconstruct.lighting import LightField, differentiable_vectors, emission_scale, finite_albedo, lighting_matrix
from reconstruct.pixel_solve import CONDITION_CAP, Moments, implicit_step, length, normal_condition, normalised_moments, relative_residual, take_pixels
from reconstruct.shadow_search import restarted_search

FLAG_NAMES = ("dark", "saturated", "ill_conditioned", "back_facing", "bad_geometry", "not_converged", "poor_fit", "grazing")
INVALIDATING_FLAGS = {
    "dark": "too dark",
    "ill_conditioned": "too few or too similar captures",
    "back_facing": "the fit faces away from the camera",
    "bad_geometry": "the point lies behind the camera or within min_distance of a superpixel (depth in metres?)",
}
"""The flags that make a pixel invalid, with what each means (for messages)."""


def invalid_causes(flag_shares: dict[str, float]) -> str:
    """'bad_geometry (the point lies ...) on 100% of the pixels; ...': the invalidating flags
    raised, largest share first, then the share of saturated pixels (their captures at full scale
    are left out of the fit, which can leave too few), from a dict of flag name -> share of
    pixels in [0, 1]."""
    raised = sorted(((share, name) for name, share in flag_shares.items() if name in INVALIDATING_FLAGS and share > 0), reverse=True)
    text = "; ".join(f"{name} ({INVALIDATING_FLAGS[name]}) on {100 * share:.3g}% of the pixels" for share, name in raised) or "no flag raised"
    # Saturated captures leave the fit (so too few equations may remain) without invalidating a pixel themselves.
    saturated = flag_shares.get("saturated", 0.0)
    return text + (f"; saturated (captures at full scale, left out of the fit) on {100 * saturated:.3g}% of the pixels" if saturated > 0 else "")


MAX_PIXELS_PER_SOLVE = 1 << 19
"""Pixels solved together (a full 512 x 612 image is one solve; larger inputs are split)."""


MAX_MIN_DISTANCE = 0.1
"""Metres: ``PSConfig.min_distance`` above this would flag points at ordinary rig distances."""


@dataclass(frozen=True, kw_only=True)
class SolverSettings:
    """Settings that the analytic solver (``PSConfig``) and Woodham (``WoodhamConfig``) share: the
    shadow search, the damping and the per-pixel flags."""

    damping: float = 1e-9
    """Tikhonov damping relative to each 3x3 system's scale: lambda = damping * trace / 3. Raised
    to at least 8 machine epsilons of the working dtype (about 1e-6 in float32) so that damped
    systems stay positive definite after rounding. Larger values bias ill-conditioned pixels."""
    max_shadow_iterations: int = 20
    """Cap on attached-shadow mask updates (each re-solves only pixels whose mask changed; the
    first fits every pixel, so at least 1)."""
    line_search_steps: int = 4
    """Times a shadow-search step that would increase the residual is halved before giving up."""
    kink_tolerance_deg: float = 0.5
    """A pixel whose shadow-search step is rejected sits at a kink of the shadowed model (a
    superpixel on its tangent plane); it counts as converged if that step is shorter (degrees)."""
    restart_condition: float = 300.0
    """Pixels whose condition number exceeds this, or that did not converge, are searched again
    from 12 more starting normals and keep the lowest residual (``math.inf`` restarts only the
    pixels that did not converge). Pixels that converge facing away from the camera are not
    restarted: on the default test scenes nearly all are glossy ones whose best Lambertian fit
    faces away, and restarting them too changed no MAE by more than 0.01 deg at up to twice the
    solve time; a rare Lambertian pixel near grazing that a restart would rescue stays flagged
    back_facing (a small ``restart_condition`` restarts every pixel)."""
    dark_threshold: float = 1e-3
    """Pixels whose brightest capture is below this (full scale 1) are flagged dark."""
    saturation_threshold: float = 0.999
    """Captures at or above this are saturated: their equations are dropped, the pixel flagged.
    Both thresholds assume exposed captures in [0, 1] (scale a raw OLAT stack first, see
    ``solve_woodham``)."""
    condition_threshold: float = 1e4
    """Pixels whose normal condition number (roughly the squared noise amplification of the
    normal: ``pixel_solve.normal_condition`` for ``solve_ps``, ``woodham.woodham_condition`` for
    Woodham, where it also decides which channels enter the normal) exceeds this are flagged
    ill_conditioned."""
    min_distance: float = 1e-3
    """Metres; light distances are clamped to at least this, and points within it of a
    superpixel or not in front of the camera (z <= min_distance) are flagged bad_geometry."""
    residual_threshold: float = 0.1
    """Pixels whose relative fit residual (``PSResult.residual``) exceeds this are flagged poor_fit:
    the Lambertian model leaves more than 1% of the capture energy unexplained (specular light,
    heavy noise, or a wrong shadow mask)."""
    grazing_cos: float = 0.1
    """Valid normals estimated more than arccos(grazing_cos) (84 deg) from the view direction
    (n . v < this) are flagged grazing: few superpixels light them and their shading barely
    changes with the normal."""

    def __post_init__(self):
        """Refuse bad values: field types, damping outside (0, 1], fewer than one shadow iteration
        (the first one is the fit itself), negative line-search steps, non-positive tolerances and
        thresholds, ``min_distance`` outside (0, MAX_MIN_DISTANCE], dark and saturation thresholds
        out of order, ``residual_threshold`` or ``grazing_cos`` outside [0, 1]."""
        check_field_types(self)
        name = type(self).__name__
        if not 0 < self.damping <= 1:  # relative to the system's scale: above 1 it outweighs the data
            raise InputError(f"{name}: damping must lie in (0, 1], got {self.damping!r}")
        if self.max_shadow_iterations < 1 or self.line_search_steps < 0:
            raise InputError(f"{name}: need max_shadow_iterations >= 1 and line_search_steps >= 0, got "
                             f"{self.max_shadow_iterations!r} and {self.line_search_steps!r}")
        for key in ("kink_tolerance_deg", "restart_condition", "condition_threshold"):
            if not getattr(self, key) > 0:
                raise InputError(f"{name}: {key} must be positive, got {getattr(self, key)!r}")
        if not 0 < self.min_distance <= MAX_MIN_DISTANCE:
            raise InputError(f"{name}: min_distance must lie in (0, {MAX_MIN_DISTANCE:g}] metres, got {self.min_distance!r}")
        if not 0 <= self.dark_threshold < self.saturation_threshold <= 1:
            raise InputError(f"{name}: need 0 <= dark_threshold < saturation_threshold <= 1, got {self.dark_threshold!r} and {self.saturation_threshold!r}")
        for key in ("residual_threshold", "grazing_cos"):
            value = getattr(self, key)
            if not 0 <= value <= 1:
                raise InputError(f"{name}: {key} must lie in [0, 1], got {value!r}")


@dataclass(frozen=True, kw_only=True)
class PSConfig(SolverSettings):
    """Settings of the analytic photometric-stereo solver (``solve_ps``): the shared ones
    (``SolverSettings``) and the albedo/normal alternation's."""

    max_alternations: int = 50
    """Cap on albedo/normal alternations per shadow mask (usually a few suffice). Below float64, a
    pixel whose moves stop shrinking above the rounding level gets up to ``min(max_alternations,
    pixel_solve.WIDE_ALTERNATIONS)`` more in float64 (``pixel_solve.alternate``)."""
    tolerance_deg: float = 1e-3
    """Alternations stop when no pixel's normal moves by more than this (degrees)."""

    def __post_init__(self):
        super().__post_init__()
        if self.max_alternations < 1:
            raise InputError(f"PSConfig: max_alternations must be >= 1, got {self.max_alternations!r}")
        if not self.tolerance_deg > 0:
            raise InputError(f"PSConfig: tolerance_deg must be positive, got {self.tolerance_deg!r}")


@dataclass(frozen=True, eq=False)
class PSResult:
    """Per-pixel result of a photometric-stereo solve (shapes (N, ...) or image-shaped (H, W, ...)).

    Attributes:
        normal: (..., 3) unit normals, camera frame, facing the camera (n . v > 0) where valid;
            (0, 0, -1) where invalid.
        albedo: (..., 3) RGB albedo >= 0 with the 1 / pi of the Lambertian BRDF absorbed
            (a = rho / pi); 0 where invalid.
        valid: (...) bool: not dark, not ill-conditioned, not back-facing, not bad geometry (and
            inside the mask for image solves). Saturated and not-converged pixels stay valid: their
            flags say that the estimate is degraded, not meaningless (not-converged ones far from
            a fixed point carry no gradient, see ``solve_ps``).
        condition: (...) normal condition number (``pixel_solve.normal_condition``; Woodham's:
            ``woodham.woodham_condition``), in [1, CONDITION_CAP] (without the zero captures at a
            kink of patterns that leave superpixels exactly dark: ``PatternEvaluator.lit_condition``).
        residual: (...) RMS residual of the Lambertian fit relative to the RMS capture, in [0, 1],
            over the equations used (saturated captures are left out; 1 where none is left or no
            light was captured, and outside the mask of image solves) (``pixel_solve.
            relative_residual``; detached): a per-pixel confidence, also for invalid pixels.
        flags: dict of (...) bool masks named in FLAG_NAMES: dark, saturated, ill_conditioned,
            back_facing, bad_geometry (point behind the camera or on a superpixel), not_converged
            (shadow search stopped by its caps or away from a self-consistent mask), poor_fit
            (a valid pixel whose residual exceeds the config's ``residual_threshold``), grazing (a
            valid pixel whose estimated n . v is below the config's ``grazing_cos``). Like
            saturated and not_converged, poor_fit and grazing pixels stay valid.

    A wrong shadow mask that fits exactly is flagged only where the search finds both answers.
    With few equations (3 M close to the 5 unknowns, e.g. tri_complementary at M = 2), a
    Lambertian pixel near a silhouette can have a second normal, with another self-consistent
    mask, that fits its noise-free captures as well as the true one; the search returns one of
    them, and the condition number, a local measure, cannot tell. Measured on 400 noise-free
    points with n . v in [0.1, 0.5] under tri_complementary M = 2: 41 valid, unflagged normals 1
    to 26 deg off, every restart landing on the same one. Three grey patterns are the extreme
    case (every self-consistent mask fits exactly): those pixels are searched from every start
    and flagged ill_conditioned where two answers fit (``shadow_search.restarted_search``) or
    where the answer sits on the tangent plane of a superpixel that carries a pattern's light
    (``PatternEvaluator.kink_condition``). On a noise-free sphere on the backlit reference rig,
    19 (olat M = 3) and 4 (mono_random M = 3) valid pixels were 11-111 deg off before these
    checks; after them 0 of 42 and 1 of 11 (13 deg, condition 3400). The checks also flag
    correct answers that cannot be told from a wrong one (olat M = 3: 61 correct valid pixels
    before, 42 after) and cost the restarts of every such pixel. The ambiguity is in the data;
    more patterns remove it.
    """

    normal: torch.Tensor
    albedo: torch.Tensor
    valid: torch.Tensor
    condition: torch.Tensor
    residual: torch.Tensor
    flags: dict = field(default_factory=dict)


def working_config(config, dtype):
    """``config`` with the damping raised to the working dtype's floor (see PSConfig.damping)."""
    floor = 8 * torch.finfo(dtype).eps
    return config if config.damping >= floor else dataclasses.replace(config, damping=floor)


def capture_flags(captures: torch.Tensor, config):
    """Equation weights and per-pixel capture statistics.

    Args:
        captures: (M, 3, N) captures, pixels last.
        config: settings with ``saturation_threshold`` and ``dark_threshold``.

    Returns:
        equation_weight (M, 3, N) (0 for saturated equations), capture_scale (N,) max |I|,
        dark (N,) bool, saturated (N,) bool.
    """
    captures = captures.detach()
    # Reductions, not |I| or comparison tensors: with an OLAT stack (M = K) each full-size
    # temporary would take as much memory as the captures.
    darkest, brightest = captures.aminmax(dim=0)
    darkest, brightest = darkest.amin(dim=0), brightest.amax(dim=0)
    scale = torch.maximum(brightest, -darkest).clamp_min(torch.finfo(captures.dtype).tiny ** 0.5)
    equation_weight = torch.lt(captures, config.saturation_threshold).to(captures.dtype)
    return equation_weight, scale, brightest < config.dark_threshold, brightest >= config.saturation_threshold


def finalise(normal, albedo, condition, residual, flags: dict, field_: LightField, config) -> PSResult:
    """Add the geometric, conditioning and fit flags, decide validity, give invalid pixels defaults.

    Args:
        normal: (N, 3) estimated unit normals.
        albedo: (N, 3) estimated albedo.
        condition: (N,) normal condition numbers.
        residual: (N,) relative fit residuals.
        flags: dark, saturated and not_converged, (N,) bool each.
        field_: the pixels' light field (view directions, bad-geometry marks).
        config: settings with ``condition_threshold``, ``residual_threshold`` and ``grazing_cos``.

    Returns:
        PSResult of the N pixels.
    """
    flags = dict(flags)
    facing = (normal.detach() * field_.view).sum(1)
    flags["ill_conditioned"] = condition > config.condition_threshold
    flags["back_facing"] = facing <= 0
    flags["bad_geometry"] = field_.bad
    valid = ~(flags["dark"] | flags["ill_conditioned"] | flags["back_facing"] | flags["bad_geometry"])  # INVALIDATING_FLAGS
    # Marks on estimates that are kept: an invalid pixel's normal is replaced below anyway.
    flags["poor_fit"] = valid & (residual > config.residual_threshold)
    flags["grazing"] = valid & (facing < config.grazing_cos)
    default_normal = torch.tensor([0.0, 0.0, -1.0], dtype=normal.dtype)
    normal = torch.where(valid[:, None], normal, default_normal)
    albedo = torch.where(valid[:, None], albedo, torch.zeros((), dtype=albedo.dtype))
    return PSResult(
        normal=normal, albedo=albedo, valid=valid, condition=condition, residual=residual.detach(), flags={name: flags[name] for name in FLAG_NAMES}
    )


class PatternEvaluator:
    """Shadow-search evaluator for multiplexed patterns (see ``reconstruct.shadow_search``).

    Moments are formed block by block, straight from each block of lighting vectors.

    Args:
        light_field: geometry of the N pixels.
        lighting: (K, 12 M) lighting matrix (used as a constant).
        captures: (M, 3, N) captures, pixels last.
        equation_weight: (M, 3, N) equation weights.
        capture_scale: (N,) per-pixel capture normalisation.
        keep_vectors: keep the lighting vectors in the moments (needed for gradients).
    """

    def __init__(self, light_field: LightField, lighting, captures, equation_weight, capture_scale, keep_vectors: bool = False):
        self.field, self.lighting = light_field, lighting.detach()
        self.captures, self.equation_weight, self.capture_scale = captures.detach(), equation_weight, capture_scale
        self.num_patterns = (lighting.shape[1] // 12) if keep_vectors else None

    def masks_differ(self, index, first, second):
        return self.field.masks_differ(index, first, second)

    def evaluate(self, index, normal):
        count = normal.shape[1]
        moments = Moments.empty(count, normal.dtype, self.num_patterns)
        for start, stop, vectors in self.field.vector_blocks(index, normal, self.lighting):
            if index is None:
                captures, weight, scale = self.captures[..., start:stop], self.equation_weight[..., start:stop], self.capture_scale[start:stop]
            else:
                pixels = index[start:stop]
                captures, weight = take_pixels(self.captures, pixels), take_pixels(self.equation_weight, pixels)
                scale = self.capture_scale[pixels]
            moments.write(start, stop, normalised_moments(vectors, captures, weight, scale), vectors)
        return moments

    def emission(self) -> torch.Tensor:
        """(K, M, 3) effective emission E[m, k, c] of the lighting matrix (its constant column)."""
        return self.lighting.reshape(self.lighting.shape[0], self.captures.shape[0], 3, 4)[..., 3]

    def exactly_determined(self) -> torch.Tensor:
        """(N,) bool: pixels that every self-consistent shadow mask fits exactly, so that their
        captures cannot rule out a wrong mask: grey patterns (each pattern's emission the same in
        every informative channel up to a scale, within ``GREY_TOLERANCE``) and, in every
        informative channel, at most three usable (unsaturated) captures, three in some, the same
        patterns in each channel with three. Those channels then solve one 3 x 3 system for
        a_c n, and their answers agree whatever the mask. A channel is not informative where its
        emission is the same under every pattern (unlit, or lit by the backlight alone): its
        equations repeat one another and fix its albedo only. The test errs towards including
        pixels, which then only cost more search (``shadow_search.restarted_search``)."""
        num_patterns, count = self.captures.shape[0], self.captures.shape[2]
        # The common cases at once: too few captures, or more than three and none saturated.
        if num_patterns < 3 or (num_patterns > 3 and bool((self.equation_weight > 0).all())):
            return torch.zeros(count, dtype=torch.bool)
        emission = self.emission()
        scale = emission.abs().amax(dim=(0, 1)).clamp_min(torch.finfo(emission.dtype).tiny)  # (3,)
        repeated = ((emission - emission[:, :1]).abs().amax(dim=(0, 1)) <= GREY_TOLERANCE * scale)  # (3,) same under every pattern
        channels = torch.nonzero(~repeated).squeeze(1)
        if channels.numel() == 0:
            return torch.zeros(count, dtype=torch.bool)
        # Each pattern's emission over the superpixels, scaled to peak 1: the same in every
        # informative channel of a grey pattern.
        shape = emission[..., channels] / emission[..., channels].amax(dim=0, keepdim=True).clamp_min(torch.finfo(emission.dtype).tiny)
        if float((shape - shape[..., :1]).abs().amax()) > GREY_TOLERANCE:
            return torch.zeros(count, dtype=torch.bool)
        usable = self.equation_weight.sum(dim=0)[channels]  # (C, N) counts (weights are 0 or 1), with no (M, C, N) temporary
        three = usable == 3
        candidate = (usable <= 3).all(dim=0) & three.any(dim=0)
        if not bool(candidate.any()):  # e.g. an OLAT stack with a few saturated captures
            return candidate
        used = self.equation_weight[:, channels] > 0  # (M, C, N)
        patterns_of_three = (used & three[None]).any(dim=1)  # (M, N): used by some channel with three
        same = ((used == patterns_of_three[:, None]) | ~three[None]).all(dim=1).all(dim=0)
        return candidate & same

    def kink_condition(self, normal, exactly_determined, condition, kink_tolerance_deg: float) -> torch.Tensor:
        """Condition numbers (N,) with ``CONDITION_CAP`` at the ``exactly_determined`` pixels
        (``exactly_determined``, (N,) bool) whose normals (3, N) lie within ``kink_tolerance_deg``
        of the tangent plane of a superpixel that gives at least ``DOMINANT_SHARE`` of some
        pattern's unshadowed light there (per channel).

        With three grey patterns, the search stops on such a kink as on an answer: whether that
        superpixel is in front or behind changes the captures by nothing there, and an answer
        with it behind, often far away, fits as exactly (noise-free sphere, olat M = 3 on the
        backlit reference rig: every pixel the restarts left 11-44 deg off sat on the tangent
        plane of one pattern's lit superpixel, as did 3 of 45 correct ones).
        """
        index = torch.nonzero(exactly_determined).squeeze(1)
        if index.numel() == 0:
            return condition
        emission = self.emission().flatten(1)  # (K, 3 M)
        sine = math.sin(math.radians(kink_tolerance_deg))
        condition = condition.clone()
        for start, stop, rows in self.field.cache_rows(index):
            falloff, near = self.field.near_tangent(rows, normal[:, rows], sine)
            light = falloff[:, :, None] * emission[None]  # (n, K, 3 M): each superpixel's unshadowed light
            # The threshold is positive, so a dominant superpixel emits.
            dominant = (light >= DOMINANT_SHARE * light.sum(1, keepdim=True).clamp_min(torch.finfo(light.dtype).tiny)).any(2)
            kink = (near & dominant).any(1)
            condition[rows[kink]] = CONDITION_CAP
        return condition

    def lit_condition(self, normal, albedo, condition, kink_tolerance_deg: float, condition_of=normal_condition):
        """Condition numbers (N,) of the normals (3, N) and albedo (3, N) of all N pixels without
        the equations of patterns that leave superpixels dark where they sit at a kink: a zero
        capture (clipped, or below zero after dark-frame subtraction) whose lighting vector lies
        within ``kink_tolerance_deg`` (degrees) of the tangent plane, under a pattern and channel
        whose emission is exactly 0 on some superpixel.

        Such a capture is explained as well by the lit superpixels falling behind the tangent
        plane as by their lying on it: it bounds the normal from one side only. With exact zeros
        in the emission (off level 0 on a rig without backlight) that can hide a whole family of
        normals: a noise-free sphere under the four corners of ``olat`` M = 4 had pixels that two
        corners reach valid at condition 4 and up to 40 deg off; without those equations their
        condition is infinite and they are flagged. Where every superpixel emits (a backlit
        display) such equations still count: leaving them out there flagged good estimates of
        ordinary noisy scenes (tri_complementary M = 2 on the demo's test scenes: 62 more invalid
        pixels, with a median error of 5 deg before, and 0.27 deg more MAE). The result is never
        below ``condition`` (N,), that of every equation; pixels without such an equation keep it
        with no extra work. ``condition_of`` (normal, albedo, moment) -> condition numbers is the
        solver's own (Woodham's per-channel one, for instance).
        """
        emission = self.emission()
        sparse = (emission == 0).any(dim=0)  # (M, 3): some superpixel stays dark
        if not bool(sparse.any()):
            return condition
        zero = self.captures <= 0
        zero &= sparse[:, :, None]
        index = torch.nonzero(zero.any(dim=(0, 1))).squeeze(1)
        if index.numel() == 0:
            return condition
        kink_cos = math.sin(math.radians(kink_tolerance_deg))  # cosine of b and n at the kink tolerance
        condition, normals = condition.clone(), normal[:, index]
        for start, stop, vectors in self.field.vector_blocks(index, normals, self.lighting):
            pixels, pixel_normal = index[start:stop], normals[:, start:stop]
            facing = (vectors * pixel_normal[None, None]).sum(2)  # b . n: (M, 3, n)
            kink = take_pixels(zero, pixels) & (facing <= kink_cos * length(vectors, dim=2))
            weight = take_pixels(self.equation_weight, pixels) * ~kink
            moments = normalised_moments(vectors, take_pixels(self.captures, pixels), weight, self.capture_scale[pixels])
            condition[pixels] = torch.maximum(condition[pixels], condition_of(pixel_normal, albedo[:, pixels], moments.moment))
        return condition

GREY_TOLERANCE = 2e-3
"""Relative difference up to which two channels' emission counts as the same (float16 inputs
round to ~5e-4)."""
DOMINANT_SHARE = 0.1
"""Share of a pattern's light at a pixel from which one superpixel's shadow decides the fit of
an exactly determined pixel (``PatternEvaluator.kink_condition``)."""


NEAR_FIXED_POINT = 0.2
"""Relative size of the implicit Newton step (of the albedo) up to which a not-converged pixel
keeps the gradient of the nearby fixed point. Measured against central finite differences of the
returned, unconverged values (float64, four shapes, three families, M = 4 and 6): converged
pixels agree (median 0, 1% of them off by over 10%); not-converged ones differ by 12 to 17% in
the median, some by over 50%, at any step size, as the derivative of a truncated search is not
that of a fixed point; beyond steps of about 0.25 they are off several times, even in sign."""


def _solve_block(captures, lighting, points, lights, falloff, config: PSConfig, block_size: int) -> PSResult:
    """Solve N pixels: captures (M, N, 3), lighting matrix (K, 12 M), points (N, 3)."""
    track_gradient = torch.is_grad_enabled() and (captures.requires_grad or lighting.requires_grad)
    captures = captures.permute(0, 2, 1).contiguous()  # (M, 3, N): pixels last
    with torch.no_grad():
        light_field = LightField(points, lights, falloff, config.min_distance, block_size)
        equation_weight, capture_scale, dark, saturated = capture_flags(captures, config)
        evaluator = PatternEvaluator(light_field, lighting, captures, equation_weight, capture_scale, keep_vectors=track_gradient)

        def fit(albedo, moments):
            return alternate_kernel.alternate(albedo, moments, config.damping, config.tolerance_deg, config.max_alternations)

        initial_albedo = (captures.detach().amax(dim=0) / capture_scale).clamp_min(0)  # = max of I / scale: the scale is positive
        view = light_field.view.T.contiguous()
        exactly_determined = evaluator.exactly_determined()
        state, condition = restarted_search(evaluator, fit, initial_albedo, view, config, exactly_determined=exactly_determined)
        condition = evaluator.lit_condition(state.normal, state.albedo, condition, config.kink_tolerance_deg)
        condition = evaluator.kink_condition(state.normal, exactly_determined, condition, config.kink_tolerance_deg)

    normal, albedo = state.normal, state.albedo
    if track_gradient:
        vectors = differentiable_vectors(light_field, state.normal, lighting, state.moments.vectors)
        graph_moments = normalised_moments(vectors, captures, equation_weight, capture_scale)
        graph_albedo, graph_normal = implicit_step(albedo, graph_moments, config.damping)
        # Values stay the searched ones (identical with and without gradient tracking); only the
        # derivative comes from the Newton step: the fixed point's where the value is one, and
        # the nearby fixed point's where the search stopped short of it. A value far from any
        # (the step moves the albedo by more than NEAR_FIXED_POINT of its norm) gets none.
        with torch.no_grad():
            step = length(graph_albedo - albedo) / length(albedo).clamp_min(torch.finfo(albedo.dtype).tiny)
        differentiable = (state.converged | (step <= NEAR_FIXED_POINT)).to(albedo.dtype)
        albedo = albedo + (graph_albedo - graph_albedo.detach()) * differentiable
        normal = normal + (graph_normal - graph_normal.detach()) * differentiable
    albedo = albedo * (state.moments.capture_scale / state.moments.lighting_scale)
    flags = {"dark": dark, "saturated": saturated, "not_converged": ~state.converged}
    return finalise(normal.T, albedo.T, condition, relative_residual(state.normal, state.moments), flags, light_field, config)


def concatenate_results(results: list[PSResult], dtype) -> PSResult:
    """Concatenate per-pixel results along the pixel axis (an empty list gives 0 pixels)."""
    if not results:
        empty = torch.zeros((0, 3), dtype=dtype)
        none = torch.zeros(0, dtype=torch.bool)
        return PSResult(empty, empty.clone(), none, torch.zeros(0, dtype=dtype), torch.zeros(0, dtype=dtype), {name: none.clone() for name in FLAG_NAMES})
    if len(results) == 1:
        return results[0]
    return PSResult(
        normal=torch.cat([r.normal for r in results]),
        albedo=torch.cat([r.albedo for r in results]),
        valid=torch.cat([r.valid for r in results]),
        condition=torch.cat([r.condition for r in results]),
        residual=torch.cat([r.residual for r in results]),
        flags={name: torch.cat([r.flags[name] for r in results]) for name in FLAG_NAMES},
    )


MAX_CAPTURE = 8.0
"""Captures are in full-scale units (1 = the sensor's saturation; values above the saturation
threshold count as saturated, so unclipped ones are fine). Far beyond 1 they are in other units,
e.g. raw 8- or 12-bit counts, where every equation would silently count as saturated."""


def check_solver_inputs(captures, emission, points, lights, config, chunk_size, config_type, min_patterns: int = 1,
                        solver: str = "photometric stereo", full_scale: bool = True) -> None:
    """The input checks the solvers share (``solve_ps``, ``reconstruct.woodham.solve_woodham``):
    shapes (captures (M, N, 3), emission (M, K, 3) >= 0, points (N, 3), lights (K, 3)), finite
    values, floating-point tensors, matching sizes, at least ``min_patterns`` captures and one
    light, a ``config_type`` config and a positive whole ``chunk_size``; with ``full_scale``,
    captures at most ``MAX_CAPTURE``. Each failure is one ``InputError`` that names the sizes
    involved."""
    check_array("captures", captures, ("M", "N", 3))
    check_array("emission", emission, ("M", "K", 3), value_range=(0.0, math.inf))
    check_array("points", points, ("N", 3))
    check_array("lights", lights, ("K", 3))
    if not (isinstance(captures, torch.Tensor) and isinstance(emission, torch.Tensor)):
        raise InputError("captures and emission must be torch tensors")
    if not (captures.is_floating_point() and emission.is_floating_point()):
        raise InputError("captures and emission must be floating-point tensors")
    if captures.shape[0] < min_patterns:
        raise InputError(f"{solver} needs at least {min_patterns} capture{'s' if min_patterns > 1 else ''}, got {captures.shape[0]}")
    if lights.shape[0] < 1:
        raise InputError(f"{solver} needs at least one light, got K = 0")
    if captures.shape[0] != emission.shape[0]:
        raise InputError(f"captures have {captures.shape[0]} patterns but emission has {emission.shape[0]}")
    if emission.shape[1] != lights.shape[0]:
        raise InputError(f"emission drives {emission.shape[1]} superpixels but there are {lights.shape[0]} lights")
    if captures.shape[1] != points.shape[0]:
        raise InputError(f"captures have {captures.shape[1]} pixels but points has {points.shape[0]}")
    if not isinstance(config, config_type):
        raise InputError(f"config must be a {config_type.__name__}, got {type(config).__name__}")
    if not is_whole_number(chunk_size, 1):
        raise InputError(f"chunk_size must be a positive whole number, got {chunk_size!r}")
    if full_scale and captures.numel() and float(captures.detach().max()) > MAX_CAPTURE:
        raise InputError(f"captures reach {float(captures.detach().max()):g}, but are in full-scale units (1 = the sensor's "
                         "saturation): raw counts? divide them by the full-scale count (e.g. 4095 for 12 bits)")


def _check_inputs(captures, emission, points, lights, config, chunk_size):
    check_solver_inputs(captures, emission, points, lights, config, chunk_size, PSConfig)


def solve_pixels(solve_block, captures, emission, points, pixel_index, lights, config) -> PSResult:
    """Shared driver: run ``solve_block`` over the pixels ``pixel_index`` (or all) of flat inputs.

    Args:
        solve_block: (captures (M, n, 3), lighting (K, 12 M), points (n, 3), lights, config) -> PSResult.
        captures: (M, P, 3); points: (P, 3); pixel_index: (N,) long indices into P, or None for all.
        emission, lights, config: as ``solve_ps`` (its ``chunk_size`` reaches ``solve_block``).
    """
    # At least float32: float16 moments and condition numbers overflow.
    dtype = torch.promote_types(torch.promote_types(captures.dtype, emission.dtype), torch.float32)
    captures, emission = captures.to(dtype), emission.to(dtype)
    points = torch.as_tensor(points).detach().to(dtype)
    lights = torch.as_tensor(lights).detach().to(dtype)
    scale = emission_scale(emission)
    lighting = lighting_matrix(emission / scale, lights)
    config = working_config(config, dtype)
    count = points.shape[0] if pixel_index is None else pixel_index.numel()
    if count == 0:
        # No pixels: empty outputs that are still on the inputs' graph, as every other result is.
        on_graph = captures[0, :0] * 0 + lighting.sum() * 0  # (0, 3)
        empty = concatenate_results([], dtype)
        return dataclasses.replace(empty, normal=on_graph, albedo=on_graph.clone())
    results = []
    for start in range(0, count, MAX_PIXELS_PER_SOLVE):
        block = slice(start, start + MAX_PIXELS_PER_SOLVE) if pixel_index is None else pixel_index[start : start + MAX_PIXELS_PER_SOLVE]
        results.append(solve_block(captures[:, block], lighting, points[block], lights, config))
    return unscale_albedo(concatenate_results(results, dtype), scale)


def unscale_albedo(result: PSResult, scale: torch.Tensor) -> PSResult:
    """``result`` with its albedo in the units of the unscaled emission (see ``emission_scale``).

    An albedo beyond the dtype's range (an emission near its smallest normal number) is clamped to
    the largest finite value, so no inf leaves the solver."""
    return dataclasses.replace(result, albedo=finite_albedo(result.albedo / scale))


def solve_ps(captures, emission, points, lights, falloff, config: PSConfig = PSConfig(), chunk_size: int = 8192) -> PSResult:
    """Analytic multiplexed RGB photometric stereo of a set of pixels (see the module docstring).

    Args:
        captures: (M, N, 3) linear captures in [0, 1] (1 = saturation) of N pixels under M patterns.
        emission: (M, K, 3) effective emission E >= 0 (exposure included), such that noise-free
            unclipped captures are I[m, n, c] = sum_k E[m, k, c] O[k, n, c].
        points: (N, 3) surface points, metres, camera frame (from a depth map or a plane prior).
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor, e.g. ``capture_sim.rig.Falloff``.
        config: solver settings.
        chunk_size: pixels per block of (pixels x lights) work; bounds the temporaries (the
            unshadowed N x K weights are kept once). Results depend on it (and on the thread
            count) only through float rounding: in float32, up to a few hundredths of a degree on
            most pixels, but a pixel whose search stops near a shadow boundary (a superpixel near
            its tangent plane) can move by tenths of a degree and switch its not_converged flag
            (0.73 deg, valid, condition 1207, olat M = 4 noise-free, chunk_size 1 against 8192);
            on ill-conditioned or ambiguous ones (several shadow masks fit nearly as
            well) rounding can tip the search to another solution and change the pixel's
            validity. float64 makes such pixels stable.

    Returns:
        PSResult with (N, 3) normals and albedo, (N,) valid, condition, residual and flags. Differentiable
        w.r.t. ``captures`` and ``emission`` (exact implicit gradients of the converged solution;
        at pixels flagged not_converged, those of the nearby fixed point, an approximation, or
        zero where the value is far from one: ``NEAR_FIXED_POINT``);
        no gradient flows to points or lights. The albedo is in the emission's units, so its
        gradient grows as 1 / (emission peak)^2: past float32's range for peaks below about 1e-19
        (the normal's stays finite; use float64, down to peaks of about 1e-154, or emission in
        units near 1, to differentiate the albedo there).

    Raises:
        InputError: wrong shapes, non-finite inputs, negative emission (captures may be slightly
            negative, as real ones are after dark-frame subtraction), or a falloff that is not
            positive and finite over the light distances of pixels with valid geometry.

    Example:
        >>> from capture_sim.rig import load_rig
        >>> rig = load_rig()
        >>> result = solve_ps(captures, emission, points, rig.lights(), rig.falloff)  # doctest: +SKIP
        >>> result.normal[result.valid]  # doctest: +SKIP
    """
    _check_inputs(captures, emission, points, lights, config, chunk_size)

    def solve_block(block_captures, lighting, block_points, block_lights, block_config):
        return _solve_block(block_captures, lighting, block_points, block_lights, falloff, block_config, chunk_size)

    return solve_pixels(solve_block, captures, emission, points, None, lights, config)


def check_image_inputs(captures, points, mask):
    """Check the shapes of image-shaped solver inputs: captures (M, H, W, 3), points (H, W, 3),
    mask (H, W) bool (values are checked on the masked pixels only, by ``check_masked_inputs``)."""
    check_array("captures", captures, ("M", "H", "W", 3), finite=False)
    check_array("points", points, (captures.shape[1], captures.shape[2], 3), finite=False)
    check_array("mask", mask, (captures.shape[1], captures.shape[2]))
    if torch.as_tensor(mask).dtype != torch.bool:
        raise InputError("mask must be a bool array")


def scatter_result(result: PSResult, pixel_index: torch.Tensor, height: int, width: int) -> PSResult:
    """Scatter a PSResult of the pixels ``pixel_index`` (flat indices into H * W) into images.

    Pixels not listed get normal (0, 0, -1), albedo 0, valid False, condition CONDITION_CAP,
    residual 1 and all flags False. Differentiable in the normals and albedo.
    """
    size = height * width

    def scatter(values, fill):
        image = torch.full((size, *values.shape[1:]), fill, dtype=values.dtype)
        return image.index_put((pixel_index,), values).reshape(height, width, *values.shape[1:])

    default_normal = torch.tensor([0.0, 0.0, -1.0], dtype=result.normal.dtype).expand(size, 3)
    return PSResult(
        normal=default_normal.index_put((pixel_index,), result.normal).reshape(height, width, 3),
        albedo=scatter(result.albedo, 0.0),
        valid=scatter(result.valid, False),
        condition=scatter(result.condition, CONDITION_CAP),
        residual=scatter(result.residual, 1.0),
        flags={name: scatter(value, False) for name, value in result.flags.items()},
    )


CHECK_PIXELS = 1 << 14
"""Masked pixels per block of ``check_masked_inputs`` (28 MB of a 144-light float32 OLAT stack)."""


def check_masked_inputs(check, flat_captures, emission, flat_points, pixel_index, lights, config, chunk_size) -> None:
    """Run a solver's input ``check`` on the masked pixels only: values outside the mask (e.g. NaN
    depth in the background of a real capture) are never read. The check runs block by block, so
    the masked captures are never copied whole (a full-frame OLAT stack is hundreds of MB)."""
    if not isinstance(flat_captures, torch.Tensor):
        check(flat_captures, emission, torch.as_tensor(flat_points)[pixel_index], lights, config, chunk_size)
        return
    for block in pixel_index.split(CHECK_PIXELS):  # one empty block when no pixel is masked
        check(flat_captures[:, block], emission, torch.as_tensor(flat_points)[block], lights, config, chunk_size)


def image_pixels(captures, points, mask):
    """Flat views of image inputs: captures (M, H*W, 3), points (H*W, 3) and the (N,) mask indices."""
    num_patterns, height, width, _ = captures.shape
    flat_captures = captures.reshape(num_patterns, height * width, 3)
    flat_points = torch.as_tensor(points).reshape(height * width, 3)
    pixel_index = torch.nonzero(torch.as_tensor(mask).reshape(-1)).squeeze(1)
    return flat_captures, flat_points, pixel_index


def solve_ps_image(
    captures, emission, points, mask, lights, falloff, config: PSConfig = PSConfig(), chunk_size: int = 8192
) -> PSResult:
    """``solve_ps`` on images: solves the pixels inside ``mask``.

    Args:
        captures: (M, H, W, 3) linear captures in [0, 1].
        emission: (M, K, 3) effective emission E >= 0 (exposure included).
        points: (H, W, 3) surface points, metres, camera frame.
        mask: (H, W) bool, pixels to solve.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: callable distance (metres) -> falloff factor.
        config: solver settings.
        chunk_size: pixels per block of (pixels x lights) work.

    Returns:
        PSResult with (H, W, 3) normals and albedo and (H, W) valid, condition, residual and flags; pixels
        outside the mask are invalid with normal (0, 0, -1) and albedo 0. Differentiable w.r.t.
        ``captures`` and ``emission``.
    """
    check_image_inputs(captures, points, mask)
    flat_captures, flat_points, pixel_index = image_pixels(captures, points, mask)
    check_masked_inputs(_check_inputs, flat_captures, emission, flat_points, pixel_index, lights, config, chunk_size)

    def solve_block(block_captures, lighting, block_points, block_lights, block_config):
        return _solve_block(block_captures, lighting, block_points, block_lights, falloff, block_config, chunk_size)

    result = solve_pixels(solve_block, flat_captures, emission, flat_points, pixel_index, lights, config)
    return scatter_result(result, pixel_index, captures.shape[1], captures.shape[2])
