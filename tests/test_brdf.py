"""The Cook-Torrance GGX lobe against closed forms, and its float32 behaviour at low roughness."""
import math

import pytest
import torch

from capture_sim.brdf import cook_torrance_specular, ggx_distribution


def test_ggx_distribution_is_normalised():
    """The projected GGX distribution integrates to one over the hemisphere: int D(h) (n.h) dw = 1."""
    theta = torch.linspace(0.0, math.pi / 2, 400_001, dtype=torch.float64)
    for alpha in (0.5, 0.1, 0.02):
        integrand = ggx_distribution(torch.cos(theta), torch.tensor(alpha, dtype=torch.float64)) * torch.cos(theta) * torch.sin(theta)
        assert abs(2 * math.pi * float(torch.trapezoid(integrand, theta)) - 1.0) < 1e-3, alpha


def test_low_roughness_peak_is_finite_in_float32():
    """At the mirror direction the peak is 1 / (pi alpha^2) and stays finite with its gradient
    (the form n.h^2 (alpha^2 - 1) + 1 cancelled to 0 in float32)."""
    view = torch.tensor([[0.0, 0.0, -1.0]])
    for roughness in (0.01, 0.02, 0.1):
        r32 = torch.tensor([roughness], requires_grad=True)
        lobe32 = cook_torrance_specular(view, view, view, r32)
        lobe32.sum().backward()
        lobe64 = cook_torrance_specular(view.double(), view.double(), view.double(), torch.tensor([roughness], dtype=torch.float64))
        assert torch.isfinite(lobe32).all() and torch.isfinite(r32.grad).all()
        assert abs(float(lobe32.detach()) / float(lobe64) - 1) < 1e-3, roughness
        alpha = max(roughness**2, 1e-4)
        assert abs(float(ggx_distribution(torch.tensor(1.0), torch.tensor(alpha))) * math.pi * alpha**2 - 1) < 1e-4


def test_schlick_fresnel_scales_the_lobe_by_its_closed_form():
    """F = F0 + (1 - F0)(1 - v.h)^5 with F0 = 0.04, at normal incidence and at grazing half angles."""
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    for light_deg, view_deg in ((0.0, 0.0), (30.0, -20.0), (70.0, -75.0)):
        light = torch.tensor([math.sin(math.radians(light_deg)), 0.0, math.cos(math.radians(light_deg))], dtype=torch.float64)
        view = torch.tensor([math.sin(math.radians(view_deg)), 0.0, math.cos(math.radians(view_deg))], dtype=torch.float64)
        half = (light + view) / (light + view).norm()
        expected = 0.04 + 0.96 * (1.0 - float(view @ half)) ** 5
        roughness = torch.tensor(0.5, dtype=torch.float64)
        ratio = cook_torrance_specular(normal, light, view, roughness, "schlick") / cook_torrance_specular(normal, light, view, roughness)
        assert float(ratio) == pytest.approx(expected, rel=1e-12)
