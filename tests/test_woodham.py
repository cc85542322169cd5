"""Woodham least squares: OLAT and multiplexed paths on an analytic sphere, the per-pixel
reference, input checks."""
import math

import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.rig import Falloff
from reconstruct.metrics import normal_metrics
from reconstruct.photometric_stereo import FLAG_NAMES
from reconstruct.reference import woodham_olat_reference
from reconstruct.woodham import WoodhamConfig, solve_woodham, solve_woodham_image, solve_woodham_olat
from tests.reconstruct_scenes import capture, emission_of, load_patterns, sphere_scene

LIMIT_OLAT_DEG = 0.1
LIMIT_PATTERNS_DEG = 0.5
REFERENCE_ATOL = 1e-6


@pytest.fixture(scope="module")
def sphere():
    return sphere_scene()


def _identity_emission(num_lights, dtype=torch.float64):
    return torch.eye(num_lights, dtype=dtype)[:, :, None].expand(num_lights, num_lights, 3)


def test_olat_stack_recovers_normals_and_albedo(sphere):
    result = solve_woodham_image(sphere.olat, _identity_emission(144), sphere.points, sphere.mask, sphere.lights, Falloff())
    assert result.normal.shape == (*sphere.mask.shape, 3) and set(result.flags) == set(FLAG_NAMES)
    assert result.valid[sphere.mask].all() and not result.valid[~sphere.mask].any()
    assert normal_metrics(result.normal, sphere.normal, sphere.mask)["mae"] < LIMIT_OLAT_DEG
    torch.testing.assert_close(result.albedo[sphere.mask], sphere.albedo[sphere.mask], rtol=1e-4, atol=1e-8)
    # Noise-free Lambertian data: the fit explains the captures; outside the mask nothing is fitted.
    assert result.residual[sphere.mask].max() < 1e-4 and not result.flags["poor_fit"].any()
    assert (result.residual[~sphere.mask] == 1).all()


def test_olat_entry_point_matches_identity_emission(sphere):
    index = torch.nonzero(sphere.mask.reshape(-1)).squeeze(1)
    olat = sphere.olat.reshape(144, -1, 3)[:, index]
    points = sphere.points.reshape(-1, 3)[index]
    exposure = 0.7
    by_exposure = solve_woodham_olat(olat * exposure, points, sphere.lights, Falloff(), exposure)
    by_emission = solve_woodham(olat, _identity_emission(144), points, sphere.lights, Falloff())
    torch.testing.assert_close(by_exposure.normal, by_emission.normal)
    torch.testing.assert_close(by_exposure.albedo, by_emission.albedo)


def test_float16_olat_stack_is_read_blockwise(sphere):
    index = torch.nonzero(sphere.mask.reshape(-1)).squeeze(1)
    exposure = 0.9 / float(sphere.olat.max())
    olat = (sphere.olat.reshape(144, -1, 3)[:, index] * exposure).half()
    points = sphere.points.reshape(-1, 3)[index]
    result = solve_woodham_olat(olat, points, sphere.lights, Falloff(), exposure=exposure, chunk_size=100)
    assert result.normal.dtype == torch.float32
    assert normal_metrics(result.normal.double(), sphere.normal.reshape(-1, 3)[index], torch.ones(len(index), dtype=torch.bool))["mae"] < 0.5


@pytest.mark.parametrize("name", ["initial_mono_gradient", "initial_mono_complementary", "initial_tri_random_6"])
def test_multiplexed_patterns(sphere, name):
    captures, emission = capture(sphere, emission_of(sphere, load_patterns(name)))
    result = solve_woodham_image(captures, emission, sphere.points, sphere.mask, sphere.lights, Falloff())
    assert normal_metrics(result.normal, sphere.normal, sphere.mask)["mae"] < LIMIT_PATTERNS_DEG


def test_matches_per_pixel_reference(sphere):
    index = torch.nonzero(sphere.mask.reshape(-1)).squeeze(1)
    pick = index[torch.randperm(index.numel(), generator=torch.Generator().manual_seed(1))[:20]]
    olat = sphere.olat.reshape(144, -1, 3)[:, pick] * 3.0
    olat[5:9, :4] = 1.0  # a few saturated captures are dropped by both
    points = sphere.points.reshape(-1, 3)[pick]
    config = WoodhamConfig(restart_condition=math.inf)
    fast = solve_woodham_olat(olat, points, sphere.lights, Falloff(), exposure=3.0, config=config)
    normals, albedo = woodham_olat_reference(olat.numpy(), np.full((144, 3), 3.0), points.numpy(), sphere.lights.numpy(), lambda d: 1.0 / d**2)
    np.testing.assert_allclose(fast.normal.numpy(), normals, atol=REFERENCE_ATOL)
    np.testing.assert_allclose(fast.albedo.numpy(), albedo, atol=REFERENCE_ATOL)
    assert fast.flags["saturated"][:4].all()


def test_bad_inputs_raise(sphere):
    index = torch.nonzero(sphere.mask.reshape(-1)).squeeze(1)[:5]
    olat = sphere.olat.reshape(144, -1, 3)[:, index]
    points = sphere.points.reshape(-1, 3)[index]
    with pytest.raises(InputError):
        solve_woodham(olat[:2], _identity_emission(144)[:2], points, sphere.lights, Falloff())  # fewer than 3
    with pytest.raises(InputError):
        solve_woodham_olat(olat[:100], points, sphere.lights, Falloff())
    with pytest.raises(InputError):
        solve_woodham_olat(olat, points, sphere.lights, Falloff(), exposure=0.0)
    with pytest.raises(InputError):
        solve_woodham_olat(olat, points, sphere.lights, Falloff(), config=WoodhamConfig(shadow_threshold=1.5))


@pytest.mark.parametrize("exposure", [0.37, 0.1, 2.2, 0.013])
def test_float32_diagonal_emission_is_detected_as_olat(exposure):
    """A one-light-at-a-time emission with any exposure in float32 takes the OLAT path (a sum
    comparison used to miss it through rounding)."""
    from reconstruct.relight import olat_emission
    from reconstruct.woodham import _diagonal_light_emission

    emission = olat_emission(torch.arange(144), 144, exposure)
    assert emission.dtype == torch.float32
    detected = _diagonal_light_emission(emission)
    assert detected is not None and torch.equal(detected, torch.diagonal(emission, dim1=0, dim2=1).T)
    emission[3, 5, 1] = 1e-6
    assert _diagonal_light_emission(emission) is None


def test_no_lights_is_refused():
    with pytest.raises(InputError, match="at least one light"):
        solve_woodham(torch.rand(3, 2, 3), torch.rand(3, 0, 3), torch.tensor([[0.0, 0.0, 0.5]] * 2), torch.zeros(0, 3), Falloff())


def _valid_errors(result, sphere):
    from reconstruct.metrics import angular_error_deg

    valid = result.valid & sphere.mask
    return valid, angular_error_deg(result.normal, sphere.normal)[valid]


@pytest.mark.parametrize("peak", [1.5, 3.0])
def test_a_channel_that_saturation_leaves_under_three_patterns_is_left_out(sphere, peak):
    """Grey patterns, over-exposed: the red channel (the brightest albedo) keeps fewer than three
    unsaturated captures where green and blue keep four. Its damped solve returned some vector of
    an unconstrained family and the summed normal was off by up to 57 (84) deg, valid."""
    captures, emission = capture(sphere, emission_of(sphere, load_patterns("initial_mono_gradient")), peak=peak)
    result = solve_woodham_image(captures.clamp(max=1.0), emission, sphere.points, sphere.mask, sphere.lights, Falloff())
    valid, errors = _valid_errors(result, sphere)
    assert int(valid.sum()) > 0.6 * int(sphere.mask.sum()) and (result.flags["saturated"] & sphere.mask).sum() > 400
    assert float(errors.max()) < LIMIT_OLAT_DEG


def test_colour_sets_use_the_channels_that_fix_the_normal_and_flag_pixels_none_does(sphere):
    """Woodham solves each channel alone: a channel lit the same way by every pattern, or by two
    distinct patterns, cannot fix g_c = a_c n (off by up to 118 deg, valid). Left out where another
    channel can; a pixel no channel determines alone is ill_conditioned (solve_ps couples them)."""
    from patterns.families import make_patterns

    grey = load_patterns("initial_mono_gradient")
    constant_red = grey.clone()
    constant_red[..., 0] = 0.7
    two_each = grey.clone()
    two_each[..., 0], two_each[..., 1], two_each[..., 2] = grey[[0, 1, 0, 1], :, 0], grey[[2, 3, 2, 3], :, 1], grey[[0, 2, 0, 2], :, 2]
    # Three patterns: a wrong shadow mask fits each channel exactly; the shared normal's residual
    # shows it and the pixel is searched again (27 valid pixels were 12-109 deg off).
    tri_gradient = make_patterns("tri_gradient", 3).double().reshape(3, -1, 3)
    for patterns, determined in ((constant_red, True), (tri_gradient, True), (two_each, False)):
        captures, emission = capture(sphere, emission_of(sphere, patterns))
        result = solve_woodham_image(captures, emission, sphere.points, sphere.mask, sphere.lights, Falloff())
        valid, errors = _valid_errors(result, sphere)
        if determined:
            assert bool(valid[sphere.mask].all()) and float(errors.max()) < LIMIT_OLAT_DEG
        else:
            assert not valid.any() and bool(result.flags["ill_conditioned"][sphere.mask].all())


def test_exposure_of_the_olat_entry_point_is_a_number(sphere):
    index = torch.nonzero(sphere.mask.reshape(-1)).squeeze(1)[:10]
    with pytest.raises(InputError, match="exposure must be a positive number, got True"):
        solve_woodham_olat(sphere.olat.reshape(144, -1, 3)[:, index], sphere.points.reshape(-1, 3)[index], sphere.lights, Falloff(), exposure=True)


@pytest.mark.parametrize("family, unlit_blue, wrong_left", [("olat", False, 0), ("mono_random", False, 1), ("olat", True, 1)])
def test_three_grey_patterns_flag_pixels_that_two_exact_answers_fit(family, unlit_blue, wrong_left):
    """Three grey patterns solve every channel's 3 x 3 system exactly whatever the shadow mask,
    so a wrong self-consistent mask fits as well as the right one (noise-free sphere on the
    backlit reference rig: 19 (olat) and 4 (mono_random) valid, unflagged pixels 11-111 deg off).
    Such pixels are searched from every start and flagged ill_conditioned where two answers fit
    (12 of the 19) or where the answer sits on a lit superpixel's tangent plane (the other 7).
    A channel left unlit repeats one equation (the backlight's) and is no reason to call the set
    colour (11 wrong valid pixels with blue off). Both solvers; what is left is documented in
    PSResult."""
    from capture_sim.rig import load_rig
    from capture_sim.simulator import light_transport, simulate
    from capture_sim.synth import lambertian_sphere
    from patterns.families import make_patterns
    from reconstruct.metrics import angular_error_deg
    from reconstruct.photometric_stereo import solve_ps

    rig = load_rig()
    scene = lambertian_sphere(rig, height=16, width=20)
    transport = light_transport(scene.olat, scene.mask)
    points = scene.points(rig.working_distance).reshape(-1, 3)[transport.pixel_index].double()
    truth = torch.as_tensor(scene.normal).reshape(-1, 3)[transport.pixel_index].double()
    patterns = make_patterns(family, 3).double()
    if unlit_blue:
        patterns[..., 2] = 0.0
    captured = simulate(patterns, transport, rig, noise=None, bit_depth=None)
    for solver in (solve_ps, solve_woodham):
        result = solver(captured.captures, captured.emission, points, rig.lights(torch.float64), rig.falloff)
        wrong = result.valid & (angular_error_deg(result.normal, truth) > 10)
        assert int(wrong.sum()) <= wrong_left, solver.__name__
        assert int(result.valid.sum()) >= 0.1 * len(truth)
