"""Accuracy metrics (DESIGN section 5): normal angular error and relighting PSNR / SSIM.

Normal error: the angle between estimated and true normals, computed as atan2(|a x b|, a . b):
finite everywhere and accurate for tiny angles, where the arccosine of a rounded cosine is not
(in float32, acos(dot) cannot resolve angles below about 0.02 degrees); it equals the clamped
arccosine of the normalised dot product otherwise.

Relighting (linear images in [0, 1], peak value 1), inside a mask:
- PSNR = 10 log10(1 / MSE) with the MSE over the masked pixels and the three channels of all
  images (pooled), computed by ``kornia.metrics.psnr`` on the masked pixels. Identical images have
  infinite PSNR; it is reported as PSNR_CAP_DB (100 dB) so results stay finite.
- SSIM: ``kornia.metrics.ssim`` maps of the images with everything outside the mask set to zero
  in both, averaged over the masked pixels and channels of all images.
"""
from __future__ import annotations

import kornia
import torch

from capture_sim.errors import InputError, all_finite, check_array, is_whole_number

PSNR_CAP_DB = 100.0
"""PSNR of identical images is infinite; it is reported as this cap so results stay finite."""


def angular_error_deg(estimate: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Angle between normals in degrees.

    Args:
        estimate: (..., 3) normals (normalised here), tensor or numpy array.
        truth: (..., 3) normals, same shape.

    Returns:
        (...) angles in [0, 180] degrees in the dtype of ``estimate`` (float32 for integer input),
        always finite (a zero vector gives 90 degrees). Differentiable with finite gradients, except
        that the gradient (about 1 / length) of vectors shorter than about 1 / the dtype's largest
        number exceeds the dtype's range: below about 1e-3 in float16, subnormal vectors in float32
        and float64.

    Example:
        >>> angular_error_deg(torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.0, 1.0, -1.0]]))
        tensor([45.])
    """
    check_array("estimate", estimate, ("...", 3))
    check_array("truth", truth, tuple(estimate.shape))
    estimate, truth = torch.as_tensor(estimate), torch.as_tensor(truth)
    out_dtype = estimate.dtype if estimate.is_floating_point() else torch.float32
    first, second = estimate.double(), truth.double()
    # The angle ignores length: bring both to components of at most 1 so no square over- or
    # underflows (vectors of norm 1e200 gave NaN gradients).
    first = first / first.detach().abs().amax(-1, keepdim=True).clamp_min(torch.finfo(torch.float64).tiny)
    second = second / second.detach().abs().amax(-1, keepdim=True).clamp_min(torch.finfo(torch.float64).tiny)
    # The tiny offset keeps the gradient finite where the vectors are parallel.
    sine = torch.sqrt(torch.linalg.cross(first, second).square().sum(-1) + 1e-300)
    cosine = (first * second).sum(-1)
    degenerate = (first.abs().amax(-1) == 0) | (second.abs().amax(-1) == 0)
    angle = torch.rad2deg(torch.atan2(sine, torch.where(degenerate, torch.ones_like(cosine), cosine)))
    return torch.where(degenerate, torch.full_like(angle, 90.0), angle).to(out_dtype)


def normal_metrics(estimate: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> dict:
    """Normal-error summary over a mask.

    Args:
        estimate: (..., 3) estimated normals, camera frame.
        truth: (..., 3) true normals.
        mask: (...) bool, pixels to count (the others may hold anything, NaN included).

    Returns:
        dict: mae and median (degrees; the mean of the two middle errors for an even count),
        under_5, under_10, under_20, under_30 (fractions of the masked pixels with an error below
        that many degrees, in [0, 1]) and count (pixels); an empty mask gives zeros and count 0.
    """
    check_array("estimate", estimate, ("...", 3), finite=False)
    check_array("truth", truth, tuple(estimate.shape), finite=False)
    estimate, truth, mask = torch.as_tensor(estimate), torch.as_tensor(truth), torch.as_tensor(mask)
    check_array("mask", mask, tuple(estimate.shape[:-1]))
    if mask.dtype != torch.bool:
        raise InputError("mask must be a bool array")
    # Only masked pixels must be finite: methods may leave NaN in the background.
    errors = angular_error_deg(estimate.detach()[mask], truth.detach()[mask]).double()
    if errors.numel() == 0:
        return {"mae": 0.0, "median": 0.0, "under_5": 0.0, "under_10": 0.0, "under_20": 0.0, "under_30": 0.0, "count": 0}
    # torch.median returns the lower of the two middle values: average both (one for an odd count).
    middle = errors.sort().values[(errors.numel() - 1) // 2 : errors.numel() // 2 + 1]
    summary = {"mae": float(errors.mean()), "median": float(middle.mean())}
    for limit in (5, 10, 20, 30):
        summary[f"under_{limit}"] = float((errors < limit).double().mean())
    summary["count"] = int(errors.numel())
    return summary


def _check_images(prediction, truth, mask) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The inputs of ``psnr`` and ``ssim`` as tensors, checked."""
    check_array("prediction", prediction, ("...", "H", "W", 3), finite=False)
    check_array("truth", truth, tuple(prediction.shape), finite=False)
    prediction, truth, mask = torch.as_tensor(prediction), torch.as_tensor(truth), torch.as_tensor(mask)
    check_array("mask", mask, tuple(prediction.shape[-3:-1]))
    if mask.dtype != torch.bool:
        raise InputError("mask must be a bool array")
    if not bool(mask.any()):
        raise InputError("mask selects no pixels")
    if prediction.numel() == 0:
        raise InputError(f"no images to compare: prediction has shape {tuple(prediction.shape)}")
    # As in ``normal_metrics``, only masked pixels must be finite: the background may hold anything.
    for name, images in (("prediction", prediction), ("truth", truth)):
        masked = images.detach()[..., mask, :]
        if not all_finite(masked):
            raise InputError(f"{name}: NaN or infinite values inside the mask")
        largest = float(masked.abs().max())
        if largest > MAX_IMAGE_VALUE:
            raise InputError(f"{name}: values up to {largest:g}, not images in full-scale units (1 = saturation); their squared errors would overflow")
    return prediction, truth, mask


MAX_IMAGE_VALUE = 1e100
"""Largest magnitude ``psnr`` and ``ssim`` accept: squares and products of larger values overflow
float64 (a PSNR of -inf, an SSIM of NaN)."""


def psnr(prediction: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR in dB over the masked pixels of linear images (peak value 1).

    Args:
        prediction: (..., H, W, 3) images, full scale 1. Values are compared as given, not
            clipped: ``reconstruct.relight.relighting_metrics`` clips both images to [0, 1] first,
            as a sensor does, and gives another number for images that leave that range.
        truth: (..., H, W, 3) reference images.
        mask: (H, W) bool, pixels to compare (must select at least one; the others may hold
            anything, NaN included).

    Returns:
        10 log10(1 / MSE), MSE pooled over the masked pixels, channels and images; capped at
        PSNR_CAP_DB.
    """
    prediction, truth, mask = _check_images(prediction, truth, mask)
    # PSNR only needs the masked values; kornia reduces them whatever their layout.
    predicted, reference = prediction.detach().double()[..., mask, :], truth.detach().double()[..., mask, :]
    value = float(kornia.metrics.psnr(predicted, reference, max_val=1.0))
    return min(value, PSNR_CAP_DB)


def ssim(prediction: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor, window_size: int = 11) -> float:
    """Mean SSIM over the masked pixels of linear images (peak value 1).

    Args:
        prediction: (..., H, W, 3) images, full scale 1, compared as given (see ``psnr``).
        truth: (..., H, W, 3) reference images.
        mask: (H, W) bool, pixels to average over (must select at least one; the others may
            hold anything, NaN included).
        window_size: odd Gaussian window of the SSIM, shrunk to fit small images.

    Returns:
        SSIM averaged over masked pixels, channels and images, in [-1, 1].
    """
    prediction, truth, mask = _check_images(prediction, truth, mask)
    if not is_whole_number(window_size, 1) or window_size % 2 == 0:
        raise InputError(f"window_size must be a positive odd whole number, got {window_size!r}")
    height, width = mask.shape
    window = min(int(window_size), 2 * ((min(height, width) - 1) // 2) + 1)

    def to_kornia(images):  # channels-last (..., H, W, 3) -> (B, 3, H, W), zero outside the mask (NaN there too)
        images = images.detach().double()
        return torch.where(mask[..., None], images, images.new_zeros(())).reshape(-1, height, width, 3).permute(0, 3, 1, 2)

    similarity = kornia.metrics.ssim(to_kornia(prediction), to_kornia(truth), window_size=window, max_val=1.0)
    return float(similarity.permute(0, 2, 3, 1)[:, mask].mean())
