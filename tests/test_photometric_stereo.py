"""Analytic multiplexed photometric stereo: shapes, input checks, accuracy on an analytic sphere,
the per-pixel reference, gradients."""
import math
import re

import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.rig import Falloff, panel_positions
from reconstruct.metrics import angular_error_deg, normal_metrics
from reconstruct.photometric_stereo import FLAG_NAMES, PSConfig, PSResult, solve_ps, solve_ps_image
from reconstruct.pixel_solve import CONDITION_CAP, alternation, alternation_jacobian, normalised_moments
from reconstruct.reference import ps_reference
from tests.reconstruct_scenes import capture, emission_of, load_patterns, pattern_names, sphere_scene

# Accuracy limits (degrees) on the noise-free sphere, and the fast-vs-reference limit.
LIMIT_NAMED_SETS_DEG = 0.5
LIMIT_EVERY_SET_DEG = 1.0
REFERENCE_ATOL = 1e-6
# Tight convergence so that finite differences of the solver are accurate to ~1e-9; the gradient
# formula (implicit differentiation) is the same in every configuration.
GRADCHECK_CONFIG = PSConfig(tolerance_deg=1e-10, max_alternations=1000, condition_threshold=CONDITION_CAP)


@pytest.fixture(scope="module")
def sphere():
    return sphere_scene()


def _sphere_captures(scene, name):
    return capture(scene, emission_of(scene, load_patterns(name)))


def _flat(scene, captures):
    index = torch.nonzero(scene.mask.reshape(-1)).squeeze(1)
    return captures.reshape(captures.shape[0], -1, 3)[:, index], scene.points.reshape(-1, 3)[index], scene.normal.reshape(-1, 3)[index]


def test_float32_noise_free_pixels_converge_despite_rounding_noise(sphere):
    """In float32 the moves of slowly contracting pixels jitter at ~0.01-0.05 deg and once failed to
    shrink above the rounding level: a third of this noise-free sphere was flagged not_converged
    (none in float64). Such pixels now finish in float64: no flag, and the float64 accuracy."""
    captures, emission = _sphere_captures(sphere, "initial_tri_random_4")
    single = [value.float() for value in (captures, emission, sphere.points, sphere.lights)]
    result = solve_ps_image(single[0], single[1], single[2], sphere.mask, single[3], Falloff())
    assert result.normal.dtype == torch.float32
    assert not result.flags["not_converged"][sphere.mask].any()
    assert normal_metrics(result.normal.double(), sphere.normal, sphere.mask)["mae"] < 0.02


def test_invalid_causes_name_saturation_that_left_too_few_equations():
    from reconstruct.photometric_stereo import invalid_causes

    text = invalid_causes({"ill_conditioned": 1.0, "saturated": 1.0, "dark": 0.0, "grazing": 0.2})
    assert text.startswith("ill_conditioned (too few or too similar captures) on 100% of the pixels; saturated")
    assert "grazing" not in text and "dark" not in text
    assert invalid_causes({"ill_conditioned": 0.5}) == "ill_conditioned (too few or too similar captures) on 50% of the pixels"


def test_image_solve_shapes_and_types(sphere):
    captures, emission = _sphere_captures(sphere, "initial_mono_gradient")
    result = solve_ps_image(captures, emission, sphere.points, sphere.mask, sphere.lights, Falloff())
    height, width = sphere.mask.shape
    assert isinstance(result, PSResult)
    assert result.normal.shape == (height, width, 3) and result.albedo.shape == (height, width, 3)
    assert result.valid.shape == result.condition.shape == (height, width)
    assert set(result.flags) == set(FLAG_NAMES) and all(flag.shape == (height, width) for flag in result.flags.values())
    assert result.valid.dtype == torch.bool and result.normal.dtype == torch.float64
    outside = ~sphere.mask
    assert not result.valid[outside].any()
    assert (result.normal[outside] == torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)).all()
    assert (result.albedo[outside] == 0).all()
    unit_length = result.normal[result.valid].norm(dim=-1)
    torch.testing.assert_close(unit_length, torch.ones_like(unit_length))
    view = -sphere.points / sphere.points.norm(dim=-1, keepdim=True)
    assert ((result.normal * view).sum(-1)[result.valid] > 0).all(), "valid normals face the camera"
    assert (result.albedo >= 0).all()


def test_flat_and_image_solves_agree_and_chunk_size_does_not_matter(sphere):
    captures, emission = _sphere_captures(sphere, "initial_tri_complementary")
    flat_captures, points, _ = _flat(sphere, captures)
    flat = solve_ps(flat_captures, emission, points, sphere.lights, Falloff(), chunk_size=37)
    image = solve_ps_image(captures, emission, sphere.points, sphere.mask, sphere.lights, Falloff())
    torch.testing.assert_close(flat.normal, image.normal[sphere.mask])
    torch.testing.assert_close(flat.albedo, image.albedo[sphere.mask])
    assert torch.equal(flat.valid, image.valid[sphere.mask])


@pytest.mark.parametrize("name", ["initial_mono_gradient", "initial_tri_complementary"])
def test_named_sets_recover_sphere_normals_and_albedo(sphere, name):
    captures, emission = _sphere_captures(sphere, name)
    result = solve_ps_image(captures, emission, sphere.points, sphere.mask, sphere.lights, Falloff())
    assert result.valid[sphere.mask].float().mean() > 0.99
    metrics = normal_metrics(result.normal, sphere.normal, sphere.mask)
    assert metrics["mae"] < LIMIT_NAMED_SETS_DEG, metrics
    good = result.valid & (angular_error_deg(result.normal, sphere.normal) < 0.01)
    torch.testing.assert_close(result.albedo[good], sphere.albedo[good], rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("name", pattern_names())
def test_every_reference_pattern_set_is_solved_to_within_a_degree(sphere, name):
    # No pixel is replaced by the invalid default here: the test measures the solver itself, also
    # on sets the default configuration flags as ill-conditioned (e.g. initial_gray_noise).
    captures, emission = _sphere_captures(sphere, name)
    assert captures.max() < 1.0
    config = PSConfig(condition_threshold=CONDITION_CAP)
    result = solve_ps_image(captures, emission, sphere.points, sphere.mask, sphere.lights, Falloff(), config)
    metrics = normal_metrics(result.normal, sphere.normal, sphere.mask)
    assert metrics["mae"] < LIMIT_EVERY_SET_DEG, (name, metrics)


def test_float32_matches_float64(sphere):
    captures, emission = _sphere_captures(sphere, "initial_mono_gradient")
    result = solve_ps_image(captures.float(), emission.float(), sphere.points.float(), sphere.mask, sphere.lights.float(), Falloff())
    assert result.normal.dtype == torch.float32
    assert normal_metrics(result.normal.double(), sphere.normal, sphere.mask)["mae"] < 0.05


@pytest.mark.parametrize("name", ["initial_mono_gradient", "initial_tri_complementary", "optimized_tri_random_4"])
def test_fast_path_matches_per_pixel_reference(sphere, name):
    captures, emission = _sphere_captures(sphere, name)
    flat_captures, points, _ = _flat(sphere, captures)
    pick = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(3))[:20]
    config = PSConfig(tolerance_deg=1e-9, max_alternations=500, restart_condition=math.inf, condition_threshold=CONDITION_CAP)
    fast = solve_ps(flat_captures[:, pick], emission, points[pick], sphere.lights, Falloff(), config)
    normals, albedo = ps_reference(flat_captures[:, pick].numpy(), emission.numpy(), points[pick].numpy(), sphere.lights.numpy(), lambda d: 1.0 / d**2)
    np.testing.assert_allclose(fast.normal.numpy(), normals, atol=REFERENCE_ATOL)
    np.testing.assert_allclose(fast.albedo.numpy(), albedo, atol=REFERENCE_ATOL)


def _tiny_problem():
    """6 points on a small sphere, 2 x 3 superpixels (K = 6), 3 random colour patterns."""
    generator = torch.Generator().manual_seed(0)
    lights = torch.as_tensor(panel_positions(2, 3, diagonal_inch=40.0).reshape(-1, 3))
    normal = torch.nn.functional.normalize(
        torch.tensor([[0.1, 0.2, -1], [0.3, -0.1, -1], [-0.2, 0.1, -1], [0, 0, -1], [0.4, 0.3, -1], [-0.3, -0.3, -1]], dtype=torch.float64), dim=1
    )
    points = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64) + 0.05 * normal
    offset = lights[None] - points[:, None]
    distance = offset.norm(dim=-1)
    shading = ((offset / distance[..., None]) * normal[:, None]).sum(-1).clamp_min(0) / distance**2
    olat = (torch.tensor([0.5, 0.4, 0.3], dtype=torch.float64) * shading[..., None]).permute(1, 0, 2)  # (K, N, 3)
    emission = torch.rand(3, 6, 3, dtype=torch.float64, generator=generator) * 0.1 + 0.01
    captures = torch.einsum("mkc,knc->mnc", emission, olat)
    scale = 0.8 / captures.max()
    return captures * scale, emission * scale, points, lights, normal


def test_gradcheck_wrt_emission_and_captures():
    captures, emission, points, lights, normal = _tiny_problem()
    result = solve_ps(captures, emission, points, lights, Falloff(), GRADCHECK_CONFIG)
    assert result.valid.all() and (result.normal - normal).abs().max() < 1e-6

    def solve(emission_, captures_):
        solved = solve_ps(captures_, emission_, points, lights, Falloff(), GRADCHECK_CONFIG)
        return solved.normal, solved.albedo

    inputs = (emission.clone().requires_grad_(True), captures.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(solve, inputs, eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=True)


def test_alternation_jacobian_matches_autograd():
    # Random moments with the awkward cases: identical patterns (singular systems), all-black
    # pixels, channels whose albedo the relu clamps at 0, and zero albedo.
    generator = torch.Generator().manual_seed(3)
    count, num_patterns = 600, 4
    vectors = torch.randn(num_patterns, 3, 3, count, generator=generator, dtype=torch.float64)
    vectors[:, :, :, :100] = vectors[:1, :, :, :100]
    vectors[:, :, :, 100:150] = 0
    captures = torch.rand(num_patterns, 3, count, generator=generator, dtype=torch.float64)
    captures[:, 0, 200:300] *= -1
    moments = normalised_moments(vectors, captures, torch.ones_like(captures), captures.abs().amax(dim=(0, 1)))
    albedo = torch.rand(3, count, generator=generator, dtype=torch.float64) + 0.1
    albedo[:, 300:350] = 0
    probe = albedo.clone().requires_grad_(True)
    mapped, _ = alternation(probe, moments, 1e-9)
    directions = torch.eye(3, dtype=torch.float64)[:, :, None].expand(3, 3, count)
    expected = torch.autograd.grad(mapped, probe, directions, is_grads_batched=True)[0]
    jacobian = alternation_jacobian(albedo, moments, 1e-9)
    assert torch.isfinite(jacobian).all()
    scale = expected.abs().amax(dim=(0, 1)).clamp_min(1.0)
    assert ((jacobian - expected).abs().amax(dim=(0, 1)) / scale).max() < 1e-9


def test_values_do_not_depend_on_gradient_tracking(sphere):
    captures, emission = _sphere_captures(sphere, "initial_tri_complementary")
    flat_captures, points, _ = _flat(sphere, captures)
    plain = solve_ps(flat_captures, emission, points, sphere.lights, Falloff())
    tracked = solve_ps(flat_captures.clone().requires_grad_(True), emission.clone().requires_grad_(True), points, sphere.lights, Falloff())
    # The gradient path adds only a derivative: the values are the same bits.
    assert torch.equal(tracked.normal.detach(), plain.normal) and torch.equal(tracked.albedo.detach(), plain.albedo)


def test_bad_inputs_raise():
    captures, emission, points, lights, _ = _tiny_problem()
    falloff = Falloff()
    with pytest.raises(InputError):
        solve_ps(captures[:, :, :2], emission, points, lights, falloff)
    with pytest.raises(InputError):
        solve_ps(captures[:2], emission, points, lights, falloff)
    with pytest.raises(InputError):
        solve_ps(captures, emission[:, :5], points, lights, falloff)
    with pytest.raises(InputError):
        solve_ps(captures, -emission, points, lights, falloff)
    with pytest.raises(InputError):
        solve_ps(captures, emission, points[:5], lights, falloff)
    nan_captures = captures.clone()
    nan_captures[0, 0, 0] = float("nan")
    with pytest.raises(InputError):
        solve_ps(nan_captures, emission, points, lights, falloff)
    with pytest.raises(InputError):
        solve_ps(captures, emission, points, lights, falloff, config=PSConfig(damping=0.0))
    with pytest.raises(InputError):
        solve_ps(captures, emission, points, lights, Falloff("fitted", a=-5.458, b=14.7449))  # negative at 0.5 m
    with pytest.raises(InputError):
        solve_ps_image(captures[:, :, None], emission, points[:, None], torch.ones(6, 1), lights, falloff)  # float mask
    # Raw 12-bit counts would all count as saturated; odd arguments failed deep inside with TypeErrors.
    with pytest.raises(InputError, match=r"captures reach .* full-scale units .* raw counts"):
        solve_ps(captures * 4095, emission * 4095, points, lights, falloff)
    with pytest.raises(InputError, match="chunk_size must be a positive whole number"):
        solve_ps(captures, emission, points, lights, falloff, chunk_size=1.5)
    with pytest.raises(InputError, match="falloff must be a function of distance"):
        solve_ps(captures, emission, points, lights, None)
    from reconstruct.unrolled_ps import light_reach, solve_ps_unrolled
    from reconstruct.woodham import solve_woodham

    with pytest.raises(InputError, match="falloff must be a function of distance"):
        solve_ps_unrolled(captures, emission, points, lights, None)
    # One factor per distance: a result that broadcast weighted every light alike, all pixels valid.
    first_light_only = lambda distance: 1.0 / distance[..., :1] ** 2  # noqa: E731
    for solver in (solve_ps, solve_ps_unrolled, solve_woodham):
        with pytest.raises(InputError, match=r"falloff returned shape \(\d+, 1\) for distances of shape"):
            solver(captures, emission, points, lights, first_light_only)
    assert torch.equal(solve_ps(captures, emission, points, lights, lambda distance: 2.0).normal,
                       solve_ps(captures, emission, points, lights, lambda distance: torch.full_like(distance, 2.0)).normal)  # a constant: a number will do
    with pytest.raises(InputError, match="torch tensors"):
        light_reach(points.numpy(), lights.numpy(), falloff)
    with pytest.raises(InputError, match="raw counts"):
        solve_woodham(captures * 255, emission * 255, points, lights, falloff)


def _render_lambertian(points, normal, albedo, lights, emission):
    """(M, N, 3) captures a_c sum_k E[m, k, c] max(0, l_k . n) / d_k^2, written out here."""
    offset = lights[None] - points[:, None]  # (N, K, 3)
    distance = offset.norm(dim=-1)
    shading = ((offset / distance[..., None]) * normal[:, None]).sum(-1).clamp_min(0) / distance**2
    return torch.einsum("mkc,nk,nc->mnc", emission, shading, albedo)


def test_residual_is_the_relative_misfit_of_the_fitted_model(sphere):
    captures, emission = _sphere_captures(sphere, "initial_mono_gradient")
    flat, points, _ = _flat(sphere, captures)
    clean = solve_ps(flat, emission, points, sphere.lights, Falloff())
    assert clean.residual.max() < 1e-4 and not clean.flags["poor_fit"].any()
    # Light no normal explains (like a highlight) in the first capture; scaled to stay unsaturated.
    disturbed = flat.clone()
    disturbed[0] *= 1.5
    disturbed, emission = disturbed * 0.6, emission * 0.6
    result = solve_ps(disturbed, emission, points, sphere.lights, Falloff())
    rendered = _render_lambertian(points, result.normal, result.albedo, sphere.lights, emission)
    expected = (disturbed - rendered).square().sum((0, 2)).sqrt() / disturbed.square().sum((0, 2)).sqrt()
    assert result.valid.float().mean() > 0.9
    torch.testing.assert_close(result.residual[result.valid], expected[result.valid], rtol=1e-4, atol=1e-6)
    assert (result.flags["poor_fit"] == (result.valid & (result.residual > PSConfig().residual_threshold))).all()
    assert result.flags["poor_fit"].float().mean() > 0.2, "poor_fit does not invalidate"
    assert (result.residual[~result.valid] > PSConfig().residual_threshold).any(), "invalid pixels keep their residual"


@pytest.mark.parametrize("key", ["residual_threshold", "grazing_cos"])
@pytest.mark.parametrize("value", [-0.1, 1.5, float("nan")])
def test_flag_thresholds_outside_the_unit_interval_are_refused(key, value):
    with pytest.raises(InputError, match=key):
        PSConfig(**{key: value})


def _tilted_problem(tilt):
    """Four float64 pixels 0.5 m in front of a 3 x 4 panel, normals tilted by about ``tilt`` rad,
    five random colour patterns; returns captures, emission, points, lights, shadowed (pixel, light) pairs."""
    generator = torch.Generator().manual_seed(0)
    lights = torch.as_tensor(panel_positions(3, 4, diagonal_inch=40.0).reshape(-1, 3))
    normal = torch.tensor([[tilt, 0.1, -1], [0.2, -tilt, -1], [-tilt, 0.15, -1], [0.05, tilt, -1]], dtype=torch.float64)
    normal = normal / normal.norm(dim=1, keepdim=True)
    points = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64) + 0.05 * normal
    offset = lights[None] - points[:, None]
    distance = offset.norm(dim=-1)
    cosine = ((offset / distance[..., None]) * normal[:, None]).sum(-1)
    olat = (torch.tensor([0.5, 0.4, 0.3], dtype=torch.float64) * (cosine.clamp_min(0) / distance**2)[..., None]).permute(1, 0, 2)
    emission = torch.rand(5, lights.shape[0], 3, dtype=torch.float64, generator=generator) * 0.1 + 0.01
    captures = torch.einsum("mkc,knc->mnc", emission, olat)
    scale = 0.8 / captures.max()
    return captures * scale, emission * scale, points, lights, int((cosine < 0).sum())


def _gradcheck_solver(captures, emission, points, lights):
    config = PSConfig(tolerance_deg=1e-10, max_alternations=1000, condition_threshold=CONDITION_CAP, restart_condition=math.inf)

    def solve(emission, captures):
        result = solve_ps(captures, emission, points, lights, Falloff(), config)
        return result.normal, result.albedo

    return torch.autograd.gradcheck(solve, (emission.clone().requires_grad_(), captures.clone().requires_grad_()), eps=1e-6, atol=1e-5, rtol=1e-3)


def test_gradcheck_with_saturated_equations():
    """Saturated equations are dropped: no gradient may flow through them."""
    captures, emission, points, lights, _ = _tilted_problem(0.2)
    captures[0, 0, :] = 1.0
    captures[1, 2, 1] = 1.0
    assert solve_ps(captures, emission, points, lights, Falloff()).flags["saturated"].any()
    assert _gradcheck_solver(captures, emission, points, lights)


def test_gradcheck_with_attached_shadows():
    """Lights behind a pixel's tangent plane add nothing to its value or its gradient."""
    captures, emission, points, lights, shadowed = _tilted_problem(1.6)
    assert shadowed > 0
    assert _gradcheck_solver(captures, emission, points, lights)


@pytest.mark.filterwarnings("ignore:32 x 40 scenes have another aspect ratio")  # the size that shows the case
def test_pixels_that_did_not_converge_carry_no_gradient():
    """A not_converged pixel whose value is far from the fixed point of its masks (here two valid
    pixels, whose Newton steps move the albedo by 27% and 42%) had a derivative off by several
    times, even in sign, against finite differences: such pixels get a zero gradient; converged
    pixels keep theirs."""
    from capture_sim.rig import load_rig
    from capture_sim.simulator import light_transport, simulate
    from capture_sim.synth import lambertian_sphere
    from patterns.families import make_patterns

    rig = load_rig()
    scene = lambertian_sphere(rig, height=32, width=40)
    mask = torch.from_numpy(scene.mask)
    transport = light_transport(scene.olat, scene.mask, dtype=torch.float64)
    points, lights = scene.points(rig.working_distance)[mask].double(), rig.lights(torch.float64)
    patterns = make_patterns("mono_gradient", 4).double().clamp(0.05, 0.95)
    captured = simulate(patterns, transport, rig, exposure=0.003, noise=None, bit_depth=None)
    fixed_noise = 0.002 * torch.sin(torch.arange(captured.captures.numel(), dtype=torch.float64)).reshape(captured.captures.shape)
    captures = (captured.captures + fixed_noise).requires_grad_()
    result = solve_ps(captures, captured.emission.detach(), points, lights, rig.falloff)
    stuck = result.flags["not_converged"] & result.valid
    assert bool(stuck.any())  # this scene has some (two pixels at the time of writing)
    (gradient,) = torch.autograd.grad(result.normal[stuck].sum() + result.albedo[stuck].sum(), captures, allow_unused=True, retain_graph=True)
    assert gradient is None or not bool(gradient.any())
    converged = torch.nonzero(~result.flags["not_converged"] & result.valid).squeeze(1)[:3]
    (gradient,) = torch.autograd.grad(result.normal[converged, 0].sum(), captures)
    assert bool(gradient.any())
    # Not-converged pixels near their fixed point (most of them under a random set) keep theirs.
    from capture_sim.synth import synthesize_scene

    scene = synthesize_scene("blob", "regions", rig, 48, 57, seed=3)
    transport = light_transport(scene.olat, scene.mask, dtype=torch.float64)
    points = scene.points(rig.working_distance)[torch.from_numpy(scene.mask)].double()
    captured = simulate(make_patterns("tri_random", 4).double(), transport, rig, exposure="auto", noise=None, bit_depth=None)
    captures = captured.captures.clone().requires_grad_()
    result = solve_ps(captures, captured.emission.detach(), points, lights, rig.falloff)
    slow = torch.nonzero(result.flags["not_converged"] & result.valid).squeeze(1)
    kept = [bool(torch.autograd.grad(result.normal[pixel, 0], captures, retain_graph=True)[0].any()) for pixel in slow[:10].tolist()]
    assert sum(kept) >= len(kept) // 2 > 0, kept


@pytest.mark.parametrize(
    "config_class,settings,message",
    [
        ("PSConfig", {"max_shadow_iterations": 0}, "max_shadow_iterations >= 1"),
        ("PSConfig", {"max_alternations": 2.5}, "must be a whole number"),
        ("PSConfig", {"line_search_steps": True}, "must be a whole number"),
        ("PSConfig", {"damping": "1e-3"}, "must be a number"),
        ("PSConfig", {"tolerance_deg": math.nan}, "must be a number"),
        ("WoodhamConfig", {"saturation_threshold": math.nan}, "must be a number"),
        ("WoodhamConfig", {"dark_threshold": 0.5, "saturation_threshold": 0.4}, "dark_threshold < saturation_threshold"),
        ("WoodhamConfig", {"min_distance": 10.0}, "min_distance must lie in"),
        ("WoodhamConfig", {"max_shadow_iterations": 0}, "max_shadow_iterations >= 1"),
        ("UnrolledPSConfig", {"saturation_threshold": 0.0}, "saturation_threshold must lie in (0, 1]"),
        ("UnrolledPSConfig", {"alternations": 1.5}, "must be a whole number"),
    ],
)
def test_solver_configs_refuse_bad_settings(config_class, settings, message):
    """Settings that used to switch saturation handling off, skip the fit, or fail inside the solve."""
    from reconstruct.unrolled_ps import UnrolledPSConfig
    from reconstruct.woodham import WoodhamConfig

    classes = {"PSConfig": PSConfig, "WoodhamConfig": WoodhamConfig, "UnrolledPSConfig": UnrolledPSConfig}
    with pytest.raises(InputError, match=re.escape(message)):
        classes[config_class](**settings)
    if config_class != "UnrolledPSConfig":  # keyword-only: a positional value cannot land on another field
        with pytest.raises(TypeError):
            classes[config_class](1e-9, 20)


def test_complex_inputs_are_refused():
    captures = torch.zeros(2, 1, 3, dtype=torch.complex64)
    with pytest.raises(InputError, match="expected real numbers"):
        solve_ps(captures, torch.ones(2, 1, 3), torch.tensor([[0.0, 0.0, 0.5]]), torch.tensor([[0.0, 0.0, 0.0]]), Falloff())


def test_exactly_determined_pixels_are_those_of_three_grey_patterns():
    """Three usable captures a channel under grey patterns (channel gains, a backlit unlit
    channel and float16 rounding allowed) make every mask fit; colour patterns, four captures,
    or channels left with different patterns after saturation do not."""
    from reconstruct.lighting import LightField, lighting_matrix
    from reconstruct.photometric_stereo import PatternEvaluator

    generator = torch.Generator().manual_seed(3)
    lights = torch.tensor([[x, y, 0.0] for x in (-0.3, 0.0, 0.3) for y in (-0.2, 0.2)])
    points = torch.tensor([[0.01 * i, 0.0, 0.5] for i in range(4)])
    field = LightField(points, lights, Falloff(), 1e-3, 64)

    def exact(grey, gains=(1.0, 0.7, 0.45), weight=None, dtype=torch.float32):
        emission = (grey[..., None] * torch.tensor(gains)).to(dtype).float()  # (M, K, 3)
        count = emission.shape[0]
        weight = torch.ones(count, 3, len(points)) if weight is None else weight
        evaluator = PatternEvaluator(field, lighting_matrix(emission, lights), torch.rand(count, 3, len(points), generator=generator), weight, torch.ones(len(points)))
        return evaluator.exactly_determined().tolist()

    grey = torch.rand(3, len(lights), generator=generator)
    assert exact(grey) == [True] * 4
    assert exact(grey, dtype=torch.float16) == [True] * 4  # rounded gains: still grey
    unlit_blue = torch.cat([grey[..., None].expand(-1, -1, 2), torch.full((3, len(lights), 1), 0.02)], dim=2)  # backlight only
    evaluator = PatternEvaluator(field, lighting_matrix(unlit_blue, lights), torch.rand(3, 3, len(points), generator=generator), torch.ones(3, 3, len(points)), torch.ones(len(points)))
    assert evaluator.exactly_determined().tolist() == [True] * 4
    assert exact(torch.rand(4, len(lights), generator=generator)) == [False] * 4  # four captures: a wrong mask shows
    colour = torch.rand(3, len(lights), 3, generator=generator)
    evaluator = PatternEvaluator(field, lighting_matrix(colour, lights), torch.rand(3, 3, len(points), generator=generator), torch.ones(3, 3, len(points)), torch.ones(len(points)))
    assert evaluator.exactly_determined().tolist() == [False] * 4
    # Four grey patterns, pattern c saturated in channel c: three usable each, but different ones.
    four = torch.rand(4, len(lights), generator=generator)
    weight = torch.ones(4, 3, len(points))
    for channel in range(3):
        weight[channel, channel] = 0.0
    assert exact(four, weight=weight) == [False] * 4
    weight[:3] = 1.0
    weight[3] = 0.0  # the same pattern lost in every channel: three grey patterns again
    assert exact(four, weight=weight) == [True] * 4
