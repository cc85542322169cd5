"""Relighting evaluation: the 5:1 OLAT split, rendering held-out lights, PSNR and SSIM inside the mask.

DESIGN section 4: relighting quality is measured on held-out OLAT images, train:test = 5:1. Every
6th superpixel (k % 6 == 5) is a test light; the other 5/6 are fit lights. Model selection needs a
validation set that never touches the test lights: every 5th fit light.

Images compared are exposed OLAT images e * O[k] clipped to [0, 1] (the sensor's full scale), with
one exposure e for truth and rendering, so the numbers do not depend on the scene's radiometric
scale. PSNR and SSIM are those of ``reconstruct.metrics`` (PSNR of the MSE pooled over every masked
pixel, channel and image, data range 1, capped at 100 dB; SSIM maps averaged over the mask).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from capture_sim.errors import InputError, check_array
from reconstruct.metrics import psnr, ssim

TEST_EVERY = 6
"""Every 6th light is held out (train:test = 5:1)."""
VALIDATION_EVERY = 5
"""Every 5th fit light validates model selection."""
SSIM_WINDOW = 11


@dataclass(frozen=True, eq=False)
class LightSplit:
    """Indices (long tensors) of a K-light OLAT stack.

    Attributes:
        fit: (K_fit,) lights the model may be fitted on (all but the test lights).
        test: (K_test,) held-out lights, k % test_every == test_every - 1.
        validation: (K_val,) every ``validation_every``-th fit light, for model selection.
        train: (K_fit - K_val,) fit lights that are not validation lights.
    """

    fit: torch.Tensor
    test: torch.Tensor
    validation: torch.Tensor
    train: torch.Tensor

    def describe(self) -> dict:
        return {key: getattr(self, key).tolist() for key in ("fit", "test", "validation", "train")}


def split_lights(num_lights: int, test_every: int = TEST_EVERY, validation_every: int = VALIDATION_EVERY) -> LightSplit:
    """Split K lights into fit and held-out test lights (5:1), and the fit lights into train and validation.

    Args:
        num_lights: K.
        test_every: every ``test_every``-th light is a test light.
        validation_every: every ``validation_every``-th fit light is a validation light.

    Returns:
        LightSplit.

    Example:
        >>> split_lights(12).test.tolist()
        [5, 11]
    """
    if num_lights < test_every or test_every < 2 or validation_every < 2:
        raise InputError(f"need at least {test_every} lights and split periods >= 2, got K = {num_lights}")
    every = torch.arange(num_lights)
    is_test = every % test_every == test_every - 1
    fit, test = every[~is_test], every[is_test]
    is_validation = torch.arange(fit.numel()) % validation_every == validation_every - 1
    return LightSplit(fit=fit, test=test, validation=fit[is_validation], train=fit[~is_validation])


def _holds_integers(values: torch.Tensor) -> bool:
    """Whether an index tensor has an integer dtype (not float, complex or bool)."""
    return not (values.is_floating_point() or values.is_complex() or values.dtype == torch.bool)


def olat_emission(light_index: torch.Tensor, num_lights: int, exposure: float, dtype=torch.float32) -> torch.Tensor:
    """(M, K, 3) effective emission of OLAT captures of the lights ``light_index`` (M of them).

    Row m lights superpixel light_index[m] alone with intensity ``exposure`` in every channel (the
    OLAT stack is backlight-free radiance per unit display intensity, DESIGN section 2).
    """
    if not exposure > 0 or not math.isfinite(exposure):
        raise InputError(f"exposure must be positive and finite, got {exposure}")
    if exposure > torch.finfo(dtype).max:
        raise InputError(f"exposure {exposure:g} overflows {dtype} (largest {torch.finfo(dtype).max:g}): use a smaller exposure or a wider dtype")
    index = torch.as_tensor(light_index)
    if not _holds_integers(index):
        raise InputError(f"light indices must be integers, got dtype {index.dtype}")
    index = index.to(torch.int64)
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= num_lights):
        raise InputError(f"light indices must lie in [0, {num_lights})")
    emission = torch.zeros((index.numel(), num_lights, 3), dtype=dtype)
    emission[torch.arange(index.numel()), index] = exposure
    return emission


def pooled_psnr(predicted: torch.Tensor, truth: torch.Tensor) -> float:
    """PSNR (dB, data range 1, ``reconstruct.metrics.psnr``) of pixel values pooled over images.

    Args:
        predicted, truth: (M, N, 3) values of N masked pixels in M images.
    """
    check_array("predicted", predicted, ("M", "N", 3))
    check_array("truth", truth, tuple(predicted.shape))
    if predicted.shape[1] == 0:
        raise InputError("no pixels to compare")
    return psnr(predicted[:, None], truth[:, None], torch.ones((1, predicted.shape[1]), dtype=torch.bool))


def relighting_metrics(predicted: torch.Tensor, truth: torch.Tensor, pixel_index: torch.Tensor, height: int, width: int) -> dict:
    """PSNR, SSIM and RMSE of rendered against true exposed OLAT images, inside the mask.

    Args:
        predicted: (M, N, 3) rendered e * O of the masked pixels (clipped to [0, 1] here).
        truth: (M, N, 3) true e * O of the same pixels (clipped to [0, 1] here).
        pixel_index: (N,) distinct flat indices of the pixels in the H x W image.
        height, width: image size.

    Returns:
        ``{"psnr": dB (pooled MSE, capped at 100), "ssim": mean over the mask, "rmse": full-scale units,
        "psnr_per_image": [M values], "images": M}``.
    """
    check_array("predicted", predicted, ("M", "N", 3))
    check_array("truth", truth, tuple(predicted.shape))
    check_array("pixel_index", pixel_index, (predicted.shape[1],))
    pixel_index = torch.as_tensor(pixel_index)
    if pixel_index.numel() == 0:
        raise InputError("relighting metrics need at least one pixel")
    if not _holds_integers(pixel_index) or int(pixel_index.min()) < 0 or int(pixel_index.max()) >= height * width:
        raise InputError(f"pixel_index must hold integer indices into the {height} x {width} image")
    if torch.unique(pixel_index).numel() != pixel_index.numel():
        raise InputError("pixel_index lists a pixel more than once")
    # Tensors or arrays, as ``reconstruct.metrics`` takes them.
    predicted = torch.as_tensor(predicted).detach().double().clamp(0.0, 1.0)
    truth = torch.as_tensor(truth).detach().double().clamp(0.0, 1.0)
    count = predicted.shape[0]

    def to_images(values):
        images = torch.zeros((count, height * width, 3), dtype=torch.float64)
        images[:, pixel_index] = values
        return images.reshape(count, height, width, 3)

    mask = torch.zeros(height * width, dtype=torch.bool)
    mask[pixel_index] = True
    mask = mask.reshape(height, width)
    predicted_images, true_images = to_images(predicted), to_images(truth)
    rows, cols = _ssim_crop(mask)
    return {
        "psnr": psnr(predicted_images, true_images, mask),
        "ssim": ssim(predicted_images[:, rows, cols], true_images[:, rows, cols], mask[rows, cols], SSIM_WINDOW),
        "rmse": float(torch.sqrt(torch.mean((predicted - truth) ** 2))),
        "psnr_per_image": [psnr(predicted_images[i], true_images[i], mask) for i in range(count)],
        "images": count,
    }


def _ssim_crop(mask: torch.Tensor) -> tuple[slice, slice]:
    """Slices of the mask's bounding box grown by one SSIM window on every side (clipped to the image).

    Every masked pixel's window then lies inside the crop, and the crop holds the image's own values
    (zero outside the mask), so the masked SSIM is unchanged while the (float64) filtering covers
    only the object (about 3x fewer pixels for a sphere at 128 x 153). The full image is kept when a
    side of the crop would be shorter than the window, which would shrink the window.
    """
    height, width = mask.shape
    rows, cols = torch.nonzero(mask, as_tuple=True)
    row_slice = slice(max(int(rows.min()) - SSIM_WINDOW, 0), min(int(rows.max()) + SSIM_WINDOW + 1, height))
    col_slice = slice(max(int(cols.min()) - SSIM_WINDOW, 0), min(int(cols.max()) + SSIM_WINDOW + 1, width))
    if row_slice.stop - row_slice.start < SSIM_WINDOW or col_slice.stop - col_slice.start < SSIM_WINDOW:
        return slice(None), slice(None)
    return row_slice, col_slice
