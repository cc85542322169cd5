"""evaluate_scene's noise: scene i of a list draws it from seed 1000 x N + i (README)."""
import pytest
import torch

from capture_sim.rig import load_rig
from capture_sim.synth import synthesize_scene
from patterns.families import make_patterns
from reconstruct.metrics import angular_error_deg
from reconstruct.photometric_stereo import solve_ps
from train.capture import capture_scene
from train.evaluate import EvalSettings, evaluate_scene
from train.scene_pixels import scene_pixels


def test_noise_seed_is_seed_times_1000_plus_scene_position():
    rig = load_rig()
    pixels = scene_pixels(synthesize_scene("sphere", "lambertian", rig, 16, 20, seed=0), rig, require_normals=True)
    patterns = make_patterns("mono_gradient", 4).float()
    settings = EvalSettings(noise_scale=1.0, seed=3)
    first, second = (evaluate_scene(pixels, patterns, settings, scene_index=i).metrics["mae"] for i in (0, 1))
    assert abs(first - second) > 1e-3  # the same scene at another place in the list draws other noise
    captured = capture_scene(pixels, patterns, 1.0, settings.exposure, torch.Generator().manual_seed(3 * 1000 + 1), None)
    result = solve_ps(captured.captures, captured.emission, pixels.points, pixels.lights(), pixels.rig.falloff, settings.ps)
    assert float(angular_error_deg(result.normal, pixels.normal).mean()) == pytest.approx(second, rel=1e-6)


def test_falloff_errors_name_the_scene(monkeypatch):
    from capture_sim.errors import InputError

    rig = load_rig()
    scene = synthesize_scene("sphere", "lambertian", rig, 16, 20, seed=0)

    def unusable(self, distances):
        raise InputError("falloff inverse_square is not positive and finite over light distances 0.000..0.951 m")

    monkeypatch.setattr(type(rig.falloff), "check", unusable)
    with pytest.raises(InputError, match=f"^scene {scene.name}: falloff inverse_square is not positive"):
        scene_pixels(scene, rig)


def test_olat_captures_are_the_sensor_of_the_exposed_stack_laid_out_for_the_solvers():
    """The OLAT captures are sensor(e * O) with the stack's noise drawn in its (K, N, 3) order, and
    pattern-major in memory, so that the solvers' pixels-last (K, 3, N) view needs no copy (at
    512 x 612 pixels that copy was 540 MB of evaluate's peak)."""
    from capture_sim.simulator import auto_exposure, sensor
    from train.evaluate import olat_captures

    rig = load_rig()
    pixels = scene_pixels(synthesize_scene("sphere", "lambertian", rig, 16, 20, seed=0), rig, require_normals=True)
    for columns in (None, torch.tensor([3, 1, 4, 1, 5])):
        captures, emission, exposure = olat_captures(pixels, EvalSettings(), torch.Generator().manual_seed(7), columns)
        radiance = pixels.transport.matrix.permute(1, 2, 0)
        assert exposure == auto_exposure(radiance)
        if columns is not None:
            radiance = radiance[:, columns]
        expected = sensor((exposure * radiance).contiguous(), rig.noise, rig.bit_depth, torch.Generator().manual_seed(7))
        assert torch.equal(captures, expected) and captures.permute(0, 2, 1).is_contiguous()
        assert torch.equal(emission, exposure * torch.eye(rig.num_lights)[:, :, None].expand(-1, -1, 3))
