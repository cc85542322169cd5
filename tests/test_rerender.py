"""The re-rendering loss against a plain Lambertian render, and its gradients."""
import math
import types

import numpy as np
import pytest
import torch

from capture_sim.rig import Falloff
from capture_sim.simulator import Capture
from train.rerender import rerender_loss


def _pixels(points, lights):
    """The parts of a ScenePixels that the loss reads."""
    return types.SimpleNamespace(points=points, lights=lambda: lights, rig=types.SimpleNamespace(falloff=Falloff()))


def _plain_render(normal, albedo, points, lights, emission):
    """sum_k E[m, k, c] a_c max(0, n . l_k) / d_k^2 clipped to [0, 1], pixel by pixel in numpy."""
    n, a, x, p, e = (t.detach().numpy() for t in (normal, albedo, points, lights, emission))
    out = np.zeros((e.shape[0], n.shape[0], 3))
    for i in range(n.shape[0]):
        for k in range(p.shape[0]):
            offset = p[k] - x[i]
            distance = np.linalg.norm(offset)
            out[:, i, :] += e[:, k, :] * a[i] * max(0.0, n[i] @ offset / distance) / distance**2
    return np.clip(out, 0.0, 1.0)


def _problem():
    generator = torch.Generator().manual_seed(0)
    lights = torch.tensor([[0.2, -0.1, 0.0], [-0.2, -0.1, 0.0], [0.0, 0.15, 0.0], [0.1, 0.1, 0.02]], dtype=torch.float64)
    points = torch.tensor([[0.0, 0.0, 0.5], [0.02, -0.01, 0.48], [-0.03, 0.02, 0.52]], dtype=torch.float64)
    normal = torch.tensor([[0.1, 0.2, -1.0], [-0.2, 0.1, -1.0], [0.05, -0.1, -1.0]], dtype=torch.float64)
    normal = normal / normal.norm(dim=1, keepdim=True)
    albedo = torch.tensor([[0.2, 0.15, 0.1], [0.1, 0.2, 0.12], [0.15, 0.1, 0.2]], dtype=torch.float64)
    emission = torch.rand(2, 4, 3, generator=generator, dtype=torch.float64) * 0.05 + 0.01
    captures = torch.rand(2, 3, 3, generator=generator, dtype=torch.float64) * 0.5
    return lights, points, normal, albedo, emission, captures


def test_rerender_loss_matches_a_plain_render():
    lights, points, normal, albedo, emission, captures = _problem()
    loss = rerender_loss(normal, albedo, Capture(captures, emission, 1.0), _pixels(points, lights), slice(None))
    rendered = _plain_render(normal, albedo, points, lights, emission)
    assert float(loss) == pytest.approx(math.sqrt(((rendered - captures.numpy()) ** 2).mean() + 1e-12), rel=1e-10)
    exact = Capture(torch.as_tensor(rendered), emission, 1.0)
    assert float(rerender_loss(normal, albedo, exact, _pixels(points, lights), slice(None))) < 1e-5


def test_rerender_loss_gradcheck():
    lights, points, normal, albedo, emission, captures = _problem()
    inputs = tuple(t.clone().requires_grad_() for t in (normal, albedo, emission, captures))

    def loss(normal, albedo, emission, captures):
        return rerender_loss(normal, albedo, Capture(captures, emission, 1.0), _pixels(points, lights), slice(None))

    assert torch.autograd.gradcheck(loss, inputs)
