"""Normal-error and relighting metrics against hand computations."""
import math

import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from reconstruct.metrics import PSNR_CAP_DB, angular_error_deg, normal_metrics, psnr, ssim


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


def test_relighting_inputs_with_repeats_or_float_indices_are_refused():
    from reconstruct.relight import olat_emission, relighting_metrics

    values = torch.rand(2, 2, 3)
    with pytest.raises(InputError, match="more than once"):
        relighting_metrics(values, values, torch.tensor([5, 5]), 4, 4)
    with pytest.raises(InputError, match="must be integers"):
        olat_emission(torch.tensor([1.7]), 4, 1.0)
