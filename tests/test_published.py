"""The rebuilt published solver (the benchmarks' baseline): it reproduces the published accuracy on
a noise-free Lambertian sphere, which ours beats, and its gradients are right."""
import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.rig import Falloff
from reconstruct.metrics import angular_error_deg
from reconstruct.photometric_stereo import solve_ps
from reconstruct.published import incident_field, solve_published
from tests.reconstruct_scenes import capture, emission_of, load_patterns, sphere_scene


@pytest.fixture(scope="module")
def sphere_pixels():
    scene = sphere_scene()
    index = torch.nonzero(scene.mask.reshape(-1)).squeeze(1)
    return scene, index, scene.points.reshape(-1, 3)[index], scene.normal.reshape(-1, 3)[index]


# Issue 3 quotes the published implementation on a noise-free Lambertian sphere: 4.2 deg with mono
# gradient (M = 4) and 11.9 deg with its own learned 4 patterns. Our sphere differs in size and
# resolution, so the match is approximate.
@pytest.mark.parametrize("name, low, high", [("initial_mono_gradient", 3.0, 5.5), ("optimized_tri_random_4", 8.0, 14.0)])
def test_reproduces_published_sphere_error_that_solve_ps_removes(sphere_pixels, name, low, high):
    scene, index, points, truth = sphere_pixels
    captures, emission = capture(scene, emission_of(scene, load_patterns(name)))
    captures = captures.reshape(captures.shape[0], -1, 3)[:, index]
    normal, albedo = solve_published(captures, emission, incident_field(points, scene.lights, Falloff()))
    published_mae = float(angular_error_deg(normal, truth).mean())
    assert low < published_mae < high
    assert torch.isfinite(albedo).all()
    ours = solve_ps(captures, emission, points, scene.lights, Falloff())
    assert float(angular_error_deg(ours.normal, truth).mean()) < published_mae / 4


def test_incident_field_is_falloff_weighted_unit_directions():
    points = torch.tensor([[0.0, 0.0, 0.5], [0.1, -0.05, 0.45]], dtype=torch.float64)
    lights = torch.tensor([[0.2, -0.3, 0.0], [-0.4, 0.1, 0.05], [0.0, 0.0, -0.1]], dtype=torch.float64)
    field = incident_field(points, lights, Falloff())
    for n in range(2):
        for k in range(3):
            offset = lights[k] - points[n]
            distance = float(offset.norm())
            torch.testing.assert_close(field[n, k], offset / distance**3)


def test_gradcheck():
    generator = torch.Generator().manual_seed(0)
    points = torch.tensor([[0.0, 0.0, 0.5], [0.05, 0.02, 0.48], [-0.03, 0.04, 0.52]], dtype=torch.float64)
    lights = torch.tensor([[0.3, -0.3, 0.0], [-0.3, -0.3, 0.0], [0.3, 0.2, 0.0], [-0.3, 0.2, 0.0], [0.0, -0.5, 0.0]], dtype=torch.float64)
    incident = incident_field(points, lights, Falloff())
    emission = torch.rand(4, 5, 3, dtype=torch.float64, generator=generator) + 0.1
    captures = torch.rand(4, 3, 3, dtype=torch.float64, generator=generator) * 0.5 + 0.2
    inputs = (captures.requires_grad_(True), emission.requires_grad_(True))
    assert torch.autograd.gradcheck(lambda c, e: solve_published(c, e, incident), inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_bad_shapes_raise():
    incident = torch.zeros(2, 5, 3)
    with pytest.raises(InputError):
        solve_published(torch.zeros(4, 2, 3), torch.zeros(4, 6, 3), incident)
    with pytest.raises(InputError):
        solve_published(torch.zeros(4, 3, 3), torch.zeros(4, 5, 3), incident)
