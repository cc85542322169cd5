"""Normal-error and relighting metrics against hand computations."""
import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from capture_sim.errors import InputError
from reconstruct.metrics import PSNR_CAP_DB, angular_error_deg, normal_metrics, psnr, ssim
from tests.conftest import TOLERANCE


def test_angular_error_hand_values():
    down = torch.tensor([0.0, 0.0, -1.0])
    estimates = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    expected = torch.tensor([0.0, 45.0, 90.0, 180.0, 90.0])
    torch.testing.assert_close(angular_error_deg(estimates, down.expand(5, 3)), expected, atol=1e-5, rtol=0)


def test_angular_error_resolves_tiny_angles_in_float32():
    angle = math.radians(1e-3)
    tilted = torch.tensor([[math.sin(angle), 0.0, -math.cos(angle)]], dtype=torch.float32)
    error = angular_error_deg(tilted, torch.tensor([[0.0, 0.0, -1.0]]))
    assert abs(float(error) - 1e-3) < 1e-6


def test_angular_error_gradient_is_finite():
    estimate = torch.tensor([[0.3, 0.1, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0]], requires_grad=True)
    truth = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.3, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    angular_error_deg(estimate, truth).sum().backward()
    assert torch.isfinite(estimate.grad).all()


def test_angular_error_gradcheck():
    generator = torch.Generator().manual_seed(0)
    estimate = torch.randn(5, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    truth = torch.randn(5, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(angular_error_deg, (estimate, truth))


@pytest.mark.parametrize("length", [1e-200, 1e200])
def test_angular_error_does_not_depend_on_length(length):
    estimate = torch.tensor([[0.0, 1.0, -1.0], [0.3, 0.1, -1.0]], dtype=torch.float64)
    truth = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    scaled = (estimate * length).requires_grad_(True)
    error = angular_error_deg(scaled, truth * length)
    torch.testing.assert_close(error, angular_error_deg(estimate, truth))
    error.sum().backward()
    assert torch.isfinite(scaled.grad).all()


def test_normal_metrics_hand_values():
    truth = torch.tensor([0.0, 0.0, -1.0]).expand(2, 3, 3)
    degrees = torch.tensor([[1.0, 4.0, 6.0], [15.0, 25.0, 80.0]])
    radians = torch.deg2rad(degrees)
    estimate = torch.stack([torch.sin(radians), torch.zeros_like(radians), -torch.cos(radians)], dim=-1)
    mask = torch.tensor([[True, True, True], [True, True, False]])
    metrics = normal_metrics(estimate, truth, mask)
    assert metrics["mae"] == pytest.approx((1 + 4 + 6 + 15 + 25) / 5, abs=1e-4)
    assert metrics["median"] == pytest.approx(6.0, abs=1e-4)
    assert metrics["under_5"] == pytest.approx(2 / 5)
    assert metrics["under_10"] == pytest.approx(3 / 5)
    assert metrics["under_20"] == pytest.approx(4 / 5)
    assert metrics["under_30"] == pytest.approx(1.0)
    assert metrics["count"] == 5
    assert normal_metrics(estimate, truth, torch.zeros(2, 3, dtype=torch.bool))["count"] == 0


def test_psnr_hand_value_inside_mask_only():
    truth = torch.zeros(1, 4, 5, 3)
    prediction = truth.clone()
    mask = torch.zeros(4, 5, dtype=torch.bool)
    mask[1:3, 1:4] = True
    prediction[0, 1:3, 1:4] = 0.1  # MSE over the mask = 0.01 -> 20 dB
    prediction[0, 0, 0] = 1.0  # outside the mask: ignored
    assert psnr(prediction, truth, mask) == pytest.approx(20.0, abs=1e-5)
    assert psnr(truth, truth, mask) == PSNR_CAP_DB


def test_ssim_sanity():
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(2, 16, 20, 3, generator=generator)
    mask = torch.ones(16, 20, dtype=torch.bool)
    mask[:, :4] = False
    assert ssim(image, image, mask) == pytest.approx(1.0, abs=1e-4)
    noisy = (image + 0.2 * torch.randn(image.shape, generator=generator)).clamp(0, 1)
    assert ssim(noisy, image, mask) < 0.9
    assert ssim(image[0], image[0], mask, window_size=31) == pytest.approx(1.0, abs=1e-4)  # window shrunk to fit


def test_bad_inputs_raise():
    image = torch.rand(4, 5, 3)
    with pytest.raises(InputError):
        psnr(image, image[:3], torch.ones(4, 5, dtype=torch.bool))
    with pytest.raises(InputError):
        psnr(image, image, torch.zeros(4, 5, dtype=torch.bool))
    with pytest.raises(InputError):
        ssim(image, image, torch.ones(4, 5))
    for metric in (psnr, ssim):  # no images at all (was NaN)
        with pytest.raises(InputError, match="no images"):
            metric(torch.zeros(0, 4, 5, 3), torch.zeros(0, 4, 5, 3), torch.ones(4, 5, dtype=torch.bool))
    with pytest.raises(InputError):
        angular_error_deg(torch.zeros(3, 2), torch.zeros(3, 2))
    with pytest.raises(InputError):
        normal_metrics(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(3, dtype=torch.bool))


def test_median_of_an_even_count_and_numpy_inputs():
    estimate = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, -1.0]])
    truth = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    metrics = normal_metrics(estimate, truth, np.ones(2, dtype=bool))
    assert metrics["median"] == pytest.approx(22.5) and metrics["mae"] == pytest.approx(22.5)
    assert angular_error_deg(np.array([[0, 0, -1]]), np.array([[0, 1, -1]])).dtype == torch.float32


def test_image_metrics_accept_numpy_and_normal_metrics_ignore_the_background():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 1, (2, 8, 9, 3))
    prediction = np.clip(truth + 0.01, 0, 1)
    mask = np.ones((8, 9), dtype=bool)
    assert psnr(prediction, truth, mask) == pytest.approx(psnr(torch.as_tensor(prediction), torch.as_tensor(truth), torch.as_tensor(mask)))
    assert ssim(prediction, truth, mask) == pytest.approx(ssim(torch.as_tensor(prediction), torch.as_tensor(truth), torch.as_tensor(mask)))
    normals = np.tile(np.array([0.0, 0.0, -1.0]), (4, 5, 1))
    estimate = normals.copy()
    estimate[0, 0] = np.nan  # an external method's background
    inside = np.ones((4, 5), dtype=bool)
    inside[0, 0] = False
    assert normal_metrics(estimate, normals, inside)["count"] == 19
    with pytest.raises(InputError, match="NaN"):
        normal_metrics(estimate, normals, np.ones((4, 5), dtype=bool))


def test_image_metrics_ignore_nan_outside_the_mask_as_normal_metrics_do():
    """psnr and ssim refused NaN anywhere (and ssim's zeroing by multiplication kept it), where
    normal_metrics ignores the background; inside the mask NaN is still refused."""
    generator = torch.Generator().manual_seed(0)
    truth = torch.rand(2, 12, 13, 3, generator=generator, dtype=torch.float64)
    prediction = (truth + 0.02 * torch.randn(truth.shape, generator=generator, dtype=torch.float64)).clamp(0, 1)
    mask = torch.ones(12, 13, dtype=torch.bool)
    mask[:, :3] = False
    polluted = prediction.clone()
    polluted[:, :, :3] = float("nan")
    polluted[0, 0, 0] = float("inf")
    for metric in (psnr, ssim):
        assert metric(polluted, truth, mask) == metric(prediction, truth, mask)
        assert metric(truth, polluted, mask) == metric(truth, prediction, mask)
        inside = polluted.clone()
        inside[1, 5, 7, 2] = float("nan")
        with pytest.raises(InputError, match="prediction: NaN or infinite values inside the mask"):
            metric(inside, truth, mask)


def test_relighting_inputs_with_repeats_or_float_indices_are_refused():
    from reconstruct.relight import olat_emission, relighting_metrics

    values = torch.rand(2, 2, 3)
    with pytest.raises(InputError, match="more than once"):
        relighting_metrics(values, values, torch.tensor([5, 5]), 4, 4)
    with pytest.raises(InputError, match="must be integers"):
        olat_emission(torch.tensor([1.7]), 4, 1.0)


# ---------------------------------------------------------------------------------------------
# SSIM and PSNR against an independent numpy / scipy computation
# ---------------------------------------------------------------------------------------------


def _reference_ssim(prediction, truth, mask, window_size=11, sigma=1.5, k1=0.01, k2=0.03, border="mirror",
                    zero_outside_mask=True, mean_over_mask=True):
    """Mean SSIM of Wang et al. (2004) with numpy and scipy only, in the conventions of
    ``reconstruct.metrics.ssim`` (which calls ``kornia.metrics.ssim`` 0.9 with its defaults):

    - both images are multiplied by the mask first (zero outside it);
    - window: the sampled Gaussian exp(-n^2 / (2 sigma^2)), n = -r..r, normalised to sum 1, with
      sigma = 1.5 whatever its size; 11 taps, shrunk to the largest odd size <= min(H, W) for small
      images; applied separably along rows and columns, to each channel on its own;
    - borders: mirrored without repeating the edge pixel (d c b | a b c d | c b a: torch's
      "reflect", scipy's "mirror"), so the map keeps H x W (kornia's padding="same");
    - local moments weighted by the window: mu_x = G * x, sigma_x^2 = G * x^2 - mu_x^2,
      sigma_xy = G * (x y) - mu_x mu_y;
    - C1 = (0.01 L)^2, C2 = (0.03 L)^2 with data range L = 1, and kornia's eps = 1e-12 added to
      the denominator;
    - the map is averaged over the masked pixels, the three channels and all images.

    The keyword arguments switch single conventions so that a test can show each one matters.

    Args:
        prediction, truth: (..., H, W, 3) images.
        mask: (H, W) bool.
    """
    mask = np.asarray(mask, dtype=bool)
    height, width = mask.shape
    keep = mask[..., None] if zero_outside_mask else np.ones((height, width, 1))
    first = (np.asarray(prediction, dtype=np.float64) * keep).reshape(-1, height, width, 3)
    second = (np.asarray(truth, dtype=np.float64) * keep).reshape(-1, height, width, 3)
    taps_count = min(window_size, 2 * ((min(height, width) - 1) // 2) + 1)
    offsets = np.arange(taps_count) - taps_count // 2
    taps = np.exp(-(offsets**2) / (2.0 * sigma**2))
    taps /= taps.sum()

    def local_mean(values):  # G * values: the window along H, then along W
        for axis in (1, 2):
            values = ndimage.correlate1d(values, taps, axis=axis, mode=border)
        return values

    mu_x, mu_y = local_mean(first), local_mean(second)  # local means
    var_x = local_mean(first**2) - mu_x**2  # sigma_x^2
    var_y = local_mean(second**2) - mu_y**2  # sigma_y^2
    cov_xy = local_mean(first * second) - mu_x * mu_y  # sigma_xy
    c1, c2 = k1**2, k2**2  # (k L)^2 with L = 1
    similarity = (2 * mu_x * mu_y + c1) * (2 * cov_xy + c2) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2) + 1e-12)
    return float(similarity[:, mask].mean() if mean_over_mask else similarity.mean())


def _ssim_cases() -> dict:
    """name -> (prediction, truth, mask): random, smooth, brightness-scaled and dark image pairs
    (2 x 32 x 40 x 3) under a full and a disc mask, and a 6 x 9 image whose window shrinks to 5."""
    rng = np.random.default_rng(0)
    height, width = 32, 40
    rows, cols = np.mgrid[:height, :width]
    masks = {"full": np.ones((height, width), dtype=bool), "disc": (rows - 15.5) ** 2 + (cols - 21.0) ** 2 < 12.0**2}
    noise = rng.normal(size=(2, height, width, 3))
    random = rng.uniform(0, 1, (2, height, width, 3))
    smooth = ndimage.gaussian_filter(rng.uniform(0, 1, (2, height, width, 3)), sigma=(0, 3, 3, 0))
    smooth = 0.1 + 0.8 * (smooth - smooth.min()) / np.ptp(smooth)  # in [0.1, 0.9]
    dark = 0.01 + 0.04 * smooth  # where C1 matters: mu^2 ~ C1
    pairs = {
        "random": (np.clip(random + 0.2 * noise, 0, 1), random),
        "smooth": (np.clip(smooth + 0.05 * noise, 0, 1), smooth),
        "scaled": (0.6 * smooth, smooth),
        "dark": (np.clip(0.8 * dark + 0.003 * noise, 0, 1), dark),
    }
    cases = {f"{pair}-{name}": (*images, mask) for pair, images in pairs.items() for name, mask in masks.items()}
    small = rng.uniform(0, 1, (6, 9, 3))
    cases["small-full"] = (0.5 * small, small, np.ones((6, 9), dtype=bool))
    return cases


@pytest.mark.parametrize("case", list(_ssim_cases()))
def test_ssim_matches_numpy_gaussian_window_reference(case):
    prediction, truth, mask = _ssim_cases()[case]
    expected = _reference_ssim(prediction, truth, mask)
    tolerance = TOLERANCE[torch.float64]  # both compute in float64: they agree to rounding
    assert ssim(prediction, truth, mask) == pytest.approx(expected, rel=tolerance["rtol"], abs=tolerance["atol"])
    assert ssim(torch.as_tensor(prediction, dtype=torch.float32), torch.as_tensor(truth, dtype=torch.float32), mask) == pytest.approx(expected, abs=1e-5)


@pytest.mark.parametrize("wrong", [
    {"sigma": 1.0}, {"sigma": 2.0}, {"window_size": 7}, {"k1": 0.02}, {"k2": 0.02}, {"k2": 0.06},
    {"border": "reflect"}, {"border": "nearest"}, {"zero_outside_mask": False}, {"mean_over_mask": False},
], ids=lambda wrong: "-".join(f"{key}={value}" for key, value in wrong.items()))
def test_reference_comparison_would_catch_a_wrong_ssim_convention(wrong):
    """Each convention of the reference, changed alone, misses the library by far more than the
    tolerance of the comparison above, so a wrong window sigma, size, C1, C2, border or masking in
    ``ssim`` would fail it."""
    misses = [abs(_reference_ssim(prediction, truth, mask, **wrong) - ssim(prediction, truth, mask))
              for prediction, truth, mask in _ssim_cases().values()]
    assert max(misses) > 1e-4, misses


def test_ssim_of_flat_images_is_the_closed_form_luminance_term():
    """Flat images have no variance: SSIM = (2 u v + C1) C2 / ((u^2 + v^2 + C1) C2 + eps) everywhere."""
    c1, c2, eps = 0.01**2, 0.03**2, 1e-12
    mask = np.ones((12, 14), dtype=bool)
    for first, second in ((0.3, 0.5), (0.02, 0.01), (0.7, 0.7)):
        expected = (2 * first * second + c1) * c2 / ((first**2 + second**2 + c1) * c2 + eps)
        assert ssim(np.full((12, 14, 3), first), np.full((12, 14, 3), second), mask) == pytest.approx(expected, rel=1e-9)


def test_ssim_of_an_image_with_itself_is_one_and_falls_monotonically_with_noise():
    prediction, truth, mask = _ssim_cases()["smooth-disc"]
    assert ssim(truth, truth, mask) == pytest.approx(1.0, abs=1e-6)
    noise = np.random.default_rng(1).normal(size=truth.shape)
    levels = (0.0, 0.005, 0.02, 0.05, 0.1, 0.3)
    scores = [ssim(np.clip(truth + level * noise, 0, 1), truth, mask) for level in levels]
    assert scores[0] == pytest.approx(1.0, abs=1e-6)
    assert all(later < earlier for earlier, later in zip(scores, scores[1:])), scores
    assert scores[-1] < 0.5, scores


def test_relighting_metrics_psnr_and_ssim_match_numpy_reference_inside_the_mask():
    """``relighting_metrics`` scatters masked pixel values into zero images, clips to [0, 1] and
    crops around the mask before the SSIM: numbers equal the numpy reference on the whole image."""
    from reconstruct.relight import relighting_metrics

    rng = np.random.default_rng(2)
    height, width, count = 40, 48, 3
    rows, cols = np.mgrid[:height, :width]
    mask = ((rows - 20) / 6.0) ** 2 + ((cols - 23) / 9.0) ** 2 < 1  # bounding box + 11 px < image: cropped
    pixel_index = rng.permutation(np.flatnonzero(mask))  # any order of the masked pixels
    truth_images = ndimage.gaussian_filter(rng.uniform(0, 1.3, (count, height, width, 3)), sigma=(0, 2, 2, 0))
    truth_images = 1.2 * (truth_images - truth_images.min()) / np.ptp(truth_images)  # some above full scale
    predicted_images = 0.9 * truth_images + 0.03 * rng.normal(size=truth_images.shape)  # some below 0
    truth = truth_images.reshape(count, -1, 3)[:, pixel_index]
    predicted = predicted_images.reshape(count, -1, 3)[:, pixel_index]

    metrics = relighting_metrics(torch.as_tensor(predicted), torch.as_tensor(truth), torch.as_tensor(pixel_index), height, width)

    clipped_truth, clipped_predicted = np.clip(truth_images, 0, 1), np.clip(predicted_images, 0, 1)
    squared_error = (clipped_predicted - clipped_truth)[:, mask] ** 2
    close = {"rel": TOLERANCE[torch.float64]["rtol"], "abs": TOLERANCE[torch.float64]["atol"]}
    assert metrics["ssim"] == pytest.approx(_reference_ssim(clipped_predicted, clipped_truth, mask), **close)
    assert metrics["psnr"] == pytest.approx(10 * np.log10(1 / squared_error.mean()), **close)
    assert metrics["psnr_per_image"] == pytest.approx(10 * np.log10(1 / squared_error.mean(axis=(1, 2))), **close)
    assert metrics["rmse"] == pytest.approx(np.sqrt(squared_error.mean()), **close)
    assert metrics["images"] == count
