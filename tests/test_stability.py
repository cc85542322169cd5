"""Degenerate inputs: outputs and gradients stay finite, and the affected pixels are flagged."""
import math

import pytest
import torch

from capture_sim.rig import Falloff
from reconstruct.metrics import angular_error_deg
from reconstruct.photometric_stereo import FLAG_NAMES, PSConfig, solve_ps
from reconstruct.woodham import solve_woodham, solve_woodham_olat
from tests.reconstruct_scenes import emission_of, load_patterns, sphere_scene

DEFAULT_NOISE = dict(shot=1e-4, read_std=5e-4)


@pytest.fixture(scope="module")
def problem():
    """Pixels of a small sphere with mono-gradient captures (noise-free, below saturation)."""
    scene = sphere_scene(16, 20)
    inside = scene.mask.reshape(-1)
    points = scene.points.reshape(-1, 3)[inside]
    olat = scene.olat.reshape(scene.olat.shape[0], -1, 3)[:, inside]
    emission = emission_of(scene, load_patterns("initial_mono_gradient"))
    radiance = torch.einsum("mkc,knc->mnc", emission, olat)
    exposure = 0.9 / float(radiance.max())
    return dict(scene=scene, points=points, olat=olat, captures=radiance * exposure, emission=emission * exposure)


def _solve_with_gradients(captures, emission, points, lights):
    """Solve, backpropagate the sum of all outputs, check that everything is finite."""
    captures = captures.clone().requires_grad_(True)
    emission = emission.clone().requires_grad_(True)
    result = solve_ps(captures, emission, points, lights, Falloff())
    (result.normal.sum() + result.albedo.sum()).backward()
    for name, value in (("normal", result.normal), ("albedo", result.albedo), ("condition", result.condition), ("residual", result.residual),
                        ("d/dcaptures", captures.grad), ("d/demission", emission.grad)):
        assert torch.isfinite(value).all(), name
    assert set(result.flags) == set(FLAG_NAMES)
    assert (result.normal[~result.valid] == torch.tensor([0.0, 0.0, -1.0], dtype=result.normal.dtype)).all()
    assert (result.albedo[~result.valid] == 0).all()
    return result


def test_half_precision_inputs_are_solved_in_float32(problem):
    result = solve_ps(problem["captures"].half(), problem["emission"].half(), problem["points"], problem["scene"].lights, Falloff())
    assert result.normal.dtype == torch.float32 and torch.isfinite(result.normal).all() and result.valid.all()


def test_clean_problem_is_valid(problem):
    result = _solve_with_gradients(problem["captures"], problem["emission"], problem["points"], problem["scene"].lights)
    assert result.valid.all()


def test_zero_albedo_pixels(problem):
    olat = problem["olat"].clone()
    olat[:, :10] = 0.0
    captures = torch.einsum("mkc,knc->mnc", problem["emission"], olat)
    result = _solve_with_gradients(captures, problem["emission"], problem["points"], problem["scene"].lights)
    assert result.flags["dark"][:10].all() and not result.valid[:10].any()
    assert result.valid[10:].all()


def test_saturated_pixels_drop_their_equations(problem):
    captures = (problem["captures"] * 3.0).clamp(max=1.0)
    result = _solve_with_gradients(captures, problem["emission"], problem["points"], problem["scene"].lights)
    saturated = (captures >= 0.999).any(dim=(0, 2))
    assert torch.equal(result.flags["saturated"], saturated) and saturated.any()
    # Pixels with all equations saturated cannot be solved; the rest still can.
    fully = (captures >= 0.999).all(dim=0).all(dim=-1)
    assert not result.valid[fully].any()


@pytest.mark.parametrize("case", ["single_pattern", "identical_patterns", "all_black"])
def test_rank_deficient_pattern_sets_are_ill_conditioned(problem, case):
    captures, emission = problem["captures"], problem["emission"]
    if case == "single_pattern":
        captures, emission = captures[:1], emission[:1]
    elif case == "identical_patterns":
        captures, emission = captures[[0, 0]], emission[[0, 0]]
    else:
        emission = torch.zeros_like(emission)
        captures = 1e-3 * torch.rand(captures.shape, generator=torch.Generator().manual_seed(0), dtype=captures.dtype)
    result = _solve_with_gradients(captures, emission, problem["points"], problem["scene"].lights)
    assert result.flags["ill_conditioned"].all() and not result.valid.any()


def test_single_colour_pattern_is_ill_conditioned(problem):
    # Three colour channels of one pattern: three equations for five unknowns.
    patterns = load_patterns("initial_tri_complementary")[:1]
    emission = emission_of(problem["scene"], patterns)
    captures = torch.einsum("mkc,knc->mnc", emission, problem["olat"])
    result = _solve_with_gradients(captures / captures.max() * 0.9, emission / captures.max() * 0.9, problem["points"], problem["scene"].lights)
    assert result.flags["ill_conditioned"].all()


def test_pixels_that_zero_captures_leave_underdetermined_are_ill_conditioned():
    # Four corner superpixels, nothing else lit (off level 0, no backlight). A pixel that two
    # corners reach fits a whole family of normals exactly: its zero captures bound the normal
    # from one side only (a corner behind the tangent plane, or on it), yet counting them gave
    # condition numbers near 4 and valid normals up to 40 deg off.
    scene = sphere_scene(40, 48)
    corners = torch.tensor([0, 15, 128, 143])
    emission = torch.zeros(4, scene.lights.shape[0], 3, dtype=torch.float64)
    emission[torch.arange(4), corners] = 1.0
    inside = scene.mask.reshape(-1)
    points, truth = scene.points.reshape(-1, 3)[inside], scene.normal.reshape(-1, 3)[inside]
    radiance = torch.einsum("mkc,knc->mnc", emission, scene.olat.reshape(scene.olat.shape[0], -1, 3)[:, inside])
    captures, emission = radiance * (0.9 / float(radiance.max())), emission * (0.9 / float(radiance.max()))
    reached = (((scene.lights[corners][None] - points[:, None]) * truth[:, None]).sum(-1) > 0).sum(1)
    assert (reached == 2).sum() >= 10 and (reached >= 3).sum() >= 100
    for solver in (solve_ps, solve_woodham):
        result = solver(captures, emission, points, scene.lights, Falloff())
        assert result.flags["ill_conditioned"][reached == 2].all() and not result.valid[reached <= 2].any(), solver.__name__
        error = angular_error_deg(result.normal, truth)
        assert result.valid[reached >= 3].all() and float(error[reached >= 3].max()) < 0.1, solver.__name__


def test_zero_captures_of_a_backlit_display_still_count(monkeypatch):
    # Every superpixel emits (backlight): noise clips dim equations to 0 at kinks, and leaving
    # them out of the condition flagged good estimates (7 of the blob's pixels here, 5 deg median
    # error on the demo's scenes); the flags stay those of every equation.
    from capture_sim.rig import load_rig
    from patterns.families import make_patterns
    from reconstruct.photometric_stereo import PatternEvaluator
    from train.capture import capture_scene
    from train.scene_pixels import scene_pixels
    from train.scene_sets import default_split

    rig = load_rig()
    blob = next(scene for scene in default_split("test", rig, (48, 58), 0) if scene.name.endswith("blob-regions"))
    pixels = scene_pixels(blob, rig, require_normals=True)
    with torch.no_grad():
        capture = capture_scene(pixels, make_patterns("tri_complementary", 2).float(), 1.0, "auto", torch.Generator().manual_seed(0))
    assert (capture.captures == 0).any()
    result = solve_ps(capture.captures, capture.emission, pixels.points, pixels.lights(), rig.falloff)
    monkeypatch.setattr(PatternEvaluator, "lit_condition", lambda self, normal, albedo, condition, kink_tolerance_deg: condition)
    every_equation = solve_ps(capture.captures, capture.emission, pixels.points, pixels.lights(), rig.falloff)
    assert torch.equal(result.condition, every_equation.condition) and torch.equal(result.valid, every_equation.valid)


def _grazing_plane(tilt_deg: float, sideways: tuple, patterns: str):
    """Points of a plane through (0, 0, 0.5) whose normal is tilted ``tilt_deg`` from the optical
    axis towards ``sideways`` (x, y), its true normal and noise-free captures."""
    scene = sphere_scene(16, 20)
    tilt = math.radians(tilt_deg)
    normal = torch.tensor([sideways[0] * math.sin(tilt), sideways[1] * math.sin(tilt), -math.cos(tilt)], dtype=torch.float64)
    rays = scene.points / scene.points[..., 2:]
    depth = (0.5 * normal[2]) / (rays @ normal)
    points = (depth[..., None] * rays).reshape(-1, 3)
    points = points[(points[:, 2] > 0.3) & (points[:, 2] < 0.8)]
    offset = scene.lights[:, None] - points[None]
    distance = offset.norm(dim=-1)
    shading = ((offset / distance[..., None]) @ normal).clamp_min(0) / distance**2 * 0.2
    emission = emission_of(scene, load_patterns(patterns))
    captures = torch.einsum("mkc,kn->mnc", emission, shading)
    scale = 0.9 / float(captures.max())
    return points, normal, captures * scale, emission * scale, scene.lights


def test_grazing_normals():
    points, normal, captures, emission, lights = _grazing_plane(86.0, (1.0, 0.0), "initial_mono_gradient")
    result = _solve_with_gradients(captures, emission, points, lights)
    view = -points / points.norm(dim=-1, keepdim=True)
    facing = (result.normal * view).sum(-1)
    assert (facing[result.valid] > 0).all()
    assert (result.flags["grazing"] == (result.valid & (facing < PSConfig().grazing_cos))).all()
    truly_grazing = (normal * view).sum(-1) < 0.09  # margin for the estimate's rounding
    assert truly_grazing.any() and result.flags["grazing"][truly_grazing & result.valid].all()


def test_wrong_grazing_solutions_are_flagged():
    # Noise-free, and yet the shadow search settles on normals 80+ deg off for some of these
    # pixels: nearly every superpixel is shadowed. They must not pass as good estimates.
    points, normal, captures, emission, lights = _grazing_plane(88.0, (0.0, 1.0), "initial_tri_random_4")
    result = _solve_with_gradients(captures, emission, points, lights)
    wrong = result.valid & (angular_error_deg(result.normal.detach(), normal.expand_as(result.normal)) > 5)
    assert wrong.any(), "the case no longer exercises a wrong solution"
    assert (result.flags["poor_fit"] | result.flags["grazing"])[wrong].all()


def test_ten_times_the_default_noise(problem):
    generator = torch.Generator().manual_seed(1)
    captures = problem["captures"]
    shot, read = DEFAULT_NOISE["shot"] * 10, DEFAULT_NOISE["read_std"] * math.sqrt(10)
    noisy = captures + torch.sqrt(shot * captures + read**2) * torch.randn(captures.shape, generator=generator, dtype=captures.dtype)
    result = _solve_with_gradients(noisy.clamp(0.0, 1.0), problem["emission"], problem["points"], problem["scene"].lights)
    assert result.valid.float().mean() > 0.8


def test_points_behind_the_display_or_on_a_light(problem):
    lights = problem["scene"].lights
    points = problem["points"].clone()
    points[:4, 2] = -0.1  # behind the camera and the display
    points[4, 2] = 0.0
    points[5] = lights[70]  # exactly on a superpixel
    points[6] = lights[3] + torch.tensor([0.0, 0.0, 1e-5], dtype=points.dtype)
    result = _solve_with_gradients(problem["captures"], problem["emission"], points, lights)
    assert result.flags["bad_geometry"][:7].all() and not result.valid[:7].any()
    assert not result.flags["bad_geometry"][7:].any()


def test_woodham_degenerate_inputs_stay_finite(problem):
    lights, points = problem["scene"].lights, problem["points"].clone()
    points[0] = lights[10]
    olat = problem["olat"].clone()
    olat[:, 1:4] = 0.0
    olat[:, 4] = 5.0
    result = solve_woodham_olat(olat, points, lights, Falloff())
    assert all(torch.isfinite(value).all() for value in (result.normal, result.albedo, result.condition))
    assert result.flags["bad_geometry"][0] and result.flags["dark"][1:4].all() and result.flags["saturated"][4]
    assert not result.valid[:5].any()
    black = solve_woodham(problem["captures"][:3], torch.zeros_like(problem["emission"][:3]), points, lights, Falloff())
    assert torch.isfinite(black.normal).all() and not black.valid.any()


def test_bad_inputs_and_background_nan_from_the_review(problem, monkeypatch):
    """Inputs found to raise raw Python errors, and NaN outside the mask of image solves."""
    from capture_sim.errors import InputError
    from reconstruct.photometric_stereo import solve_ps_image
    from reconstruct.relight import relighting_metrics
    from reconstruct.unrolled_ps import UnrolledPSConfig, light_reach
    from reconstruct.woodham import solve_woodham_image

    scene, lights = problem["scene"], problem["scene"].lights
    with pytest.raises(InputError):
        solve_ps(problem["captures"][:0], problem["emission"][:0], problem["points"], lights, Falloff())
    with pytest.raises(InputError):
        solve_woodham_olat(problem["olat"].numpy(), problem["points"], lights, Falloff(), 1.0)
    for bad_index in (torch.zeros(0, dtype=torch.long), torch.tensor([99]), torch.tensor([1.0])):
        values = torch.zeros(2, bad_index.numel(), 3)
        with pytest.raises(InputError):
            relighting_metrics(values, values, bad_index, 4, 4)
    with pytest.raises(InputError):
        UnrolledPSConfig(chunk_pixels=0)
    with pytest.raises(InputError):
        UnrolledPSConfig(shadow_iterations=0)
    # The reference rig's fitted falloff has a pole inside the working range: refused, not used.
    with pytest.raises(InputError):
        light_reach(problem["points"], lights, Falloff("fitted", -5.4580, 14.7449))
    # NaN depth and captures outside the mask are never read.
    captures = torch.einsum("mkc,khwc->mhwc", problem["emission"], scene.olat)
    points = scene.points.clone()
    outside = ~scene.mask
    captures[:, outside] = float("nan")
    points[outside] = float("nan")
    result = solve_ps_image(captures, problem["emission"], points, scene.mask, lights, Falloff())
    assert result.valid[scene.mask].any() and not result.valid[outside].any()
    assert torch.isfinite(result.normal).all()
    woodham = solve_woodham_image(captures, problem["emission"], points, scene.mask, lights, Falloff())
    assert torch.isfinite(woodham.normal).all()
    # Inside the mask, NaN is refused wherever it is: the masked pixels are checked in blocks.
    from reconstruct import photometric_stereo

    last = torch.nonzero(scene.mask.reshape(-1)).max()
    captures.reshape(captures.shape[0], -1, 3)[1, last, 2] = float("nan")
    with monkeypatch.context() as patch:
        patch.setattr(photometric_stereo, "CHECK_PIXELS", 3)
        for solve in (solve_ps_image, solve_woodham_image):
            with pytest.raises(InputError, match="captures"):
                solve(captures, problem["emission"], points, scene.mask, lights, Falloff())


@pytest.mark.parametrize("factor", [1e-25, 1e20])
def test_emission_in_any_units_gives_the_same_normals(problem, factor):
    """Radiance in other units (an OLAT stack scaled by 1e-25 or 1e20): the same normals, the albedo
    in the new units; squared lighting terms used to under- or overflow float32."""
    from reconstruct.unrolled_ps import solve_ps_unrolled

    captures, emission, points = (problem[key].float() for key in ("captures", "emission", "points"))
    lights = problem["scene"].lights.float()  # float32: where 1e20 squared overflows
    base = solve_ps(captures, emission, points, lights, Falloff())
    scaled_emission = (emission * factor).requires_grad_()
    scaled = solve_ps(captures, scaled_emission, points, lights, Falloff())
    scaled.normal.sum().backward()  # (d albedo / d emission ~ 1 / emission^2 is past float32 at 1e-25)
    assert torch.isfinite(scaled_emission.grad).all()
    assert torch.equal(scaled.valid, base.valid) and base.valid.all()
    assert (scaled.normal - base.normal).abs().max() < 5e-4  # 0.03 deg: float32 rounding of the scaled emission
    assert torch.allclose(scaled.albedo * factor, base.albedo, rtol=1e-3)
    normal, albedo = solve_ps_unrolled(captures, emission, points, lights, Falloff())
    normal_scaled, albedo_scaled = solve_ps_unrolled(captures, emission * factor, points, lights, Falloff())
    assert (normal_scaled - normal).abs().max() < 5e-4 and torch.allclose(albedo_scaled * factor, albedo, rtol=1e-3)
    olat = (problem["olat"] * 0.9 / float(problem["olat"].max())).float()
    woodham = solve_woodham_olat(olat, points, lights, Falloff())
    woodham_scaled = solve_woodham_olat(olat, points, lights, Falloff(), exposure=factor)
    assert torch.equal(woodham_scaled.valid, woodham.valid) and (woodham_scaled.normal - woodham.normal).abs().max() < 5e-4


def test_edge_cases_from_the_numerics_review(problem):
    """Empty pixel sets stay on the graph, subnormal emission gives finite albedo, out-of-range
    settings are refused, and a point at the camera centre still gets a unit normal."""
    from capture_sim.errors import InputError
    from reconstruct.unrolled_ps import UnrolledPSConfig, solve_ps_unrolled
    from reconstruct.woodham import WoodhamConfig

    captures, emission, points = (problem[key].float() for key in ("captures", "emission", "points"))
    lights = problem["scene"].lights.float()
    empty_captures = captures[:, :0].clone().requires_grad_()
    empty = solve_ps(empty_captures, emission, points[:0], lights, Falloff())
    (empty.normal.sum() + empty.albedo.sum()).backward()  # raised "does not require grad" before
    assert empty.normal.shape == (0, 3) and empty_captures.grad.shape == empty_captures.shape
    subnormal = emission * 1e-41  # below float32's smallest normal number: albedo ~1e41 overflows
    assert torch.isfinite(solve_ps(captures, subnormal, points, lights, Falloff()).albedo).all()
    assert torch.isfinite(solve_ps_unrolled(captures, subnormal, points, lights, Falloff())[1]).all()
    olat = problem["olat"].float()
    assert torch.isfinite(solve_woodham_olat(olat, points, lights, Falloff(), exposure=1e-45).albedo).all()
    for exposure in (1e39, "bright", math.nan):
        with pytest.raises(InputError, match="exposure"):
            solve_woodham_olat(olat, points, lights, Falloff(), exposure=exposure)
    for make in (lambda: WoodhamConfig(damping=2.0), lambda: WoodhamConfig(damping=math.inf), lambda: UnrolledPSConfig(damping=1e30)):
        with pytest.raises(InputError, match="damping"):
            make()
    with pytest.raises(InputError):
        solve_ps_unrolled(captures, emission, points, lights[:, :2], Falloff())
    with pytest.raises(InputError):
        solve_ps_unrolled(captures.numpy(), emission, points, lights, Falloff())
    at_centre = points.clone()
    at_centre[0] = 0.0
    normal, _ = solve_ps_unrolled(captures, emission, at_centre, lights, Falloff())
    assert torch.allclose(normal.norm(dim=1), torch.ones(normal.shape[0]), atol=1e-5)


def test_edge_cases_from_the_api_fuzz(problem):
    """Found by fuzzing the public functions: a black backlight-free display emits nothing (its
    gradient floor emitted tiny ** gamma, which auto exposure lifted to 0.9 of full scale); integer
    transports, negative radiance, non-float or non-unit render inputs, overflowing images and bad
    SSIM windows are refused with one clear error; the unrolled solver's empty result reaches
    both inputs' graphs."""
    from capture_sim.display import display_emission
    from capture_sim.errors import InputError
    from capture_sim.render import render_olat
    from capture_sim.simulator import auto_exposure, light_transport
    from reconstruct.metrics import psnr, ssim
    from reconstruct.unrolled_ps import solve_ps_unrolled

    black = torch.zeros(1, 2, 3, 3, requires_grad=True)
    emitted = display_emission(black, torch.zeros(2, 3), gamma=1.0)
    assert float(emitted.detach().abs().max()) == 0.0
    emitted.sum().backward()
    assert torch.isfinite(black.grad).all()
    assert auto_exposure(emitted.detach()) == 1.0
    with pytest.raises(InputError, match="floating"):
        light_transport(torch.rand(4, 2, 3, 3), dtype=torch.int32)
    with pytest.raises(InputError, match="negative"):
        light_transport(-torch.rand(4, 2, 3, 3))
    with pytest.raises(InputError, match="negative"):
        auto_exposure(-torch.rand(2, 10, 3))
    points, normals, lights = torch.tensor([[0.0, 0.0, 0.5]]), torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.1, 0.0, 0.0]])
    args = (torch.ones(1, 1), torch.full((1, 3), 0.5), torch.zeros(1), torch.ones(1))
    render_olat(points, normals, lights, *args)
    with pytest.raises(InputError, match="floating"):
        render_olat(points.int(), normals, lights, *args)
    with pytest.raises(InputError, match="unit vectors"):
        render_olat(points, normals * 2, lights, *args)
    image, mask = torch.rand(2, 8, 9, 3, dtype=torch.float64), torch.ones(8, 9, dtype=torch.bool)
    for metric in (psnr, ssim):
        with pytest.raises(InputError, match="full-scale"):
            metric(image * 1e200, image, mask)
    for window in (3.0, "11", True):
        with pytest.raises(InputError, match="window_size"):
            ssim(image, image, mask, window_size=window)
    assert ssim(image, image, mask, window_size=__import__("numpy").int64(3)) == pytest.approx(1.0)
    captures, emission, points = (problem[key].float() for key in ("captures", "emission", "points"))
    emission = emission.clone().requires_grad_()
    normal, albedo = solve_ps_unrolled(captures[:, :0], emission, points[:0], problem["scene"].lights.float(), Falloff())
    (normal.sum() + albedo.sum()).backward()
    assert emission.grad is not None and float(emission.grad.abs().max()) == 0.0
