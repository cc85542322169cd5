"""Differentiable capture simulator (DESIGN section 3).

    I_m(x) = q( clip( e * sum_k L[m, k] * O[k](x) + noise ) )

The sum over lights is one batched matrix product per colour channel over a *channel-major* light
transport matrix T of shape (3, K, N) (N pixels): (3, M, K) @ (3, K, N). This layout makes the
contraction a plain GEMM; a channels-last (K, H, W, 3) stack would need a strided einsum several
times slower, and broadcasting lights would materialise (M, K, N, 3).

Gradient surrogates (so that learning feels the sensor):
- noise is reparameterised: x + sqrt(a * x + sigma_read^2) * z with z ~ N(0, 1) drawn from a seeded
  generator, so gradients flow through both the signal and the noise level;
- clipping to [0, 1] is exact in the forward pass; its backward pass is the exact slope 1 inside
  [0, 1] and a decaying tail exp(-beta * excess) outside, where excess is the distance beyond the
  range, so saturated or black pixels still tell the patterns which way leaves saturation
  (beta = ``CLIP_SHARPNESS``) instead of going silent as a true clip would;
- quantisation is straight-through: exact rounding forward, identity backward.

Exposure: a fixed number, or "auto": the largest e that puts the 99.9th percentile of the
noise-free captures at 0.9 of full scale, computed without gradient (during learning it is
recomputed every step and treated as a constant).
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import torch

from capture_sim.display import display_emission
from capture_sim.errors import InputError, all_finite, check_array
from capture_sim.rig import MAX_BIT_DEPTH, NoiseModel, Rig

AUTO_EXPOSURE_PERCENTILE = 99.9
AUTO_EXPOSURE_TARGET = 0.9


@dataclass(frozen=True, eq=False)
class LightTransport:
    """An OLAT stack in the simulator's channel-major layout, restricted to a set of pixels.

    Attributes:
        matrix: (3, K, N) float tensor, T[c, k, n] = O[k](pixel n)[c].
        pixel_index: (N,) long indices of the pixels into the flattened H * W image.
        height, width: image size the indices refer to.
    """

    matrix: torch.Tensor
    pixel_index: torch.Tensor
    height: int
    width: int

    @property
    def num_lights(self) -> int:
        return self.matrix.shape[1]

    @property
    def num_pixels(self) -> int:
        return self.matrix.shape[2]

    def subset(self, columns: torch.Tensor | slice) -> "LightTransport":
        """The transport of the pixels at positions ``columns`` (indices into 0..N-1, a copy; or a
        slice, a view)."""
        return LightTransport(self.matrix[:, :, columns], self.pixel_index[columns], self.height, self.width)

    def to_image(self, values: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """Scatter per-pixel values (..., N, D) into images (..., H, W, D); other pixels get ``fill``."""
        lead, depth = values.shape[:-2], values.shape[-1]
        image = values.new_full((*lead, self.height * self.width, depth), fill)
        image[..., self.pixel_index, :] = values
        return image.reshape(*lead, self.height, self.width, depth)


def light_transport(olat, mask=None, dtype=torch.float32) -> LightTransport:
    """Convert an OLAT stack to the channel-major transport of the pixels inside ``mask``.

    Copies one light at a time so that peak memory stays near the source plus the result.

    Args:
        olat: (K, H, W, 3) numpy array or tensor, radiance per unit display intensity.
        mask: optional (H, W) bool; None keeps every pixel.
        dtype: floating dtype of the result.

    Returns:
        LightTransport with a (3, K, N) matrix, N = number of selected pixels.

    Raises:
        InputError: wrong shapes, a dtype that is not floating, NaN, infinite or negative values.
    """
    check_array("olat", olat, ("K", "H", "W", 3), finite=False)
    if not dtype.is_floating_point:
        raise InputError(f"light_transport: dtype must be a floating-point dtype, got {dtype}")
    num_lights, height, width, _ = olat.shape
    source = torch.as_tensor(olat)
    if mask is None:
        index = torch.arange(height * width)
    else:
        mask_t = torch.as_tensor(mask)
        check_array("mask", mask_t, (height, width))
        index = torch.nonzero(mask_t.reshape(-1), as_tuple=False).squeeze(1)
    matrix = torch.empty((3, num_lights, index.numel()), dtype=dtype)
    lowest, finite = 0.0, True
    for k in range(num_lights):
        # Gathering rows first then transposing is ~2x faster than a strided transpose-copy.
        rows = source[k].reshape(-1, 3)[index]
        matrix[:, k, :] = rows.T
        # Per light, not over the whole matrix: after one 540 MB reduction the solver's full-frame
        # benchmark ran 25% slower in half of the runs (measured, cause unknown), and isfinite
        # over it took 0.9 GB of temporaries. NaN and infinities reach the minimum or maximum.
        if rows.numel():
            low, high = torch.aminmax(rows.detach())
            low, high = float(low), float(high)
            finite = finite and math.isfinite(low) and math.isfinite(high)
            lowest = min(lowest, low)
    if not finite:
        raise InputError("olat: contains NaN or infinite values")
    if lowest < 0:
        raise InputError(f"olat: has negative radiance (min {lowest:g}); radiance per unit display intensity is >= 0")
    return LightTransport(matrix, index, height, width)


def noise_free_radiance(emission: torch.Tensor, transport: LightTransport) -> torch.Tensor:
    """Contract emitted intensities with the light transport (no exposure, noise or clipping).

    Args:
        emission: (M, K, 3) emitted intensity per pattern, superpixel and channel.
        transport: light transport with a (3, K, N) matrix.

    Returns:
        (M, N, 3) sum_k emission[m, k, c] * O[k](n)[c].
    """
    if emission.shape[1] != transport.num_lights:
        raise InputError(f"patterns drive {emission.shape[1]} superpixels but the OLAT stack has {transport.num_lights} lights")
    per_channel = torch.matmul(emission.permute(2, 0, 1), transport.matrix.to(emission.dtype))  # (3, M, N)
    return per_channel.permute(1, 2, 0)


def auto_exposure(radiance: torch.Tensor, percentile: float = AUTO_EXPOSURE_PERCENTILE, target: float = AUTO_EXPOSURE_TARGET) -> float:
    """Exposure e putting the ``percentile`` of noise-free captures at ``target`` of full scale.

    Args:
        radiance: (M, N, 3) noise-free radiance (any layout; all values are pooled).

    Returns:
        e > 0 as a Python float (1.0 when the percentile is 0: a dark scene, so nothing divides by
        zero).

    Raises:
        InputError: the radiance contains NaN (it would be ordered as the brightest value), or its
            percentile is infinite or a subnormal number (a scene scaled past the dtype's range,
            whose exposure would be 0 or overflow).
    """
    return auto_exposure_at(radiance, percentile, target)[0]


LARGE_SELECTION = 1 << 24
"""Values from which ``auto_exposure_at`` narrows its selection to candidates first."""


def _top_candidates(values: torch.Tensor, count: int) -> torch.Tensor | None:
    """Indices of the values (n,) at or above a threshold that leaves at least the ``count``
    largest among them (exactly: the count-th largest is then above the threshold), for inputs
    of at least ``LARGE_SELECTION`` values; None for smaller ones or when the guess fails. On a
    full-resolution OLAT stack (135 M values) topk over everything took 5.4 s and 2 GB."""
    if values.numel() < LARGE_SELECTION or count > values.numel() // 8:
        return None
    sample = values[torch.randint(values.numel(), (1 << 16,), generator=torch.Generator().manual_seed(0))]
    # Twice the wanted share above the threshold, plus a margin for the sample's spread.
    share = min(1.0, 2.0 * count / values.numel() + 4.0 / 256)
    threshold = torch.quantile(sample.float(), 1.0 - share)
    candidates = torch.nonzero(values >= threshold.to(values.dtype)).squeeze(1)
    return candidates if candidates.numel() >= count else None


def auto_exposure_at(radiance: torch.Tensor, percentile: float = AUTO_EXPOSURE_PERCENTILE,
                     target: float = AUTO_EXPOSURE_TARGET) -> tuple[float, int | None]:
    """``auto_exposure``, and the flat index into ``radiance`` of the value at the percentile that
    set it (None for a dark or empty scene, whose exposure is the fixed 1.0): e = target / that
    value, a function of one noise-free capture (``train.capture.exposure_with_gradient``)."""
    # The rank statistic is exact in the input's own dtype (converting to float64 would only copy).
    if not (0 < percentile <= 100 and 0 < target < math.inf):
        raise InputError(f"auto exposure needs a percentile in (0, 100] and a positive target, got {percentile!r}, {target!r}")
    values = torch.as_tensor(radiance).detach().reshape(-1)
    if not values.is_floating_point():
        values = values.to(torch.float32)
    if values.numel() == 0:
        return 1.0, None  # no pixels: nothing to expose for
    if math.isnan(float(values.sum())):  # any NaN makes the sum NaN; ~5x cheaper than isnan().any()
        raise InputError("auto exposure: the noise-free radiance contains NaN")
    # Nearest rank ceil(p n / 100) in exact arithmetic: in floats 99.9 / 100 * 1000 is 999.0000000000001,
    # and the ceiling would take the next rank (the maximum), which one bright pixel then decides.
    rank = min(values.numel(), max(1, math.ceil(Fraction(str(percentile)) * values.numel() / 100)))
    # The rank-th smallest is the smallest of the top numel - rank + 1: topk finds those few
    # values ~3x faster than kthvalue's full selection (a learning step asks every time).
    candidates = _top_candidates(values, values.numel() - rank + 1)
    pool = values if candidates is None else values[candidates]
    top = torch.topk(pool, values.numel() - rank + 1, sorted=False)
    smallest = top.values.kthvalue(1)
    index = top.indices[smallest.indices]
    level, index = float(smallest.values), int(index if candidates is None else candidates[index])
    # Any positive normal number works: radiance may come in any units (an OLAT stack scaled by
    # 1e-20 is still a scene); below the dtype's smallest normal the gain would overflow it.
    if level == 0:
        return 1.0, None
    if level < 0:
        raise InputError(f"auto exposure: the radiance's {percentile:g}th percentile {level:g} is negative; radiance is >= 0")
    if not torch.finfo(values.dtype).tiny <= level < math.inf:
        raise InputError(f"auto exposure: the radiance's {percentile:g}th percentile {level:g} is outside the range of "
                         f"{values.dtype} (the scene's OLAT values are scaled too far); rescale the scene")
    return target / level, index


def check_exposure_range(exposure: float, *exposed: torch.Tensor) -> None:
    """Raise ``InputError`` if an exposure pushed any of the ``exposed`` tensors (exposed
    radiance or emission, any shape) past their dtype's range (there the radiance is inf, and
    inf * 0, an unlit pixel, NaN: the solver would report NaN captures), or is 0 in their dtype
    (every capture black: the solvers would report no emitted light)."""
    if not all(all_finite(values) for values in exposed):
        raise InputError(f"exposure {exposure:g} is too large: the exposed radiance overflows {exposed[0].dtype}; use a smaller value or 'auto'")
    if float(torch.tensor(exposure, dtype=exposed[0].dtype)) == 0:  # every capture would be black
        raise InputError(f"exposure {exposure:g} is too small: it is 0 in {exposed[0].dtype}; use a larger value or 'auto'")


CLIP_SHARPNESS = 50.0
"""beta of the clipping's gradient tail exp(-beta * excess), per unit of full scale (module docstring)."""


class _SaturatingClip(torch.autograd.Function):
    """Exact clip to [0, 1] forward; slope 1 inside and a decaying tail outside backward."""

    @staticmethod
    def forward(ctx, signal, sharpness):
        ctx.save_for_backward(signal)
        ctx.sharpness = sharpness
        return signal.clamp(0.0, 1.0)

    @staticmethod
    def backward(ctx, grad_output):
        (signal,) = ctx.saved_tensors
        beta = ctx.sharpness
        excess = (signal - 1.0).clamp_min(0.0) + (-signal).clamp_min(0.0)
        slope = torch.exp(-beta * excess)
        return grad_output * slope, None


def _rounded(signal: torch.Tensor, levels: float) -> torch.Tensor:
    """``signal`` rounded to multiples of 1 / ``levels``, in its dtype."""
    # In at least float32: 2^16 - 1 levels and more overflow float16 (max 65504).
    work = signal.to(torch.promote_types(signal.dtype, torch.float32))
    return (torch.round(work * levels) / levels).to(signal.dtype)


class _StraightThroughRound(torch.autograd.Function):
    @staticmethod
    def forward(ctx, signal, levels):
        return _rounded(signal, levels)

    @staticmethod
    def backward(ctx, grad_output):
        return grad_output, None


def sensor(
    signal: torch.Tensor,
    noise: NoiseModel | None,
    bit_depth: int | None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Apply sensor noise, saturation and quantisation to exposed noise-free signal.

    Args:
        signal: (...) exposed signal e * sum_k L O, full scale = 1.
        noise: Poisson-Gaussian model, or None for a noise-free sensor.
        bit_depth: quantisation bits, or None for none.
        generator: torch random generator for the noise (seeded for reproducibility); None draws
            from torch's global generator (``torch.manual_seed``).

    Returns:
        (...) captures in [0, 1], same shape (and memory layout) as ``signal``, in its dtype or
        float32 if narrower. Without gradient, large signals run in blocks of ``SENSOR_BLOCK``
        values along the leading axis, with the same values.

    Raises:
        InputError: a bit depth outside 1..16 (``rig.MAX_BIT_DEPTH``), or a generator that is not a ``torch.Generator``.
        Values are not scanned (a hot path of learning; ``simulate`` checks its inputs).
    """
    if bit_depth is not None and not (isinstance(bit_depth, numbers.Integral) and not isinstance(bit_depth, bool) and 1 <= bit_depth <= MAX_BIT_DEPTH):
        raise InputError(f"bit_depth must be None or a whole number in 1..{MAX_BIT_DEPTH}, got {bit_depth!r}")
    if generator is not None and not isinstance(generator, torch.Generator):
        raise InputError(f"generator must be a torch.Generator (e.g. torch.Generator().manual_seed(0)) or None, got {generator!r}")
    # At least float32: float16's smallest normal (6e-5) is a variance floor far above the read
    # noise's, and its spacing near 1 is coarser than 12-bit quantisation.
    dtype = torch.promote_types(signal.dtype, torch.float32)
    levels = None if bit_depth is None else float(2 ** int(bit_depth) - 1)
    if not (torch.is_grad_enabled() and signal.requires_grad) and signal.dim() > 0 and signal.numel() > SENSOR_BLOCK:
        return _sensor_in_blocks(signal, dtype, noise, levels, generator)
    signal = signal.to(dtype)
    if noise is not None:
        signal = _with_noise(signal, noise, generator)
    captured = _SaturatingClip.apply(signal, CLIP_SHARPNESS)
    if levels is not None:
        captured = _StraightThroughRound.apply(captured, levels)
    return captured


SENSOR_BLOCK = 1 << 22
"""Values per block of ``sensor`` without gradient (16 MB in float32): a full-resolution OLAT
capture (144 x 313 344 x 3 values) then needs its output and a few blocks, not six full-size
temporaries (+3 GB)."""


def _with_noise(signal: torch.Tensor, noise: NoiseModel, generator: torch.Generator | None) -> torch.Tensor:
    """signal + sqrt(a signal + sigma_read^2) z, z drawn for ``signal``'s values in order."""
    # The floor keeps the square root's gradient finite where the variance is zero (no read
    # noise at zero signal, or a noise model scaled to 0).
    std = torch.sqrt(noise.shot * signal.clamp_min(0.0) + noise.read_std**2 + torch.finfo(signal.dtype).tiny)
    return signal + std * _standard_normal(signal.numel(), generator, signal.dtype).view(signal.shape)


def _standard_normal(count: int, generator: torch.Generator | None, dtype: torch.dtype) -> torch.Tensor:
    # Drawn in float32 whatever the working dtype: torch.randn gives one seed different numbers
    # in float32 and float64, and the same seed must give the same noise at either precision.
    return torch.randn(count, generator=generator, dtype=torch.float32).to(dtype)


def _draw_blocks(count: int, per_row: int) -> list[tuple[int, int]]:
    """(start, stop) blocks of ``count`` rows of ``per_row`` values, about ``SENSOR_BLOCK`` values
    each: a multiple of 16 values, but for the last, which holds 16 values or more (a shorter
    tail joins the block before it)."""
    unit = 16 // math.gcd(16, per_row)  # rows per whole number of groups of 16 values
    rows = max(unit, SENSOR_BLOCK // per_row // unit * unit)
    blocks = [[start, min(start + rows, count)] for start in range(0, count, rows)]
    if len(blocks) > 1 and (blocks[-1][1] - blocks[-1][0]) * per_row < 16:
        tail = blocks.pop()
        blocks[-1][1] = tail[1]
    return [tuple(block) for block in blocks]


def _sensor_in_blocks(signal, dtype, noise, levels, generator) -> torch.Tensor:
    """``sensor`` without gradient, block by block along the leading axis (of the flattened signal
    when it is contiguous): the same operations in the same order on every value, and the noise
    drawn block by block from the one generator, in the order of one whole draw, with only a few
    blocks of temporaries. torch's CPU normal sampler transforms its uniform draws in groups of 16,
    so blocks of whole groups (``_draw_blocks``) continue one draw exactly (tests/test_simulator.py
    checks the values against the whole draw's)."""
    rows = signal.reshape(-1) if signal.is_contiguous() else signal
    out = torch.empty_like(rows, dtype=dtype)  # the input's memory layout: no transposing copy
    for start, stop in _draw_blocks(rows.shape[0], rows[0].numel()):
        block = rows[start:stop].to(dtype, copy=True)
        if noise is not None:
            block = _with_noise(block, noise, generator)
        block.clamp_(0.0, 1.0)
        if levels is not None:
            block = _rounded(block, levels)
        out[start:stop] = block
    return out.view(signal.shape)


@dataclass(frozen=True, eq=False)
class Capture:
    """Result of a simulated capture.

    Attributes:
        captures: (M, N, 3) simulated images of the transport's pixels, in [0, 1].
        emission: (M, K, 3) effective emission e * L, so that noise-free I = sum_k emission O.
        exposure: the exposure e used.
    """

    captures: torch.Tensor
    emission: torch.Tensor
    exposure: float


def simulate(
    patterns: torch.Tensor,
    transport: LightTransport,
    rig: Rig,
    exposure: float | str | None = None,
    noise: NoiseModel | None | str = "rig",
    bit_depth: int | None | str = "rig",
    generator: torch.Generator | None = None,
) -> Capture:
    """Simulate the captures of a pattern set (DESIGN section 3), differentiably in ``patterns``.

    Args:
        patterns: (M, R, C, 3) set values in [0, 1] for the rig's R x C grid.
        transport: light transport of the scene's pixels, K = R * C lights.
        rig: display model (backlight, gamma, scale) and sensor defaults.
        exposure: a number, "auto", None for the rig's setting (a number or auto), or a scalar
            tensor, whose gradient then reaches the captures and the emission.
        noise: a NoiseModel, None for no noise (quantisation is ``bit_depth``'s: the command line's
            ``--noise off`` passes None for both), or "rig" for the rig's model.
        bit_depth: bits, None for no quantisation, or "rig" for the rig's setting.
        generator: torch random generator for the noise; None draws from torch's global one.

    Returns:
        Capture with (M, N, 3) captures, (M, K, 3) effective emission and the exposure used, in the
        patterns' dtype or float32, whichever is wider.
    """
    check_array("patterns", patterns, ("M", rig.rows, rig.cols, 3), value_range=(0.0, 1.0))
    patterns = torch.as_tensor(patterns)
    if patterns.shape[0] == 0:
        raise InputError("patterns: need at least one pattern (M >= 1)")
    if not (noise is None or noise == "rig" or isinstance(noise, NoiseModel)):
        raise InputError(f"noise must be a NoiseModel, None or 'rig', got {noise!r}")
    rig.check_lights(transport.num_lights)
    # At least float32: float16 radiance underflows (auto exposure would see a black scene) and its
    # 2^16 quantisation levels overflow.
    patterns = patterns.to(torch.promote_types(patterns.dtype, torch.float32))
    emitted = display_emission(patterns, rig.backlight_flat(patterns.dtype), rig.gamma, rig.scale)
    radiance = noise_free_radiance(emitted, transport)
    if exposure is None:
        exposure = rig.exposure if rig.exposure is not None else "auto"
    gain = None
    if isinstance(exposure, torch.Tensor):  # a scalar that carries its gradient (train.capture.exposure_with_gradient)
        if exposure.dim() != 0 or not exposure.is_floating_point():
            raise InputError(f"exposure: a tensor exposure must be a floating-point scalar, got shape {tuple(exposure.shape)} {exposure.dtype}")
        gain, exposure = exposure, float(exposure.detach())
    elif exposure != "auto":
        if isinstance(exposure, bool):  # float(True) is 1.0: a flag passed where a number belongs
            raise InputError(f"exposure must be a positive number or 'auto', got {exposure!r}")
        try:
            exposure = float(exposure)
        except (TypeError, ValueError):
            raise InputError(f"exposure must be a positive number or 'auto', got {exposure!r}") from None
    exposure = auto_exposure(radiance) if exposure == "auto" else exposure
    if not exposure > 0 or not np.isfinite(exposure):
        raise InputError(f"exposure must be a positive number or 'auto', got {exposure}")
    gain = exposure if gain is None else gain.to(emitted.dtype)
    emission, exposed = gain * emitted, gain * radiance
    check_exposure_range(exposure, emission, exposed)
    noise_model = rig.noise if noise == "rig" else noise
    bits = rig.bit_depth if bit_depth == "rig" else bit_depth
    captures = sensor(exposed, noise_model, bits, generator)
    return Capture(captures=captures, emission=emission, exposure=exposure)
