"""Inverse renderer (reconstruct.basis_render, fit_start, inverse_render), relighting evaluation (reconstruct.relight) and the
`displex invrender` command (train.invrender_command)."""
from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

import reconstruct.basis_render as basis_render
import reconstruct.inverse_render as inverse_render
from capture_sim.errors import InputError
from capture_sim.rig import RIG_DIR, Falloff, load_rig
from capture_sim.render import render_olat
from capture_sim.scene import save_scene
from capture_sim.synth import synthesize_scene
from reconstruct.basis_render import EmissionPlan, render_under_patterns, shading_geometry
from reconstruct.fit_start import (
    InitialEstimate,
    cluster_albedo,
    fill_from_neighbours,
    grid_neighbours,
    initial_estimate,
    into_visible_hemisphere,
    least_squares_albedos,
    olat_least_squares,
)
from reconstruct.inverse_render import FitConfig, InverseRenderResult, fit_inverse_render, search_normals
from reconstruct.relight import (
    olat_emission,
    pooled_psnr,
    relighting_metrics,
    split_lights,
)
from tests.conftest import TOLERANCE
from tests.reconstruct_scenes import sphere_scene

TOL = {"degrees": 1e-2, "psnr_db": 1e-9}


def _random_scene(num_pixels=40, num_basis=3, num_lights=None, dtype=torch.float64, seed=0, rig=None):
    """Points about 0.5 m away with normals facing the camera and random basis BRDFs."""
    generator = torch.Generator().manual_seed(seed)
    rig = rig or load_rig()
    lights = rig.lights(dtype)
    points = torch.randn(num_pixels, 3, generator=generator, dtype=dtype) * 0.03 + torch.tensor([0.0, 0.0, 0.5], dtype=dtype)
    normals = torch.randn(num_pixels, 3, generator=generator, dtype=dtype) * 0.4
    normals[:, 2] = -1.0
    normals = normals / normals.norm(dim=-1, keepdim=True)
    weights = torch.softmax(torch.randn(num_pixels, num_basis, generator=generator, dtype=dtype), -1)
    diffuse = torch.rand(num_basis, 3, generator=generator, dtype=dtype) * 0.8 + 0.1
    specular = torch.rand(num_basis, generator=generator, dtype=dtype) * 0.5 + 0.05
    roughness = torch.rand(num_basis, generator=generator, dtype=dtype) * 0.6 + 0.2
    return points, normals, lights, weights, diffuse, specular, roughness


def _reference_images(points, normals, lights, emission, weights, diffuse, specular, roughness, falloff=Falloff()):
    """Plain broadcast reference: every OLAT image by render_olat, then the sum over lights."""
    diffuse_olat, specular_olat = render_olat(points, normals, lights, weights, diffuse, specular, roughness, falloff)
    return torch.einsum("mkc,knc->mnc", emission, diffuse_olat + specular_olat)


# ----------------------------------------------------------------------------------------------
# render_under_patterns
# ----------------------------------------------------------------------------------------------


def test_render_under_patterns_matches_broadcast_reference():
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene()
    emission = torch.rand(3, lights.shape[0], 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    expected = _reference_images(points, normals, lights, emission, weights, diffuse, specular, roughness)
    images = render_under_patterns(normals, points, lights, emission, weights, diffuse, specular, roughness, Falloff(), chunk_pixels=16)
    assert images.shape == (3, points.shape[0], 3)
    torch.testing.assert_close(images, expected, **TOLERANCE[torch.float64])


def test_render_olat_style_emission_and_lambertian_bases_match_reference():
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene()
    chosen = torch.tensor([7, 0, 100, 55])
    gains = torch.rand(4, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64) + 0.1
    emission = torch.zeros(4, lights.shape[0], 3, dtype=torch.float64)
    emission[torch.arange(4), chosen] = gains
    plan = EmissionPlan(emission)
    assert plan.gain is not None and plan.light_index.tolist() == chosen.tolist()
    expected = _reference_images(points, normals, lights, emission, weights, diffuse, specular, roughness)
    images = render_under_patterns(normals, points, lights, emission, weights, diffuse, specular, roughness, Falloff())
    torch.testing.assert_close(images, expected, **TOLERANCE[torch.float64])
    lambertian = render_under_patterns(normals, points, lights, emission, weights, diffuse, None, roughness, Falloff())
    expected = _reference_images(points, normals, lights, emission, weights, diffuse, torch.zeros_like(specular), roughness)
    torch.testing.assert_close(lambertian, expected, **TOLERANCE[torch.float64])


def test_far_field_equals_rendering_every_pixel_at_the_centroid():
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene()
    emission = torch.rand(2, lights.shape[0], 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    centroid = points.mean(0, keepdim=True).expand_as(points)
    expected = _reference_images(centroid, normals, lights, emission, weights, diffuse, specular, roughness)
    images = render_under_patterns(normals, points, lights, emission, weights, diffuse, specular, roughness, Falloff(), far_field=True)
    torch.testing.assert_close(images, expected, **TOLERANCE[torch.float64])


def test_chunking_does_not_change_values_or_gradients():
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene(num_pixels=23)
    emission = torch.rand(2, lights.shape[0], 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    results = []
    for chunk in (5, 1000):
        leaves = [t.clone().requires_grad_() for t in (normals, weights, diffuse, specular, roughness)]
        images = render_under_patterns(leaves[0], points, lights, emission, leaves[1], leaves[2], leaves[3], leaves[4], Falloff(), chunk_pixels=chunk)
        images.square().sum().backward()
        results.append((images.detach(), [leaf.grad for leaf in leaves]))
    torch.testing.assert_close(results[0][0], results[1][0], **TOLERANCE[torch.float64])
    for first, second in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(first, second, **TOLERANCE[torch.float64])


def test_render_gradcheck_float64(tiny_rig):
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene(num_pixels=4, num_basis=2, rig=tiny_rig)
    emission = torch.rand(2, lights.shape[0], 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64) + 0.1
    inputs = [t.clone().requires_grad_() for t in (normals, emission, weights, diffuse, specular, roughness)]

    def render(n, e, w, d, s, r):
        return render_under_patterns(n, points, lights, e, w, d, s, r, Falloff(), chunk_pixels=3)

    assert torch.autograd.gradcheck(render, inputs)


def test_lobe_sum_gradcheck_across_blocks(monkeypatch):
    monkeypatch.setattr(basis_render, "_LOBE_BLOCK_ROWS", 4)
    generator = torch.Generator().manual_seed(6)
    n_dot_h = torch.rand(9, 5, generator=generator, dtype=torch.float64)
    inputs = [
        torch.rand(9, 5, generator=generator, dtype=torch.float64),  # n . l
        n_dot_h.square(),
        1 - n_dot_h.square(),  # independent inputs for the check; the renderer passes (1 - n.h)(1 + n.h)
        torch.rand(9, 2, generator=generator, dtype=torch.float64),
        torch.rand(2, generator=generator, dtype=torch.float64) * 0.9 + 0.01,  # alpha^2
        torch.rand(2, generator=generator, dtype=torch.float64) * 0.4 + 0.05,
    ]
    assert torch.autograd.gradcheck(basis_render._LobeSum.apply, [t.requires_grad_() for t in inputs])


def test_sharp_lobes_in_float32_match_the_simulator():
    """The renderer's float32 GGX lobe at the fit's lowest roughness agrees with the simulator's
    (capture_sim.brdf) in float64: 1 + n.h^2 (alpha^2 - 1) cancelled near the peak (6% at 0.05)."""
    from capture_sim.brdf import ggx_distribution

    n_dot_h = 1 - torch.logspace(-9, -1, 200, dtype=torch.float64)
    alpha = torch.tensor(0.05**2, dtype=torch.float64)
    ones = torch.ones(200, 1, dtype=torch.float64)
    for dtype in (torch.float32, torch.float64):
        h = n_dot_h.to(dtype)[:, None]
        lobe = basis_render._LobeSum.apply(ones.to(dtype), h * h, (1 - h) * (1 + h), ones.to(dtype), (alpha * alpha).to(dtype)[None],
                                             torch.zeros(1, dtype=dtype))
        # D = a^2 / (pi t^2): the lobe sum is 1 / t^2 here; the truth at the n . h the dtype holds.
        expected = ggx_distribution(h[:, 0].double(), alpha) * math.pi / alpha**2
        assert torch.allclose(lobe[:, 0].double(), expected, rtol=1e-5 if dtype == torch.float32 else 1e-12)


@pytest.mark.parametrize("bad", ["normals_shape", "negative_emission", "nan_normals", "roughness_range", "pixel_mismatch", "falloff"])
def test_render_bad_input_raises(bad):
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene(num_pixels=5)
    emission = torch.rand(2, lights.shape[0], 3, dtype=torch.float64)
    falloff = Falloff("fitted", a=-1.0, b=0.0) if bad == "falloff" else Falloff()  # negative everywhere
    if bad == "normals_shape":
        normals = normals[:, :2]
    elif bad == "negative_emission":
        emission = -emission
    elif bad == "nan_normals":
        normals = normals.clone()
        normals[0, 0] = math.nan
    elif bad == "roughness_range":
        roughness = roughness + 1.0
    elif bad == "pixel_mismatch":
        points = points[:3]
    with pytest.raises(InputError):
        render_under_patterns(normals, points, lights, emission, weights, diffuse, specular, roughness, falloff)


def test_degenerate_inputs_give_finite_values_and_gradients():
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene(num_pixels=6)
    normals = normals.clone()
    normals[0] = 0.0  # zero vector
    normals[1] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # grazing: n . v = 0
    normals[2] = -normals[2]  # facing away from the camera
    view = -points[3] / points[3].norm()
    normals[3] = view  # mirror configuration for lights near the camera
    lights = lights.clone()
    lights[0] = points[4]  # a superpixel on the surface point
    roughness = torch.tensor([0.0, 1.0, 0.3], dtype=torch.float64)  # alpha clamped, not zero
    emission = torch.rand(2, lights.shape[0], 3, dtype=torch.float64)
    leaves = [t.clone().requires_grad_() for t in (normals, weights, diffuse, specular, roughness)]
    images = render_under_patterns(leaves[0], points, lights, emission, *leaves[1:], Falloff())
    images.sum().backward()
    assert bool(torch.isfinite(images).all())
    assert all(bool(torch.isfinite(leaf.grad).all()) for leaf in leaves)
    # Zero pixels: an empty result on the graph; a float32 normal of length 1e20 renders as its unit vector.
    empty = [leaf[:0] if index < 2 else leaf for index, leaf in enumerate(leaves)]
    render_under_patterns(empty[0], points[:0], lights, emission, *empty[1:], Falloff()).sum().backward()
    long_normal = normals[3:4].float() * 1e20
    assert torch.allclose(render_under_patterns(long_normal, points[3:4].float(), lights.float(), emission.float(), weights[3:4].float(),
                                                diffuse.float(), specular.float(), roughness.float(), Falloff()),
                          images[:, 3:4].detach().float(), rtol=1e-4)


# ----------------------------------------------------------------------------------------------
# Initialisation pieces
# ----------------------------------------------------------------------------------------------


def test_grid_neighbours_match_a_plain_loop():
    height, width = 5, 7
    mask = torch.rand(height, width, generator=torch.Generator().manual_seed(7)) > 0.4
    pixel_index = torch.nonzero(mask.reshape(-1)).squeeze(1)
    neighbours = grid_neighbours(pixel_index, height, width)
    position = {int(p): i for i, p in enumerate(pixel_index)}
    for i, flat in enumerate(pixel_index.tolist()):
        row, col = divmod(flat, width)
        right = position.get(flat + 1, -1) if col + 1 < width else -1
        down = position.get(flat + width, -1) if row + 1 < height else -1
        assert neighbours[i].tolist() == [right, down]


def test_fill_from_neighbours_grows_known_values_and_leaves_unreachable_pixels():
    height, width = 3, 5
    pixel_index = torch.tensor([0, 1, 2, 5, 6, 7, 4, 14])  # two blocks; 4 and 14 are isolated pixels
    values = torch.zeros(8, 1)
    values[0] = 2.0
    values[2] = 4.0
    known = torch.zeros(8, dtype=torch.bool)
    known[[0, 2]] = True
    filled, reached = fill_from_neighbours(values, known, pixel_index, height, width)
    assert reached[:6].all() and not reached[6:].any()
    assert filled[1, 0] == pytest.approx(3.0)  # between 2 and 4
    assert filled[3, 0] == pytest.approx(2.0) and filled[5, 0] == pytest.approx(4.0)
    assert filled[4, 0] == pytest.approx(3.0)  # below pixel 1, filled in the second round


def test_into_visible_hemisphere_keeps_good_normals_and_tilts_others():
    view = torch.tensor([[0.0, 0.0, -1.0]]).expand(3, 3)
    normals = torch.tensor([[0.0, 0.6, -0.8], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    tilted = into_visible_hemisphere(normals, view, 0.2)
    torch.testing.assert_close(tilted[0], normals[0])
    assert float((tilted[1] * view[1]).sum()) == pytest.approx(0.2, abs=1e-6) and float(tilted[1, 0]) > 0
    torch.testing.assert_close(tilted[2], view[2])  # straight away from the camera: no azimuth to keep
    torch.testing.assert_close(tilted.norm(dim=-1), torch.ones(3))


def test_olat_least_squares_recovers_a_lambertian_sphere():
    scene = sphere_scene(24, 30)
    mask = scene.mask.reshape(-1)
    stack = scene.olat.reshape(scene.olat.shape[0], -1, 3)[:, mask]
    exposure = 0.9 / float(stack.max())
    lights = torch.arange(0, stack.shape[0], 2)
    emission = olat_emission(lights, stack.shape[0], exposure, torch.float64)
    normal, albedo, valid = olat_least_squares((stack[lights] * exposure), EmissionPlan(emission), scene.points.reshape(-1, 3)[mask],
                                               scene.lights, Falloff())
    truth = scene.normal.reshape(-1, 3)[mask]
    angle = torch.rad2deg(torch.acos((normal * truth).sum(-1).clamp(-1, 1)))
    assert bool(valid.all())
    assert float(angle.max()) < TOL["degrees"]
    torch.testing.assert_close(albedo, scene.albedo.reshape(-1, 3)[mask], rtol=1e-6, atol=1e-9)


def test_olat_least_squares_handles_a_pure_red_object_and_bad_inputs_are_refused():
    """An object dark in two channels is still lit in the third; degenerate fits raise InputError."""
    scene = sphere_scene(24, 30)
    mask = scene.mask.reshape(-1)
    red = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    stack = scene.olat.reshape(scene.olat.shape[0], -1, 3)[:, mask] * red
    exposure = 0.9 / float(stack.max())
    lights = torch.arange(0, stack.shape[0], 2)
    emission = olat_emission(lights, stack.shape[0], exposure, torch.float64)
    points = scene.points.reshape(-1, 3)[mask]
    normal, albedo, valid = olat_least_squares(stack[lights] * exposure, EmissionPlan(emission), points, scene.lights, Falloff())
    truth = scene.normal.reshape(-1, 3)[mask]
    assert bool(valid.all())
    assert float(torch.rad2deg(torch.acos((normal * truth).sum(-1).clamp(-1, 1))).max()) < TOL["degrees"]
    assert float(albedo[:, 1:].abs().max()) == 0.0
    captures = (stack[lights] * exposure).float()
    index = torch.nonzero(mask).squeeze(1)
    for bad_emission, bad_index in ((torch.zeros_like(emission), index), (emission, index.double()), (emission, torch.cat([index[:1], index[:-1]]))):
        with pytest.raises(InputError):
            fit_inverse_render(captures, bad_emission.float(), points.float(), scene.lights.float(), Falloff(), bad_index, 24, 30)
    # Arrays where tensors go: one line, not an AttributeError from deep inside.
    with pytest.raises(InputError, match="must be torch tensors"):
        fit_inverse_render(captures, emission.float().numpy(), points.float(), scene.lights.float(), Falloff(), index, 24, 30)
    with pytest.raises(InputError, match=re.escape("falloff fitted (a=-5.458, b=14.7449) is not positive")):
        olat_least_squares(stack[lights] * exposure, EmissionPlan(emission), points, scene.lights, Falloff("fitted", a=-5.4580, b=14.7449))


def test_shading_geometry_of_half_precision_points_next_to_a_light_is_finite():
    """1 / d^2 at 2 mm overflows float16: the factor is computed wider and kept at float16's largest."""
    lights = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0]])
    points = torch.tensor([[0.0, 0.0, 0.002], [0.0, 0.0, 0.5]], dtype=torch.float16)
    geometry = shading_geometry(points, lights.half(), Falloff())
    assert torch.isfinite(geometry.falloff).all() and float(geometry.falloff[0, 0]) == torch.finfo(torch.float16).max


def test_cluster_albedo_separates_hues_and_is_seeded():
    generator = torch.Generator().manual_seed(8)
    colours = torch.tensor([[0.8, 0.2, 0.2], [0.2, 0.7, 0.3], [0.2, 0.3, 0.8]])
    truth = torch.randint(0, 3, (300,), generator=generator)
    brightness = torch.rand(300, 1, generator=generator) * 0.8 + 0.4  # hue and saturation ignore it
    albedo = colours[truth] * brightness
    valid = torch.ones(300, dtype=torch.bool)
    labels, centres = cluster_albedo(albedo, valid, 3, seed=1)
    again, _ = cluster_albedo(albedo, valid, 3, seed=1)
    assert torch.equal(labels, again)
    for j in range(3):  # each true colour maps to exactly one cluster
        assert len(set(labels[truth == j].tolist())) == 1
    assert len(set(labels.tolist())) == 3 and centres.shape == (3, 3)


def test_cluster_albedo_keeps_the_tightest_of_its_restarts():
    from reconstruct.fit_start import hue_saturation_features

    generator = torch.Generator().manual_seed(9)
    albedo = torch.rand(400, 3, generator=generator) * 0.8 + 0.1  # no clear clusters: k-means++ starts matter
    valid = torch.ones(400, dtype=torch.bool)
    features = torch.as_tensor(hue_saturation_features(albedo))

    def distortion(labels):
        centres = torch.stack([features[labels == j].mean(0) for j in range(5)])
        return float(((features - centres[labels]) ** 2).sum())

    single = [distortion(cluster_albedo(albedo, valid, 5, seed=seed, restarts=1)[0]) for seed in range(8)]
    assert distortion(cluster_albedo(albedo, valid, 5, seed=0, restarts=8)[0]) <= min(single) + 1e-9


def test_least_squares_albedos_are_exact_for_true_geometry():
    points, normals, lights, _, diffuse, specular, _ = _random_scene(num_pixels=60, num_basis=2, dtype=torch.float32)
    labels = torch.arange(60) % 2
    weights = torch.nn.functional.one_hot(labels, 2).float()
    emission = torch.rand(3, lights.shape[0], 3, generator=torch.Generator().manual_seed(9))
    roughness = torch.full((2,), 0.5)
    captures = render_under_patterns(normals, points, lights, emission, weights, diffuse, specular, roughness, Falloff())
    emission = emission * (0.9 / float(captures.max()))  # below saturation: every equation counts
    captures = captures * (0.9 / float(captures.max()))
    found_diffuse, found_specular, solved = least_squares_albedos(captures, emission, points, lights, Falloff(), normals, labels, 2, True, 0.5)
    torch.testing.assert_close(found_diffuse, diffuse, rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(found_specular, specular, rtol=1e-3, atol=1e-4)
    assert solved.tolist() == [True, True]
    # A cluster without pixels is reported unsolved, with finite (meaningless) albedos.
    found_diffuse, found_specular, solved = least_squares_albedos(captures, emission, points, lights, Falloff(), normals,
                                                                  torch.zeros_like(labels), 3, True, 0.5)
    assert solved.tolist() == [True, False, False]
    assert torch.isfinite(found_diffuse).all() and torch.isfinite(found_specular).all()


def test_normal_search_finds_a_far_start_and_never_worsens():
    points, normals, lights, weights, diffuse, specular, roughness = _random_scene(num_pixels=12, dtype=torch.float32)
    # Gradient-style patterns (ramps along +-x and +-y of the display) constrain normals well.
    span = lights[:, :2] / lights[:, :2].abs().max(0).values
    ramps = torch.stack([1 + span[:, 0], 1 - span[:, 0], 1 + span[:, 1], 1 - span[:, 1]]) / 2
    emission = ramps[:, :, None].expand(-1, -1, 3).contiguous()
    captures = render_under_patterns(normals, points, lights, emission, weights, diffuse, specular, roughness, Falloff())
    emission = emission * (0.9 / float(captures.max()))
    captures = captures * (0.9 / float(captures.max()))
    config = FitConfig(num_basis=3)
    truth = InverseRenderResult(normals, weights, diffuse, specular, roughness, True, False)
    model = inverse_render.BasisModel.from_result(truth, config)
    start = torch.tensor([0.5, -0.5, -0.7071])
    with torch.no_grad():
        model.normal_raw[:6] = start / start.norm()  # 6 pixels start far off; 6 start at the truth
    plan = EmissionPlan(emission)
    geometry = shading_geometry(points, lights[plan.light_index], Falloff())
    pixels_first = captures.permute(1, 0, 2).contiguous()
    saturated = pixels_first >= 0.999
    before = inverse_render.pixel_rmse(model, geometry, plan, pixels_first, saturated)
    changed = search_normals(model, torch.arange(12), geometry, plan, pixels_first, saturated, config)
    after = inverse_render.pixel_rmse(model, geometry, plan, pixels_first, saturated)
    angle = torch.rad2deg(torch.acos((model.normals().detach() * normals).sum(-1).clamp(-1, 1)))
    assert bool(changed[:6].all()) and not bool(changed[6:].any())
    assert bool((after <= before + 1e-7).all())
    # The refinement cap has about 4 degrees between candidates; gradient steps finish the job.
    assert float(angle.max()) < 8.0


def test_fit_config_rejects_bad_settings():
    for bad in (dict(num_basis=0), dict(iterations=-1), dict(normal_lr=0.0), dict(final_lr_fraction=0.0),
                dict(initial_roughness=0.01), dict(normal_search_at=(1.5,)), dict(search_max_fraction=0.0),
                # NaN passes every comparison: it turned the fit's output NaN or its regulariser off
                dict(specular_floor=math.nan), dict(saturation_threshold=math.nan), dict(tv_weight=math.nan),
                dict(specular_floor=-0.1), dict(saturation_threshold=0.0), dict(normal_lr=math.inf), dict(iterations=2.5),
                dict(search_residual_ratio=math.inf)):
        with pytest.raises(InputError):
            FitConfig(**bad)
    from reconstruct.model_selection import SelectionConfig

    for bad in (dict(tolerance_db=math.nan), dict(far_field_tolerance=math.inf), dict(min_improvement_db=-1.0), dict(patience=1.5)):
        with pytest.raises(InputError):
            SelectionConfig(**bad)


# ----------------------------------------------------------------------------------------------
# Fit on small synthetic scenes
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_scene():
    rig = load_rig()
    scene = synthesize_scene("sphere", "svbrdf", rig, 24, 29, seed=2)
    from train.scene_pixels import scene_pixels

    return scene, scene_pixels(scene, rig)


def _olat_fit_data(pixels, light_index=None):
    olat = pixels.transport.matrix.permute(1, 2, 0)
    exposure = float(0.9 / torch.quantile(olat.reshape(-1), 0.999))
    split = split_lights(olat.shape[0])
    index = split.fit if light_index is None else light_index
    return (olat[index] * exposure).clamp(0, 1), olat_emission(index, olat.shape[0], exposure), exposure, split, olat


def test_fit_recovers_small_olat_scene(small_scene):
    scene, pixels = small_scene
    captures, emission, exposure, split, olat = _olat_fit_data(pixels)
    result = fit_inverse_render(captures, emission, pixels.points, pixels.lights(), Falloff(), pixels.transport.pixel_index,
                                scene.height, scene.width, FitConfig(num_basis=3, iterations=120))
    assert result.normal.shape == (pixels.num_pixels, 3) and result.weights.shape == (pixels.num_pixels, 3)
    torch.testing.assert_close(result.weights.sum(1), torch.ones(pixels.num_pixels))
    angle = torch.rad2deg(torch.acos((result.normal * pixels.normal).sum(-1).clamp(-1, 1)))
    assert float(angle.mean()) < 3.0
    relit = result.render(pixels.points, pixels.lights(), olat_emission(split.test, olat.shape[0], exposure), Falloff())
    metrics = relighting_metrics(relit, olat[split.test] * exposure, pixels.transport.pixel_index, scene.height, scene.width)
    assert metrics["psnr"] > 35.0 and 0.9 < metrics["ssim"] <= 1.0
    assert result.rmse_history[-1] < result.rmse_history[0]


def test_warm_start_reproduces_the_result(small_scene):
    scene, pixels = small_scene
    captures, emission, *_ = _olat_fit_data(pixels)
    config = FitConfig(num_basis=2, iterations=20)
    arguments = (captures, emission, pixels.points, pixels.lights(), Falloff(), pixels.transport.pixel_index, scene.height, scene.width)
    first = fit_inverse_render(*arguments, config)
    again = fit_inverse_render(*arguments, FitConfig(num_basis=2, iterations=0), warm_start=first)
    for name in ("normal", "diffuse", "specular", "roughness"):
        torch.testing.assert_close(getattr(again, name), getattr(first, name), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(again.weights, first.weights, rtol=0, atol=1e-5)
    with pytest.raises(InputError):
        fit_inverse_render(*arguments, FitConfig(num_basis=3, iterations=0), warm_start=first)


def test_fit_on_degenerate_captures_stays_finite(small_scene):
    scene, pixels = small_scene
    captures, emission, *_ = _olat_fit_data(pixels)
    captures = captures.clone()
    captures[:, :10] = 0.0  # dark pixels
    captures[:, 10:20] = 1.0  # saturated pixels
    result = fit_inverse_render(captures, emission, pixels.points, pixels.lights(), Falloff(), pixels.transport.pixel_index,
                                scene.height, scene.width, FitConfig(num_basis=2, iterations=10))
    for value in (result.normal, result.weights, result.diffuse, result.specular, result.roughness, torch.tensor(result.loss_history)):
        assert bool(torch.isfinite(value).all())


def test_emission_in_any_units_gives_the_same_fit(small_scene):
    """Emission scaled by a power of two, 1e-20 or 1e20 (another radiometric unit) changes the
    albedos by the same factor and nothing else; before, x64 moved normals by 16 deg on average, 1e6
    by 39 deg, and 1e20 gave NaN."""
    scene, pixels = small_scene
    captures, emission, *_ = _olat_fit_data(pixels)
    config = FitConfig(num_basis=2, iterations=20)
    arguments = (pixels.points, pixels.lights(), Falloff(), pixels.transport.pixel_index, scene.height, scene.width, config)
    natural = fit_inverse_render(captures, emission, *arguments)
    for factor in (1e-20, 1 / 64, 64.0, 1e20):
        scaled = fit_inverse_render(captures, emission * factor, *arguments)
        torch.testing.assert_close(scaled.normal, natural.normal, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(scaled.diffuse * factor, natural.diffuse, rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(scaled.specular * factor, natural.specular, rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(torch.tensor(scaled.rmse_history), torch.tensor(natural.rmse_history), rtol=1e-4, atol=1e-6)
    for factor in (1e-35, 1e35):
        with pytest.raises(InputError, match="emission peak"):
            fit_inverse_render(captures, emission.double() * factor, *arguments)
    infinite = emission.clone()
    infinite[0, 0, 0] = math.inf
    for bad in (infinite, emission[:0]):
        with pytest.raises(InputError):
            initial_estimate(captures[: bad.shape[0]], bad, pixels.points, pixels.lights(), Falloff())


def _stability_patterns(case, rig):
    generator = torch.Generator().manual_seed(5)
    if case == "one_pattern":
        return torch.rand(1, rig.rows, rig.cols, 3, generator=generator)
    if case == "identical_patterns":
        return torch.rand(1, rig.rows, rig.cols, 3, generator=generator).expand(2, -1, -1, -1).contiguous()
    if case == "all_black":
        return torch.zeros(3, rig.rows, rig.cols, 3)
    return torch.rand(4, rig.rows, rig.cols, 3, generator=generator)  # "strong_noise": random patterns, 10x noise


@pytest.mark.parametrize("case", ["one_pattern", "identical_patterns", "all_black", "strong_noise"])
def test_fit_stays_finite_on_the_reconstruction_stability_cases(small_scene, case):
    """The stability suite of the reconstruction issue (rank-deficient sets, 10x noise) through the
    whole fit: outputs, loss history and the gradients of the last step's loss are finite."""
    from capture_sim.simulator import simulate

    scene, pixels = small_scene
    rig = pixels.rig
    noise = rig.noise.scaled(10.0) if case == "strong_noise" else None
    capture = simulate(_stability_patterns(case, rig), pixels.transport, rig, exposure=0.5, noise=noise, bit_depth=None,
                       generator=torch.Generator().manual_seed(6))
    arguments = (capture.captures, capture.emission, pixels.points, pixels.lights(), Falloff(), pixels.transport.pixel_index,
                 scene.height, scene.width)
    result = fit_inverse_render(*arguments, FitConfig(num_basis=2, iterations=8, normal_search_at=(0.0,)))
    for value in (result.normal, result.weights, result.diffuse, result.specular, result.roughness, torch.tensor(result.loss_history)):
        assert bool(torch.isfinite(value).all()), case
    leaves = [t.clone().requires_grad_() for t in (result.normal, result.weights, result.diffuse, result.specular, result.roughness)]
    rendered = render_under_patterns(leaves[0], pixels.points, pixels.lights(), capture.emission, *leaves[1:], Falloff())
    torch.sqrt(((rendered - capture.captures) ** 2).mean() + 1e-12).backward()
    assert bool(torch.isfinite(rendered).all()) and all(bool(torch.isfinite(leaf.grad).all()) for leaf in leaves), case


def test_fit_bad_input_raises(small_scene):
    scene, pixels = small_scene
    captures, emission, *_ = _olat_fit_data(pixels)
    arguments = [captures, emission, pixels.points, pixels.lights(), Falloff(), pixels.transport.pixel_index, scene.height, scene.width]
    # A fitted falloff with its pole inside the scene (DESIGN section 3: negative below 0.608 m).
    pole = Falloff("fitted", a=-5.4580, b=14.7449)
    for position, bad in ((0, captures[:, :, :2]), (1, emission[:-1]), (2, pixels.points[:-1]), (5, pixels.transport.pixel_index + 10**6), (4, pole)):
        wrong = list(arguments)
        wrong[position] = bad
        with pytest.raises(InputError, match="is not positive and finite" if position == 4 else None):
            fit_inverse_render(*wrong, FitConfig(iterations=1))
    for height, width in ((float(scene.height), float(scene.width)), (-scene.height, -scene.width)):  # torch's TypeError; a product that fits
        with pytest.raises(InputError, match="positive whole numbers"):
            fit_inverse_render(*arguments[:6], height, width, FitConfig(iterations=1))


def test_initial_estimate_on_patterns_is_finite_and_unit(small_scene):
    scene, pixels = small_scene
    rig = pixels.rig
    patterns = torch.rand(4, rig.rows, rig.cols, 3, generator=torch.Generator().manual_seed(11))
    from capture_sim.simulator import simulate

    capture = simulate(patterns, pixels.transport, rig, noise=None, bit_depth=None)
    initial = initial_estimate(capture.captures, capture.emission, pixels.points, pixels.lights(), Falloff(),
                               pixel_index=pixels.transport.pixel_index, height=scene.height, width=scene.width)
    assert isinstance(initial, InitialEstimate)
    torch.testing.assert_close(initial.normal.norm(dim=-1), torch.ones(pixels.num_pixels))
    view = -pixels.points / pixels.points.norm(dim=-1, keepdim=True)
    assert bool(((initial.normal * view).sum(-1) >= 0.2 - 1e-6).all())
    assert bool(torch.isfinite(initial.albedo).all()) and bool((initial.albedo >= 0).all())


def test_least_squares_start_is_bounded_by_the_photometric_stereo_albedo_and_the_specular_floor(small_scene, monkeypatch):
    # Least squares that give rho_d above the photometric-stereo albedo (which takes all reflected
    # light as diffuse) or rho_s ~ 0 start the fit in a minimum with an over-bright basis.
    scene, pixels = small_scene
    captures, emission, *_ = _olat_fit_data(pixels)
    initial = initial_estimate(captures, emission, pixels.points, pixels.lights(), Falloff(),
                               pixel_index=pixels.transport.pixel_index, height=scene.height, width=scene.width)
    config = FitConfig(num_basis=3)
    _, centres = cluster_albedo(initial.albedo, initial.valid, 3, config.seed)

    def too_bright_and_no_specular(*args, **kwargs):
        return torch.stack([2.0 * centres[0], 0.5 * centres[1], torch.zeros(3)]), torch.zeros(3), torch.tensor([True, True, False])

    monkeypatch.setattr(inverse_render, "least_squares_albedos", too_bright_and_no_specular)
    model = inverse_render._initial_model(captures, emission, pixels.points, pixels.lights(), Falloff(), initial, config)
    torch.testing.assert_close(model.diffuse(), torch.stack([centres[0], 0.5 * centres[1], centres[2]]))
    torch.testing.assert_close(model.specular(), torch.full((3,), config.initial_specular * config.specular_floor))


# ----------------------------------------------------------------------------------------------
# Relighting metrics
# ----------------------------------------------------------------------------------------------


def test_split_lights_is_five_to_one_and_disjoint():
    split = split_lights(144)
    assert split.test.numel() == 24 and split.fit.numel() == 120
    assert split.test.tolist() == list(range(5, 144, 6))
    assert not set(split.test.tolist()) & set(split.fit.tolist())
    assert set(split.validation.tolist()) | set(split.train.tolist()) == set(split.fit.tolist())
    assert split.validation.numel() == 24 and not set(split.validation.tolist()) & set(split.train.tolist())
    with pytest.raises(InputError):
        split_lights(3)


def test_olat_emission_refuses_an_exposure_its_dtype_cannot_hold():
    """1e300 in float32 failed inside torch's conversion ("value cannot be converted"): now one
    clear error; float64 holds it."""
    with pytest.raises(InputError, match="exposure 1e.300 overflows torch.float32"):
        olat_emission(torch.arange(3), 5, 1e300)
    assert float(olat_emission(torch.arange(3), 5, 1e300, torch.float64).amax()) == 1e300
    with pytest.raises(InputError, match="positive and finite"):
        olat_emission(torch.arange(3), 5, float("inf"))


def test_pooled_psnr_matches_closed_form():
    truth = torch.full((2, 10, 3), 0.5, dtype=torch.float64)
    assert pooled_psnr(truth + 0.01, truth) == pytest.approx(40.0, abs=TOL["psnr_db"])  # MSE 1e-4
    assert pooled_psnr(truth, truth) == pytest.approx(100.0)  # identical images: the metrics cap
    with pytest.raises(InputError):
        pooled_psnr(truth[:, :0], truth[:, :0])


def test_relighting_ssim_of_identical_and_shuffled_images():
    pixel_index = torch.arange(20, 236)  # a dense mask: SSIM windows see image structure, not background
    images = torch.rand(2, pixel_index.numel(), 3, generator=torch.Generator().manual_seed(12), dtype=torch.float64)
    assert relighting_metrics(images, images, pixel_index, 16, 16)["ssim"] == pytest.approx(1.0, abs=1e-6)
    assert relighting_metrics(images.numpy(), images.numpy(), pixel_index, 16, 16)["ssim"] == pytest.approx(1.0, abs=1e-6)  # arrays too
    assert relighting_metrics(images, 1.0 - images, pixel_index, 16, 16)["ssim"] < 0.0  # anti-correlated


def test_relighting_ssim_on_the_cropped_object_equals_the_full_image_ssim():
    from reconstruct.metrics import ssim

    height, width = 40, 50
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    mask = ((rows - 14) ** 2 + (cols - 30) ** 2) < 8**2  # small and off-centre: the crop is much smaller
    pixel_index = torch.nonzero(mask.reshape(-1)).squeeze(1)
    generator = torch.Generator().manual_seed(13)
    truth = torch.rand(2, pixel_index.numel(), 3, generator=generator, dtype=torch.float64)
    predicted = (truth + 0.1 * torch.randn(truth.shape, generator=generator, dtype=torch.float64)).clamp(0, 1)

    def full(values):
        images = torch.zeros((2, height * width, 3), dtype=torch.float64)
        images[:, pixel_index] = values
        return images.reshape(2, height, width, 3)

    expected = ssim(full(predicted), full(truth), mask, 11)
    assert relighting_metrics(predicted, truth, pixel_index, height, width)["ssim"] == pytest.approx(expected, abs=1e-12)


def test_relighting_metrics_clip_to_full_scale():
    pixel_index = torch.arange(0, 64, 2)
    truth = torch.full((3, 32, 3), 0.5)
    over = truth.clone()
    over[:, :4] = 5.0
    truth[:, :4] = 1.0  # both saturate: no error after clipping
    metrics = relighting_metrics(over, truth, pixel_index, 8, 8)
    assert metrics["psnr"] == pytest.approx(100.0) and metrics["rmse"] == 0.0 and metrics["images"] == 3


# ----------------------------------------------------------------------------------------------
# Command end to end
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory, small_scene):
    path = tmp_path_factory.mktemp("scene") / "small.npz"
    save_scene(small_scene[0], path)
    return path


def test_run_invrender_olat_writes_every_output(tmp_path, scene_file, monkeypatch):
    import train.invrender_figures
    from train.invrender_command import InvRenderConfig, run_invrender

    colour_ranges = {}
    save_figure = train.invrender_figures.save_figure

    def keep_ranges(fig, path):
        colour_ranges[Path(path).name] = [image.get_clim() for ax in fig.axes for image in ax.get_images()]
        save_figure(fig, path)

    monkeypatch.setattr(train.invrender_figures, "save_figure", keep_ranges)
    out = tmp_path / "run"
    out.mkdir()
    (out / "model_selection.png").write_bytes(b"an earlier --basis auto run's chart")
    result = run_invrender(InvRenderConfig(scene=scene_file, out=out, json=tmp_path / "result.json", basis="2", iterations=4))
    assert not (out / "model_selection.png").exists()  # it would contradict this run's result.json
    for key in ("mae", "psnr", "ssim", "seconds", "J"):
        assert key in result and math.isfinite(result[key])
    assert result["J"] == 2 and result["specular"] and result["model_selection"] is None
    assert result["light_model"]["far_field"] is False  # the reference rig is near field at 0.5 m
    for name in ("normals.png", "normals.npy", "normals_figure.png", "weights.png", "weights.npy", "brdf_spheres.png",
                 "relit.png", "config.json", "result.json"):
        assert (out / name).is_file(), name
    assert any((out / "tensorboard").glob("events.out.tfevents*"))
    normals = np.load(out / "normals.npy")
    assert normals.shape == (*small_scene_shape(scene_file), 3)
    assert json.loads((tmp_path / "result.json").read_text())["J"] == 2
    assert colour_ranges["weights.png"] == [(0.0, 1.0)] * 2  # weights on the simplex: one scale for every basis


def small_scene_shape(path):
    from capture_sim.scene import load_scene

    scene = load_scene(path)
    return scene.height, scene.width


def test_run_invrender_patterns_without_output_folder(tmp_path, scene_file):
    from patterns.families import make_patterns
    from patterns.io import save_patterns
    from train.invrender_command import InvRenderConfig, run_invrender

    pattern_file = tmp_path / "patterns.npz"
    save_patterns(pattern_file, make_patterns("mono_gradient", 4), {"family": "mono_gradient"})
    result = run_invrender(InvRenderConfig(scene=scene_file, patterns=str(pattern_file), basis="1", iterations=3, noise="off"))
    assert result["data"]["M"] == 4 and result["data"]["noise"] is None and result["J"] == 1
    assert math.isfinite(result["psnr"]) and result["data"]["exposure"] > 0


def test_invrender_warns_when_no_pixel_is_solvable_and_never_overwrites_inputs(tmp_path, scene_file, capsys):
    from train.cli import run

    black = tmp_path / "out" / "weights.npy"  # identical (all-black) patterns, saved where --out writes weights.npy
    black.parent.mkdir()
    np.save(black, np.zeros((4, 9, 16, 3), dtype=np.float32))
    assert run(["invrender", "--scene", str(scene_file), "--patterns", str(black), "--basis", "1", "--iterations", "2",
                "--out", str(tmp_path / "out")]) == 2
    assert "would destroy" in capsys.readouterr().err and np.load(black).shape == (4, 9, 16, 3)
    assert run(["invrender", "--scene", str(scene_file), "--patterns", str(black), "--basis", "1", "--iterations", "2",
                "--json", str(tmp_path / "r.json")]) == 0
    assert "displex: warning: photometric stereo flags every pixel" in capsys.readouterr().err


@pytest.mark.parametrize("bad", [dict(basis="9"), dict(basis="x"), dict(iterations=0), dict(noise="loud"), dict(geometry="sideways"),
                                 dict(exposure="-1"), dict(tv_weight=math.nan), dict(tv_weight=math.inf)])
def test_run_invrender_bad_settings_raise(scene_file, bad):
    from train.invrender_command import InvRenderConfig, run_invrender

    with pytest.raises(InputError):
        run_invrender(InvRenderConfig(scene=scene_file, **bad))


def test_invrender_thread_settings_from_python_use_the_cli_check(scene_file):
    """InvRenderConfig and bench_invrender refuse what `displex --threads` refuses, with its message."""
    from capture_sim.errors import MAX_THREADS, check_thread_count
    from train.bench_invrender import bench_invrender
    from train.invrender_command import InvRenderConfig

    assert check_thread_count(0) == 0 and check_thread_count(MAX_THREADS) == MAX_THREADS
    for bad in (-1, MAX_THREADS + 1, 2.0, True):
        with pytest.raises(InputError, match=r"thread count must be 0 \(torch's default\) or 1\.\.1024"):
            InvRenderConfig(scene=scene_file, threads=bad).validate()
    with pytest.raises(InputError, match="thread count"):
        bench_invrender(threads=-1)


def test_run_invrender_without_ground_truth_normals(tmp_path, small_scene):
    import dataclasses

    from train.invrender_command import InvRenderConfig, run_invrender

    save_scene(dataclasses.replace(small_scene[0], normal=None), tmp_path / "no-normals.npz")
    out = tmp_path / "run"
    result = run_invrender(InvRenderConfig(scene=tmp_path / "no-normals.npz", out=out, basis="1", iterations=2))
    assert result["mae"] is None and result["normal_error"] is None and math.isfinite(result["psnr"])
    assert (out / "normals_figure.png").is_file()


def test_run_invrender_failure_leaves_the_earlier_run_whole(tmp_path, scene_file, monkeypatch):
    """A rerun that fails part-way (here while writing its figures) leaves --out exactly as the
    finished run left it, logs included: no folder mixing two runs, no staging leftovers; a fresh
    --out is not left behind at all."""
    import train.invrender_command as command
    import train.invrender_figures as figures

    def tree(folder):
        return {str(path.relative_to(folder)): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}

    out, fresh = tmp_path / "run", tmp_path / "fresh"
    command.run_invrender(command.InvRenderConfig(scene=scene_file, out=out, basis="1", iterations=2))
    before = tree(out)
    assert any(name.startswith("tensorboard/events") for name in before)
    write_png = figures.write_png

    def broken(path, image):
        write_png(path, image)
        raise RuntimeError("disk failed")

    monkeypatch.setattr(figures, "write_png", broken)
    for folder in (out, fresh):
        with pytest.raises(RuntimeError):
            command.run_invrender(command.InvRenderConfig(scene=scene_file, out=folder, basis="1", iterations=3, seed=9))
    assert tree(out) == before and sorted(path.name for path in out.iterdir() if path.name.startswith(".")) == []
    assert not fresh.exists()


def test_run_invrender_refused_move_keeps_the_earlier_logs(tmp_path, scene_file, monkeypatch):
    """A rerun refused when its staged files move in (after the fit) leaves the earlier run's
    files and logs as they were; a rerun that succeeds replaces the earlier logs."""
    import capture_sim.atomic as atomic
    import train.invrender_command as command

    out = tmp_path / "run"
    command.run_invrender(command.InvRenderConfig(scene=scene_file, out=out, basis="1", iterations=2))
    logs = sorted((out / "tensorboard").rglob("events*"))
    assert logs
    fitted, fit, check = [], command._fit_and_evaluate, atomic.check_replaceable

    def fit_then_refuse(*args, **kwargs):
        fitted.append(True)
        return fit(*args, **kwargs)

    def refuse_after_fit(path):
        if fitted:
            raise InputError(f"cannot replace {path}")
        return check(path)

    monkeypatch.setattr(command, "_fit_and_evaluate", fit_then_refuse)
    monkeypatch.setattr(atomic, "check_replaceable", refuse_after_fit)
    with pytest.raises(InputError, match="cannot replace"):
        command.run_invrender(command.InvRenderConfig(scene=scene_file, out=out, basis="1", iterations=2))
    assert sorted((out / "tensorboard").rglob("events*")) == logs
    monkeypatch.undo()
    command.run_invrender(command.InvRenderConfig(scene=scene_file, out=out, basis="1", iterations=2))
    now = sorted((out / "tensorboard").rglob("events*"))
    assert now and not set(now) & set(logs)


def test_run_invrender_refuses_a_tensorboard_folder_it_did_not_write(tmp_path, scene_file):
    from train.invrender_command import InvRenderConfig, run_invrender

    for name, make in (("logs", lambda board: (board / "train").mkdir(parents=True)), ("file", lambda board: board.write_text("x"))):
        board = tmp_path / name / "tensorboard"
        board.parent.mkdir()
        make(board)
        with pytest.raises(InputError, match="was not written by displex invrender"):
            run_invrender(InvRenderConfig(scene=scene_file, out=board.parent, basis="1", iterations=2))
    assert (tmp_path / "logs" / "tensorboard" / "train").is_dir()


def test_run_invrender_refuses_a_scene_too_bright_for_float32_naming_the_olat_stack(tmp_path, scene_file):
    """Auto exposure would need a gain of ~1e-32: the message points at the scene, not at an
    emission the user never set."""
    from train.invrender_command import InvRenderConfig, run_invrender

    with np.load(scene_file) as data:
        arrays = dict(data)
    np.savez(tmp_path / "bright.npz", **{**arrays, "olat": arrays["olat"].astype(np.float32) * np.float32(1e30)})
    with pytest.raises(InputError, match="rescale the scene's OLAT stack"):
        run_invrender(InvRenderConfig(scene=tmp_path / "bright.npz", basis="1", iterations=1))
    # Black patterns on a rig without backlight: the patterns are the cause, not the scene.
    rig_text = (RIG_DIR / "panel-55in-4x8.toml").read_text().replace("backlight = 0.025", "backlight = 0.0")
    (tmp_path / "dark.toml").write_text(rig_text)
    np.save(tmp_path / "black.npy", np.zeros((4, 4, 8, 3), dtype=np.float32))
    scene = synthesize_scene("cylinder", "lambertian", load_rig(tmp_path / "dark.toml"), height=12, width=14, seed=0)
    save_scene(scene, tmp_path / "cyl.npz")
    with pytest.raises(InputError, match="the patterns emit no light"):
        run_invrender(InvRenderConfig(scene=tmp_path / "cyl.npz", rig=str(tmp_path / "dark.toml"), patterns=str(tmp_path / "black.npy"),
                                      basis="1", iterations=1))


def test_run_invrender_refuses_a_json_inside_its_tensorboard_folder(tmp_path, scene_file):
    from train.invrender_command import InvRenderConfig, run_invrender

    with pytest.raises(InputError, match="lies in --out's tensorboard folder"):
        run_invrender(InvRenderConfig(scene=scene_file, out=tmp_path / "o", json=tmp_path / "o" / "tensorboard" / "x.json", basis="1", iterations=1))


def test_run_invrender_missing_scene_raises(tmp_path):
    from train.invrender_command import InvRenderConfig, run_invrender

    with pytest.raises(InputError):
        run_invrender(InvRenderConfig(scene=tmp_path / "missing.npz", basis="1", iterations=1))


# ----------------------------------------------------------------------------------------------
# Acceptance at 128 x 153 (slow): quality only. Wall and CPU times, and the learned M = 4 sets, are
# measured by `displex bench invrender` (its "acceptance" part runs this scene from OLAT, from M = 4
# patterns it learns with the `displex train` defaults, and from the published learned set).
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def acceptance_scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("acceptance") / "sphere-svbrdf.npz"
    save_scene(synthesize_scene("sphere", "svbrdf", load_rig(), 128, 153, seed=1), path)
    return path


@pytest.mark.slow
def test_acceptance_olat_cook_torrance_scene(acceptance_scene):
    from train.invrender_command import InvRenderConfig, run_invrender

    result = run_invrender(InvRenderConfig(scene=acceptance_scene, basis="3", noise="off"))  # default 400 iterations
    assert result["psnr"] >= 40.0 and result["mae"] <= 3.0


@pytest.mark.slow
def test_acceptance_four_gradient_patterns(acceptance_scene, tmp_path):
    from patterns.families import make_patterns
    from patterns.io import save_patterns
    from train.invrender_command import InvRenderConfig, run_invrender

    save_patterns(tmp_path / "mono_gradient.npz", make_patterns("mono_gradient", 4), {"family": "mono_gradient"})
    result = run_invrender(InvRenderConfig(scene=acceptance_scene, patterns=str(tmp_path / "mono_gradient.npz"), basis="3",
                                           iterations=600, noise="off"))
    assert result["psnr"] >= 35.0
