"""Accuracy metrics (DESIGN section 5): normal angular error and relighting PSNR / SSIM."""
from __future__ import annotations

import kornia
import torch

from capture_sim.errors import check_array

PSNR_CAP_DB = 100.0
"""PSNR of identical images is infinite; it is reported as this cap so JSON stays finite."""


def angular_error_deg(estimate: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Angle between normals in degrees.

    Args:
        estimate, truth: (..., 3) normals (normalised here; zero vectors give 90 degrees).

    Returns:
        (...) angles in [0, 180] degrees, always finite.
    """
    check_array("estimate", estimate, ("...", 3))
    check_array("truth", truth, tuple(estimate.shape))
    a = estimate.double() / estimate.double().norm(dim=-1, keepdim=True).clamp_min(1e-12)
    b = truth.double() / truth.double().norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # atan2 of |a x b| and a.b is accurate for tiny angles, where acos of a rounded cosine is not.
    return torch.rad2deg(torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))).to(estimate.dtype)


def normal_metrics(estimate: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> dict:
    """Normal-error summary over a mask.

    Args:
        estimate, truth: (..., 3) normals, camera frame.
        mask: (...) bool, pixels to count.

    Returns:
        dict with mae and median (degrees) and under_5, under_10, under_20, under_30 (fractions of
        the masked pixels in [0, 1]); NaN-free (an empty mask gives zeros and count 0).
    """
    mask = torch.as_tensor(mask, dtype=torch.bool)
    check_array("mask", mask, tuple(estimate.shape[:-1]))
    errors = angular_error_deg(estimate.detach(), truth.detach())[mask].double()
    if errors.numel() == 0:
        return {"mae": 0.0, "median": 0.0, "under_5": 0.0, "under_10": 0.0, "under_20": 0.0, "under_30": 0.0, "count": 0}
    summary = {"mae": float(errors.mean()), "median": float(errors.median())}
    for limit in (5, 10, 20, 30):
        summary[f"under_{limit}"] = float((errors < limit).double().mean())
    summary["count"] = int(errors.numel())
    return summary


def _to_kornia(images: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B, H, W, 3) channels-last images with the outside of the mask zeroed, as (B, 3, H, W)."""
    return (images * mask[..., None]).permute(0, 3, 1, 2).float()


def psnr(prediction: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor) -> float:
    """PSNR in dB over the masked pixels of linear images in [0, 1] (peak 1).

    Args:
        prediction, truth: (B, H, W, 3) or (H, W, 3) images.
        mask: (H, W) bool.

    Returns:
        10 log10(1 / MSE) over masked pixels and channels, capped at ``PSNR_CAP_DB``.
    """
    check_array("prediction", prediction, ("...", "H", "W", 3))
    check_array("truth", truth, tuple(prediction.shape))
    mask = torch.as_tensor(mask, dtype=torch.bool)
    error = (prediction.double() - truth.double())[..., mask, :]
    mse = float((error * error).mean()) if error.numel() else 0.0
    if mse <= 10 ** (-PSNR_CAP_DB / 10):
        return PSNR_CAP_DB
    return float(-10.0 * torch.log10(torch.tensor(mse)))


def ssim(prediction: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor, window_size: int = 11) -> float:
    """Mean SSIM (kornia) over the masked pixels; outside the mask both images are zeroed first.

    Args:
        prediction, truth: (B, H, W, 3) or (H, W, 3) linear images in [0, 1].
        mask: (H, W) bool.
        window_size: odd Gaussian window size of the SSIM.

    Returns:
        SSIM averaged over masked pixels and channels, in [-1, 1].
    """
    check_array("prediction", prediction, ("...", "H", "W", 3))
    check_array("truth", truth, tuple(prediction.shape))
    mask = torch.as_tensor(mask, dtype=torch.bool)
    batch_pred = prediction.reshape(-1, *prediction.shape[-3:])
    batch_truth = truth.reshape(-1, *truth.shape[-3:])
    window = min(window_size, 2 * (min(mask.shape) // 2) - 1)
    ssim_map = kornia.metrics.ssim(_to_kornia(batch_pred, mask), _to_kornia(batch_truth, mask), window_size=max(window, 1), max_val=1.0)
    return float(ssim_map.permute(0, 2, 3, 1)[:, mask].mean())
