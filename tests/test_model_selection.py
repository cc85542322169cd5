"""Model selection (reconstruct.model_selection): J, Lambertian or specular, near or far field."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from capture_sim.errors import DisplexWarning, InputError
from capture_sim.materials import Material, make_material
from capture_sim.rig import Falloff, load_rig
from capture_sim.render import render_olat
from capture_sim.scene import Scene, save_scene
from capture_sim.shapes import cast_camera_rays, make_shape
from capture_sim.simulator import auto_exposure, sensor
from capture_sim.synth import synthesize_scene
from reconstruct.fit_start import initial_estimate
from reconstruct.inverse_render import FitConfig, FitProblem
from reconstruct.model_selection import (
    Candidate,
    SelectionConfig,
    choose_light_model,
    choose_smallest,
    light_spread,
    select_basis,
    select_model,
)
from reconstruct.relight import olat_emission, split_lights
from train.scene_pixels import scene_pixels


def _scripted(table: dict):
    """An evaluate() returning PSNRs from ``table[(J, specular)]`` and recording the calls."""
    calls = []

    def evaluate(num_basis, specular):
        calls.append((num_basis, specular))
        psnr = table[(num_basis, specular)]
        return Candidate(num_basis, specular, psnr, 10 ** (-psnr / 20), 0.0)

    return evaluate, calls


# ----------------------------------------------------------------------------------------------
# Selection rule
# ----------------------------------------------------------------------------------------------


def test_select_model_picks_smallest_within_tolerance_and_stops_early():
    table = {(j, s): 30.0 + min(j, 3) * 3.0 + (1.0 if s else 0.0) - 0.05 * j for j in range(1, 9) for s in (False, True)}
    evaluate, calls = _scripted(table)
    selection = select_model(evaluate, SelectionConfig(tolerance_db=0.5, min_improvement_db=0.1, patience=2))
    # Best is J=3 specular (38.85); J=4, 5 do not improve by 0.1 dB -> stop after J=5.
    assert calls == [(j, s) for j in range(1, 6) for s in (False, True)]
    assert selection.stopped_early
    assert (selection.best.num_basis, selection.best.specular) == (3, True)
    assert (selection.chosen.num_basis, selection.chosen.specular) == (3, True)
    assert len(selection.curve) == 10 and "0.5 dB" in selection.rule


def test_select_model_prefers_lambertian_when_lobes_do_not_help():
    table = {(j, s): 45.0 - 0.01 * j + (0.2 if s else 0.0) for j in range(1, 9) for s in (False, True)}
    evaluate, _ = _scripted(table)
    selection = select_model(evaluate, SelectionConfig(tolerance_db=0.5))
    assert (selection.chosen.num_basis, selection.chosen.specular) == (1, False)
    assert (selection.best.num_basis, selection.best.specular) == (1, True)


def test_select_model_runs_to_max_basis_while_improving():
    table = {(j, s): 20.0 + 2.0 * j for j in range(1, 5) for s in (False, True)}
    evaluate, calls = _scripted(table)
    selection = select_model(evaluate, SelectionConfig(max_basis=4))
    assert not selection.stopped_early and len(calls) == 8
    assert (selection.chosen.num_basis, selection.chosen.specular) == (4, False)


def test_choose_smallest_orders_by_basis_then_lobes():
    curve = [Candidate(2, False, 40.0, 0.0, 0.0), Candidate(1, True, 40.3, 0.0, 0.0), Candidate(3, True, 40.6, 0.0, 0.0)]
    chosen, best = choose_smallest(curve, 0.5)
    assert (chosen.num_basis, chosen.specular) == (1, True) and best.num_basis == 3
    chosen, _ = choose_smallest(curve, 0.0)
    assert chosen.num_basis == 3
    with pytest.raises(InputError):
        choose_smallest([], 0.5)


def test_psnrs_above_the_ceiling_count_as_equal():
    # Noise-free captures of one Lambertian material: the PSNRs differ by the fits' convergence.
    curve = [Candidate(1, False, 80.6, 0.0, 0.0), Candidate(1, True, 50.2, 0.0, 0.0), Candidate(2, False, 83.1, 0.0, 0.0)]
    chosen, best = choose_smallest(curve, 0.5, 60.0)
    assert (chosen.num_basis, chosen.specular) == (1, False) and best.num_basis == 2  # best: as measured
    assert choose_smallest(curve, 0.5)[0].num_basis == 2  # without a ceiling, the old rule
    # A candidate below the ceiling still has to be within the tolerance of it.
    chosen, _ = choose_smallest([Candidate(1, False, 59.0, 0.0, 0.0), Candidate(2, False, 70.0, 0.0, 0.0)], 0.5, 60.0)
    assert chosen.num_basis == 2
    table = {(j, s): 80.0 + j - (30.0 if s else 0.0) for j in range(1, 9) for s in (False, True)}
    evaluate, calls = _scripted(table)
    selection = select_model(evaluate, SelectionConfig())
    # J = 2 and 3 gain nothing at the ceiling: the sweep stops after J = 3 (patience 2) and keeps J = 1.
    assert (selection.chosen.num_basis, selection.chosen.specular) == (1, False) and len(calls) == 6
    assert selection.stopped_early and "above 60 dB counted as 60" in selection.rule
    selection = select_model(evaluate, SelectionConfig(psnr_ceiling_db=math.inf))
    assert selection.chosen.num_basis == 8 and "counted as" not in selection.rule


@pytest.mark.slow
def test_selection_picks_one_lambertian_basis_for_noise_free_captures():
    """A uniform Lambertian sphere without noise scored 80.6 dB with J = 1 and 83.1 with J = 2,
    which the bare 0.5 dB rule took for a second material."""
    rig = load_rig()
    pixels = scene_pixels(synthesize_scene("sphere", "lambertian", rig, 40, 48, seed=1), rig)
    olat = pixels.transport.matrix.permute(1, 2, 0)
    split, exposure = split_lights(olat.shape[0]), auto_exposure(olat)
    captures = (olat * exposure).clamp(0, 1)
    problem = FitProblem(captures[split.train], olat_emission(split.train, olat.shape[0], exposure), pixels.points, pixels.lights(),
                         rig.falloff, pixels.transport.pixel_index, 40, 48)
    selection = select_basis(problem, olat_emission(split.validation, olat.shape[0], exposure), captures[split.validation],
                             FitConfig(seed=0), SelectionConfig(iterations=60))
    assert min(candidate.psnr for candidate in selection.curve if not candidate.specular) > 60.0  # the case in point
    assert (selection.chosen.num_basis, selection.chosen.specular) == (1, False)


def test_selection_config_rejects_bad_settings():
    for bad in (dict(max_basis=0), dict(patience=0), dict(iterations=0), dict(tolerance_db=-1.0), dict(far_field_tolerance=-0.1),
                dict(psnr_ceiling_db=0.0), dict(psnr_ceiling_db=math.nan)):
        with pytest.raises(InputError):
            SelectionConfig(**bad)


# ----------------------------------------------------------------------------------------------
# Light model
# ----------------------------------------------------------------------------------------------


def test_light_spread_closed_form():
    points = torch.tensor([[0.0, 0.0, 0.5], [0.1, 0.0, 0.5]], dtype=torch.float64)
    lights = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)  # a light at the camera centre
    spread = light_spread(points, lights, Falloff())
    # The centroid is (0.05, 0, 0.5); directions to the light are -x / |x|, so the angles are the
    # differences of the points' polar angles atan(x / 0.5).
    angle_a = math.degrees(math.atan(0.1))
    angle_b = math.degrees(math.atan(0.2) - math.atan(0.1))
    assert spread["max_direction_deg"] == pytest.approx(max(angle_a, angle_b), rel=1e-9)
    assert spread["mean_direction_deg"] == pytest.approx((angle_a + angle_b) / 2, rel=1e-9)
    centre_sq = 0.05**2 + 0.25  # 1/d^2 falloff relative to the centroid's: d_c^2 / d^2
    deviations = (abs(centre_sq / 0.25 - 1), abs(centre_sq / (0.1**2 + 0.25) - 1))
    assert spread["max_falloff_ratio_deviation"] == pytest.approx(max(deviations), rel=1e-9)
    # A falloff that is not positive and finite everywhere is refused, not reported as inf or NaN.
    from capture_sim.errors import InputError

    with pytest.raises(InputError, match="falloff is not positive and finite"):
        light_spread(points, lights, lambda distance: 1.0 / (distance - 0.5))  # a pole at the first point


def _far_rig(factor: float = 200.0):
    rig = load_rig()
    return rig.replace(light_positions=rig.light_positions * factor)


def test_choose_light_model_far_display_is_far_field_and_reference_rig_is_not():
    for rig, expected in ((_far_rig(), True), (load_rig(), False)):
        scene = synthesize_scene("sphere", "lambertian", rig, 24, 29, seed=1)
        pixels = scene_pixels(scene, rig)
        olat = pixels.transport.matrix.permute(1, 2, 0)
        split = split_lights(olat.shape[0])
        exposure = auto_exposure(olat)
        emission = olat_emission(split.fit, olat.shape[0], exposure)
        initial = initial_estimate((olat[split.fit] * exposure).clamp(0, 1), emission, pixels.points, pixels.lights(), rig.falloff)
        decision = choose_light_model(initial, emission, pixels.points, pixels.lights(), rig.falloff)
        assert decision["far_field"] is expected
        assert math.isfinite(decision["near_vs_far_relative_rms"]) and decision["max_direction_deg"] >= 0
        if expected:
            assert decision["max_direction_deg"] < 0.2 and decision["near_vs_far_relative_rms"] < 2e-3
        else:
            assert decision["near_vs_far_relative_rms"] > 0.02


# ----------------------------------------------------------------------------------------------
# End to end
# ----------------------------------------------------------------------------------------------


def test_run_invrender_auto_basis_writes_the_curve(tmp_path):
    from train.invrender_command import InvRenderConfig, run_invrender

    rig = _far_rig()
    save_scene(synthesize_scene("sphere", "lambertian", rig, 24, 29, seed=1), tmp_path / "far.npz")
    out = tmp_path / "run"
    with pytest.warns(DisplexWarning, match="light positions differ"):  # a far scene, run with the default rig
        result = run_invrender(InvRenderConfig(scene=tmp_path / "far.npz", out=out, iterations=5, noise="off",
                                               selection=SelectionConfig(iterations=5, max_basis=2)))
    selection = result["model_selection"]
    assert result["far_field"] is True and result["light_model"]["mode"] == "auto"
    assert len(selection["curve"]) == 4 and {c["num_basis"] for c in selection["curve"]} == {1, 2}
    assert result["J"] == selection["chosen"]["num_basis"] and result["specular"] == selection["chosen"]["specular"]
    assert (out / "model_selection.png").is_file()


def test_max_candidates_is_the_length_of_a_full_sweep():
    table = {(j, s): 20.0 + 2.0 * j for j in range(1, 5) for s in (False, True)}
    evaluate, calls = _scripted(table)
    config = SelectionConfig(max_basis=4)
    select_model(evaluate, config)
    assert config.max_candidates == len(calls) == 8


def test_invrender_progress_bar_counts_candidate_fits(tmp_path, monkeypatch, capsys):
    """One bar step per candidate fit: total ``max_candidates``, ending full when the sweep stops
    early; then one over the final fit's steps (it ran silently); ``progress=False`` prints nothing."""
    import train.invrender_command as command
    from train.invrender_command import InvRenderConfig, run_invrender

    save_scene(synthesize_scene("sphere", "lambertian", load_rig(), 24, 29, seed=1), tmp_path / "sphere.npz")
    # No J can gain 100 dB: the sweep stops after J = 2 of 3, four fits of six.
    selection = SelectionConfig(iterations=2, max_basis=3, patience=1, min_improvement_db=100.0)
    config = InvRenderConfig(scene=tmp_path / "sphere.npz", iterations=2, noise="off", geometry="near", selection=selection)
    real_tqdm, bars = command.tqdm, []

    def recording_tqdm(*args, **kwargs):
        bars.append((kwargs["total"], real_tqdm(*args, **kwargs)))
        return bars[-1][1]

    monkeypatch.setattr(command, "tqdm", recording_tqdm)
    capsys.readouterr()
    result = run_invrender(config)
    fits = len(result["model_selection"]["curve"])
    assert result["model_selection"]["stopped_early"] and fits == 4
    [(initial_total, bar), (fit_total, fit_bar)] = bars  # then the final fit's steps
    assert initial_total == selection.max_candidates == 6 and bar.n == bar.total == fits
    assert fit_total == config.iterations and fit_bar.n == fit_total
    err = capsys.readouterr().err
    assert "model selection" in err and f"{fits}/{fits}" in err and "fitting" in err

    bars.clear()
    run_invrender(config, progress=False)
    assert len(bars) == 2 and capsys.readouterr().err == ""


def _olat_selection(scene: Scene, rig, iterations: int, seed: int = 0):
    """select_basis as the command runs it in OLAT mode: train lights fit, validation lights score."""
    pixels = scene_pixels(scene, rig)
    olat = pixels.transport.matrix.permute(1, 2, 0)
    split = split_lights(olat.shape[0])
    exposure = auto_exposure(olat)
    captures = sensor(olat * exposure, rig.noise, rig.bit_depth, torch.Generator().manual_seed(seed))
    problem = FitProblem(captures[split.train], olat_emission(split.train, olat.shape[0], exposure), pixels.points, pixels.lights(),
                         rig.falloff, pixels.transport.pixel_index, scene.height, scene.width)
    return select_basis(problem, olat_emission(split.validation, olat.shape[0], exposure), captures[split.validation],
                        FitConfig(seed=seed), SelectionConfig(iterations=iterations))


@pytest.mark.slow
def test_selection_picks_one_lambertian_basis_for_a_lambertian_sphere():
    rig = load_rig()
    selection = _olat_selection(synthesize_scene("sphere", "lambertian", rig, 40, 48, seed=1), rig, iterations=60)
    assert (selection.chosen.num_basis, selection.chosen.specular) == (1, False)


@pytest.mark.slow
def test_selection_finds_the_number_of_materials_of_the_regions_scene():
    rig = load_rig()
    scene = synthesize_scene("blob", "regions", rig, 48, 58, seed=1)
    assert scene.meta["material"]["num_basis"] == 4
    selection = _olat_selection(scene, rig, iterations=100)
    assert 3 <= selection.chosen.num_basis <= 5 and selection.chosen.specular


def _three_material_scene(rig, height: int, width: int, seed: int = 1) -> Scene:
    """Three piecewise GGX materials (the regions texture without its fourth basis)."""
    camera_rig = rig.with_resolution(height, width)
    hits = cast_camera_rays(make_shape("sphere", seed=seed, distance=rig.working_distance), camera_rig.camera.matrix(), height, width)
    regions = make_material("regions", hits.points, seed=seed)
    weights = regions.weights[..., 1:] / regions.weights[..., 1:].sum(-1, keepdim=True)  # drop the Lambertian basis
    material = Material("regions", regions.diffuse_albedo[1:], regions.specular_albedo[1:], regions.roughness[1:], weights, regions.texture)
    index = torch.nonzero(hits.mask.reshape(-1)).squeeze(1)
    diffuse, specular = render_olat(hits.points.reshape(-1, 3)[index], hits.normals.reshape(-1, 3)[index], rig.lights(torch.float64),
                                    material.weights.reshape(-1, 3)[index], material.diffuse_albedo, material.specular_albedo,
                                    material.roughness, rig.falloff)
    olat = np.zeros((rig.num_lights, height * width, 3), dtype=np.float32)
    olat[:, index.numpy()] = (diffuse + specular).numpy()
    return Scene(olat=olat.reshape(rig.num_lights, height, width, 3), mask=hits.mask.numpy().copy(), K_cam=camera_rig.camera.matrix(),
                 light_positions=rig.light_positions.astype(np.float32), normal=hits.normals.numpy().astype(np.float32),
                 depth=hits.depth.numpy().astype(np.float32), meta={"name": "three-materials"})


@pytest.mark.slow
def test_selection_finds_three_materials():
    rig = load_rig()
    selection = _olat_selection(_three_material_scene(rig, 48, 58), rig, iterations=100)
    assert 2 <= selection.chosen.num_basis <= 4 and selection.chosen.specular
