import math
import re

import numpy as np
import pytest
import torch

from capture_sim.display import display_emission
from capture_sim.errors import InputError
from capture_sim.reference import simulate_noise_free_reference
from capture_sim.rig import NoiseModel, load_rig
from capture_sim.simulator import auto_exposure, light_transport, noise_free_radiance, sensor, simulate
from tests.conftest import TOLERANCE


def _random_stack(rig, seed=0, dtype=np.float32):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 1.0, (rig.num_lights, rig.camera.height, rig.camera.width, 3)).astype(dtype)


def test_emission_matches_display_formula(tiny_rig):
    patterns = torch.rand(2, tiny_rig.rows, tiny_rig.cols, 3, dtype=torch.float64)
    emitted = display_emission(patterns, tiny_rig.backlight_flat(torch.float64), 2.2, 1.5)
    expected = 1.5 * (patterns.reshape(2, -1, 3) + torch.as_tensor(tiny_rig.backlight.reshape(1, -1, 1))) ** 2.2
    assert emitted.shape == (2, tiny_rig.num_lights, 3)
    torch.testing.assert_close(emitted, expected, **TOLERANCE[torch.float64])


@pytest.mark.parametrize("kind", ["one_hot", "random", "white"])
def test_noise_free_simulation_matches_reference(tiny_rig, kind):
    olat = _random_stack(tiny_rig)
    num_lights = tiny_rig.num_lights
    patterns = {
        "one_hot": np.eye(num_lights)[:, :, None].repeat(3, axis=2).reshape(num_lights, tiny_rig.rows, tiny_rig.cols, 3),
        "random": np.random.default_rng(1).uniform(0, 1, (3, tiny_rig.rows, tiny_rig.cols, 3)),
        "white": np.ones((1, tiny_rig.rows, tiny_rig.cols, 3)),
    }[kind]
    exposure = 0.7  # large enough that the white pattern clips
    capture = simulate(torch.as_tensor(patterns, dtype=torch.float32), light_transport(olat), tiny_rig, exposure=exposure, noise=None, bit_depth=None)
    expected = simulate_noise_free_reference(patterns, olat, tiny_rig.backlight, tiny_rig.gamma, tiny_rig.scale, exposure)
    got = capture.captures.reshape(len(patterns), tiny_rig.camera.height, tiny_rig.camera.width, 3).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-7)
    if kind == "white":
        assert (got == 1.0).any(), "the test needs visible clipping"


def test_masked_transport_scatters_back(tiny_rig):
    olat = _random_stack(tiny_rig)
    mask = np.zeros((4, 5), dtype=bool)
    mask[1:3, 1:4] = True
    transport = light_transport(olat, mask)
    assert transport.matrix.shape == (3, tiny_rig.num_lights, mask.sum())
    patterns = torch.rand(2, tiny_rig.rows, tiny_rig.cols, 3)
    emitted = display_emission(patterns, tiny_rig.backlight_flat(), tiny_rig.gamma)
    image = transport.to_image(noise_free_radiance(emitted, transport))
    full = light_transport(olat).to_image(noise_free_radiance(emitted, light_transport(olat)))
    torch.testing.assert_close(image[:, mask], full[:, mask])
    assert (image[:, ~mask] == 0).all()


def test_auto_exposure_puts_percentile_at_target():
    radiance = torch.rand(4, 20000, 3) * 3.0
    exposure = auto_exposure(radiance)
    exposed = (exposure * radiance).reshape(-1)
    assert abs(float(torch.quantile(exposed, 0.999)) - 0.9) < 2e-3
    values = radiance.reshape(-1)
    for percentile in (99.9, 50.0, 100.0):  # exactly the rank statistic, top and middle included
        rank = -(-round(percentile * 10) * values.numel() // 1000)  # ceil(p n / 100) in integers
        assert auto_exposure(radiance, percentile) == 0.9 / float(torch.kthvalue(values, rank).values)
    with pytest.raises(InputError, match="NaN"):  # refused wherever it would rank
        auto_exposure(torch.tensor([1.0, math.nan, 2.0, 3.0]), 50.0)
    assert auto_exposure(torch.tensor([1, 2, 3])) == 0.9 / 3.0  # integer radiance is read as float
    # The nearest rank of 1000 values is the 999th: in floats, ceil(99.9 / 100 * 1000) took the 1000th,
    # so one bright outlier set the exposure.
    assert auto_exposure(torch.arange(1.0, 1001.0)) == 0.9 / 999
    # A full-resolution stack's worth of values goes through candidates first: the same rank statistic.
    from capture_sim.simulator import LARGE_SELECTION, auto_exposure_at

    large = torch.rand(LARGE_SELECTION, generator=torch.Generator().manual_seed(5)) ** 4
    large[::7] = 0.5  # ties
    for percentile in (99.9, 90.0):
        rank = -(-round(percentile * 10) * large.numel() // 1000)
        exposure, index = auto_exposure_at(large, percentile)
        assert exposure == 0.9 / float(torch.kthvalue(large, rank).values) == 0.9 / float(large[index])
    assert auto_exposure(torch.cat([torch.ones(999), torch.tensor([1000.0])])) == 0.9
    assert auto_exposure(torch.zeros(2, 10, 3)) == 1.0
    # A scene scaled past float32's range has no usable exposure: said, not returned as 0 or 1.
    for scale in (math.inf, 1e-42):
        with pytest.raises(InputError, match="outside the range of torch.float32.*rescale the scene"):
            auto_exposure(torch.full((2, 10, 3), scale))
    assert auto_exposure(torch.full((2, 10, 3), 1e-30)) == pytest.approx(0.9e30)  # tiny units are fine


def test_generator_must_be_a_torch_generator():
    from capture_sim.errors import InputError
    from capture_sim.rig import NoiseModel
    from capture_sim.simulator import sensor

    with pytest.raises(InputError, match="generator must be a torch.Generator"):
        sensor(torch.full((4,), 0.5), NoiseModel(1e-4, 1e-3), 12, generator=0)


def test_noise_variance_matches_model():
    noise = NoiseModel(shot=1e-4, read_std=5e-4)
    generator = torch.Generator().manual_seed(0)
    for level in (0.05, 0.5):
        signal = torch.full((100_000,), level, dtype=torch.float64)
        captured = sensor(signal, noise, bit_depth=None, generator=generator)
        expected = noise.shot * level + noise.read_std**2
        assert abs(float(captured.var()) / expected - 1.0) < 0.05
        assert abs(float(captured.mean()) - level) < 4 * np.sqrt(expected / 1e5)


def test_float16_signal_gets_the_noise_of_the_model():
    """float16's smallest normal used to floor the variance far above the read noise."""
    noise = NoiseModel(shot=1e-4, read_std=5e-4)
    signal = torch.full((200_000,), 0.1, dtype=torch.float16)
    captured = sensor(signal, noise, bit_depth=None, generator=torch.Generator().manual_seed(0))
    assert captured.dtype == torch.float32
    assert abs(float(captured.std()) / math.sqrt(noise.shot * 0.1 + noise.read_std**2) - 1.0) < 0.05


def test_noise_is_reproducible_with_seed(tiny_rig):
    transport = light_transport(_random_stack(tiny_rig))
    patterns = torch.rand(2, tiny_rig.rows, tiny_rig.cols, 3)
    runs = [simulate(patterns, transport, tiny_rig, generator=torch.Generator().manual_seed(5)).captures for _ in range(2)]
    other = simulate(patterns, transport, tiny_rig, generator=torch.Generator().manual_seed(6)).captures
    assert torch.equal(runs[0], runs[1])
    assert not torch.equal(runs[0], other)


def test_one_seed_gives_the_same_noise_in_float32_and_float64():
    noise = NoiseModel(shot=1e-4, read_std=5e-4)
    signal = torch.linspace(0.0, 0.8, 1000, dtype=torch.float64)
    wide, narrow = (sensor(signal.to(dtype), noise, None, torch.Generator().manual_seed(5)) for dtype in (torch.float64, torch.float32))
    assert float((wide - narrow.double()).abs().max()) < 1e-6  # different draws differ by ~1e-2


def test_rig_and_noise_model_number_types():
    """Numpy numbers are numbers; a bit depth must be a whole number (not 12.5, not True)."""
    import dataclasses

    assert NoiseModel(np.float32(1e-4), np.float64(5e-4)).shot == pytest.approx(1e-4)
    rig = load_rig()
    assert dataclasses.replace(rig, bit_depth=np.int64(10)).bit_depth == 10
    for bad in (12.5, True, 0, 17, 24):  # 24 bits: neighbouring levels merged in float32
        with pytest.raises(InputError, match="bit_depth must be a whole number in 1..16"):
            dataclasses.replace(rig, bit_depth=bad)
    assert dataclasses.replace(rig, bit_depth=16).bit_depth == 16
    levels = sensor(torch.arange(65536, dtype=torch.float64) / 65535, None, bit_depth=16).float()
    assert torch.unique(levels).numel() == 65536  # every 16-bit level stays distinct in float32
    with pytest.raises(InputError, match="bit_depth must be None or a whole number in 1..16, got 24"):
        sensor(levels, None, bit_depth=24)


def test_rig_file_with_both_light_positions_and_a_panel_is_refused(tmp_path):
    from capture_sim.rig import RIG_DIR

    text = (RIG_DIR / "panel-32in-5x10.toml").read_text().replace("[display.panel]", "light_positions = [[[0.0, 0.0, 0.0]]]\n\n[display.panel]")
    (tmp_path / "both.toml").write_text(text)
    with pytest.raises(InputError, match="both light_positions and a \\[display.panel\\] table"):
        load_rig(tmp_path / "both.toml")
    ragged = (RIG_DIR / "panel-32in-5x10.toml").read_text().replace("backlight = 0.03", "backlight = [[0.1, 0.2], [0.3]]")
    (tmp_path / "ragged.toml").write_text(ragged)
    with pytest.raises(InputError, match="display backlight must be a list of equal-length lists of numbers"):
        load_rig(tmp_path / "ragged.toml")
    # A copied file keeps the preset's `name`: the message names the file too.
    (tmp_path / "gamma0.toml").write_text((RIG_DIR / "panel-32in-5x10.toml").read_text().replace("gamma = 2.2", "gamma = 0.0"))
    with pytest.raises(InputError, match=r"rig panel-32in-5x10: display gamma .* \(rig file .*gamma0.toml\)$"):
        load_rig(tmp_path / "gamma0.toml")


def test_light_transport_of_a_stack_that_requires_grad_warns_nothing():
    import warnings

    stack = torch.rand(4, 3, 5, 3, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert light_transport(stack).num_lights == 4


def test_quantisation_levels_and_straight_through_gradient():
    signal = torch.linspace(0.0, 1.0, 101, dtype=torch.float64, requires_grad=True)
    captured = sensor(signal, None, bit_depth=4)
    levels = captured.detach() * 15
    torch.testing.assert_close(levels, levels.round())
    captured.sum().backward()
    assert torch.all(signal.grad == 1.0)  # identity inside [0, 1]


def test_clip_gradient_surrogate_points_out_of_saturation():
    signal = torch.tensor([1.002, 1.5, -0.002], dtype=torch.float64, requires_grad=True)
    captured = sensor(signal, None, None)
    assert torch.equal(captured.detach(), torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))
    captured.sum().backward()
    assert 0.5 < signal.grad[0] < 1 and signal.grad[1] < 1e-6 and 0.5 < signal.grad[2] < 1


def test_simulator_gradcheck(tiny_rig):
    olat = torch.as_tensor(_random_stack(tiny_rig, dtype=np.float64)) * 0.2
    transport = light_transport(olat, dtype=torch.float64)
    patterns = (0.2 + 0.6 * torch.rand(2, tiny_rig.rows, tiny_rig.cols, 3, dtype=torch.float64)).requires_grad_()

    def captured(values):
        generator = torch.Generator().manual_seed(0)
        return simulate(values, transport, tiny_rig, exposure=0.5, noise=NoiseModel(), bit_depth=None, generator=generator).captures

    assert torch.autograd.gradcheck(captured, (patterns,), eps=1e-6, atol=1e-6)


def test_bad_inputs_raise_clear_errors(tiny_rig):
    transport = light_transport(_random_stack(tiny_rig))
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        simulate(torch.full((1, tiny_rig.rows, tiny_rig.cols, 3), 1.5), transport, tiny_rig)
    with pytest.raises(InputError, match="shape"):
        simulate(torch.rand(1, 3, 3, 3), transport, tiny_rig)
    with pytest.raises(InputError, match="NaN"):
        bad = _random_stack(tiny_rig)
        bad[0, 0, 0, 0] = np.nan
        light_transport(bad)
    with pytest.raises(InputError, match="infinite"):  # checked light by light, as NaN
        bad = _random_stack(tiny_rig)
        bad[-1, 0, 0, 2] = np.inf
        light_transport(bad)
    with pytest.raises(InputError, match="exposure"):
        simulate(torch.rand(1, tiny_rig.rows, tiny_rig.cols, 3), transport, tiny_rig, exposure=-1.0)
    with pytest.raises(InputError, match="exposure must be a positive number"):  # float(True) would be 1
        simulate(torch.rand(1, tiny_rig.rows, tiny_rig.cols, 3), transport, tiny_rig, exposure=True)
    other_rig = tiny_rig.replace(light_positions=tiny_rig.light_positions[:1], backlight=tiny_rig.backlight[:1])
    with pytest.raises(InputError, match="lights"):
        simulate(torch.rand(1, 1, 3, 3), transport, other_rig)
    with pytest.raises(InputError, match="at least one pattern"):
        simulate(torch.rand(0, tiny_rig.rows, tiny_rig.cols, 3), transport, tiny_rig)
    with pytest.raises(InputError, match="NoiseModel"):
        simulate(torch.rand(1, tiny_rig.rows, tiny_rig.cols, 3), transport, tiny_rig, noise="default")
    assert auto_exposure(torch.zeros(0, 0, 3)) == 1.0


def test_review_fixes_for_sensor_rig_and_files(tiny_rig, tmp_path):
    """Zero noise variance keeps finite gradients; bad rig values, numpy patterns, fitted falloffs
    and written file permissions behave."""
    import dataclasses
    import os

    from capture_sim.atomic import write_text
    from capture_sim.render import render_olat
    from capture_sim.rig import Falloff, rig_from_dict

    signal = torch.tensor([0.0, 0.3, 0.9], dtype=torch.float64, requires_grad=True)
    for model in (NoiseModel().scaled(0.0), NoiseModel(shot=1e-4, read_std=0.0)):
        sensor(signal, model, None, torch.Generator().manual_seed(0)).sum().backward()
        assert torch.isfinite(signal.grad).all()
        signal.grad = None
    for bad in (dict(shot=-1e-4), dict(read_std=float("nan"))):
        with pytest.raises(InputError):
            NoiseModel(**bad)
    with pytest.raises(InputError):
        dataclasses.replace(tiny_rig, gamma=float("nan"))
    with pytest.raises(InputError):
        rig_from_dict({"camera": {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "height": 4, "width": 4},
                       "display": {"panel": {"rows": 2, "cols": 2}}, "exposure": "Auto"}, "bad")
    stack = _random_stack(tiny_rig)
    transport = light_transport(stack)
    patterns = np.full((2, tiny_rig.rows, tiny_rig.cols, 3), 0.5)
    assert torch.isfinite(simulate(patterns, transport, tiny_rig, exposure=1.0, noise=None).captures).all()
    with pytest.raises(InputError):
        simulate(torch.as_tensor(patterns), transport, tiny_rig, exposure="Auto")
    points = torch.tensor([[0.0, 0.0, 0.5]])
    lights = torch.tensor([[0.1, 0.0, 0.2]])  # 0.32 m away
    shading = (points, torch.tensor([[0.0, 0.0, -1.0]]), lights, torch.ones(1, 1), torch.ones(1, 3), torch.zeros(1), torch.ones(1))
    # the reference rig's fitted falloff is negative below 0.608 m; the message names it
    with pytest.raises(InputError, match=re.escape("falloff fitted (a=-5.458, b=14.7449) is not positive")):
        render_olat(*shading, Falloff("fitted", -5.4580, 14.7449))
    # any falloff callable: one returning a number or a numpy array renders as the tensor one does
    reference = render_olat(*shading, lambda d: 1.0 / d**2)[0]
    for falloff in (lambda d: float(1.0 / d.item() ** 2), lambda d: (1.0 / d**2).numpy()):
        assert torch.allclose(render_olat(*shading, falloff)[0], reference)
    # NaN, negative albedo, wrong shapes and an unknown Fresnel are refused, not rendered.
    bad = {1: torch.tensor([[math.nan, 0.0, -1.0]]), 2: torch.zeros(1, 2), 3: torch.ones(1, 2), 4: -torch.ones(1, 3), 6: torch.full((1,), 2.0)}
    for position, value in bad.items():
        with pytest.raises(InputError):
            render_olat(*[value if index == position else item for index, item in enumerate(shading)])
    with pytest.raises(InputError, match="visibility"):
        render_olat(*shading, visibility=torch.full((1, 1), math.nan))
    with pytest.raises(InputError, match="fresnel must be one of"):
        render_olat(*shading, fresnel="schlik")
    with pytest.raises(InputError, match="diffuse_albedo: expected a torch tensor"):
        render_olat(*shading[:4], [[1.0, 1.0, 1.0]], *shading[5:])
    with pytest.raises(InputError, match="noise scale 1e\\+06 takes this rig's noise"):
        NoiseModel(shot=1e7).scaled(1e6)
    # one specular albedo and roughness for every basis (0-d) broadcast as before
    assert torch.equal(render_olat(*shading[:5], torch.tensor(0.0), torch.tensor(1.0))[0], reference)
    glossy = render_olat(*shading[:5], torch.full((1,), 0.5), torch.full((1,), 0.3), lambda d: 1.0 / d**2)[1]
    assert torch.equal(render_olat(*shading[:5], torch.tensor(0.5), torch.tensor(0.3), lambda d: 1.0 / d**2)[1], glossy)
    umask = os.umask(0o022)
    try:
        write_text(tmp_path / "a.txt", "x")
        assert (os.stat(tmp_path / "a.txt").st_mode & 0o777) == 0o644
    finally:
        os.umask(umask)


def test_half_precision_and_gamma_below_one_stay_finite(tiny_rig):
    """float16 quantisation at 16 bits overflowed (65535 levels), float16 radiance under auto
    exposure underflowed to a black scene, and d/dP (P + B)^gamma is infinite at P + B = 0."""
    import dataclasses

    assert torch.equal(sensor(torch.ones(3).half(), None, 16), torch.ones(3).half())
    assert torch.isfinite(sensor(torch.full((4,), 0.7).half(), None, np.int64(16))).all()  # numpy integers are bit depths too
    rng = np.random.default_rng(0)
    olat = rng.uniform(0, 1e-6, size=(tiny_rig.num_lights, tiny_rig.camera.height, tiny_rig.camera.width, 3)).astype(np.float32)
    transport = light_transport(olat)
    patterns = torch.rand(2, tiny_rig.rows, tiny_rig.cols, 3, generator=torch.Generator().manual_seed(0))
    single = simulate(patterns, transport, tiny_rig, exposure="auto", noise=None, bit_depth=None)
    half = simulate(patterns.half(), transport, tiny_rig, exposure="auto", noise=None, bit_depth=None)
    assert half.captures.dtype == torch.float32 and half.exposure == pytest.approx(single.exposure, rel=1e-2)
    dark_rig = dataclasses.replace(tiny_rig, backlight=np.zeros((tiny_rig.rows, tiny_rig.cols)), gamma=0.5)
    black = torch.zeros(2, tiny_rig.rows, tiny_rig.cols, 3, requires_grad=True)
    simulate(black, transport, dark_rig, exposure=1.0, noise=None, bit_depth=None).captures.sum().backward()
    assert torch.isfinite(black.grad).all()
    with pytest.raises(InputError):
        display_emission(torch.rand(3), torch.zeros(1), 2.2)


def test_panel_aspect_follows_the_panel_pixels_unless_stated():
    """A [display.panel] without ``aspect`` takes it from ``panel_pixels`` (square display pixels:
    16:10 here, where the old 16:9 default put the outer rows about 1 cm off); a stated aspect
    that disagrees with the pixels is warned."""
    import warnings

    from capture_sim.errors import DisplexWarning, forget_warnings
    from capture_sim.rig import panel_positions, rig_from_dict

    camera = {"fx": 100.0, "fy": 100.0, "cx": 15.5, "cy": 11.5, "height": 24, "width": 32}
    panel = {"rows": 6, "cols": 10, "diagonal_inch": 24.0}
    rig = rig_from_dict({"camera": camera, "display": {"panel": panel, "panel_pixels": [1200, 1920]}}, "desk")
    np.testing.assert_allclose(rig.light_positions, panel_positions(6, 10, 24.0, (1920.0, 1200.0)))
    height = rig.light_positions[-1, 0, 1] - rig.light_positions[0, 0, 1]
    assert height == pytest.approx(24 * 0.0254 * 10 / math.hypot(16, 10) * 5 / 6)
    odd = {"camera": camera, "display": {"panel": {**panel, "aspect": [16, 9]}, "panel_pixels": [1200, 1920]}}
    with pytest.warns(DisplexWarning, match=r"rig desk: \[display.panel\] aspect 16:9 differs from panel_pixels 1920 x 1200"):
        rig_from_dict(odd, "desk")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rig_from_dict(odd, "desk")
    assert not caught  # said once per command (``warn_once``) ...
    forget_warnings()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(2):  # ... but a warning raised as an error is not counted as said
            with pytest.raises(DisplexWarning):
                rig_from_dict(odd, "desk")


@pytest.mark.parametrize("shape, layout", [((37, 11, 3), None), ((1001, 3), None), ((3, 50, 7), (1, 2, 0)), ((2, 3, 1001), (2, 0, 1))])
def test_sensor_without_gradient_works_in_blocks_with_the_values_of_one_draw(monkeypatch, shape, layout):
    """Without gradient, ``sensor`` runs in blocks of about SENSOR_BLOCK values (a full-resolution
    OLAT capture took +3 GB of full-size temporaries) and draws the noise block by block: the values,
    dtype and memory layout must be those of the one-piece path (the gradient path)."""
    import capture_sim.simulator as simulator

    drawn = []
    draw = simulator._standard_normal
    monkeypatch.setattr(simulator, "_standard_normal", lambda count, *rest: drawn.append(count) or draw(count, *rest))
    monkeypatch.setattr(simulator, "SENSOR_BLOCK", 64)
    signal = torch.rand(shape, generator=torch.Generator().manual_seed(1)) * 1.2 - 0.1
    if layout is not None:
        signal = signal.permute(*layout)
    for noise, bits, dtype in ((NoiseModel(1e-3, 1e-2), 12, torch.float32), (None, 8, torch.float32), (NoiseModel(), None, torch.float64), (NoiseModel(), 10, torch.float16)):
        drawn.clear()
        typed = signal.to(dtype)
        whole = sensor(typed.clone().requires_grad_(), noise, bits, torch.Generator().manual_seed(3)).detach()
        if noise is not None:
            assert drawn == [typed.numel()]
        drawn.clear()
        with torch.no_grad():
            blocked = sensor(typed, noise, bits, torch.Generator().manual_seed(3))
        assert torch.equal(blocked, whole) and blocked.dtype == whole.dtype and blocked.stride() == whole.stride()
        if noise is not None:
            assert len(drawn) > 1 and sum(drawn) == typed.numel()
            assert all(count % 16 == 0 for count in drawn[:-1]) and drawn[-1] >= 16 and max(drawn) <= 64 + 16 * 3 * 11


def test_sensor_blocks_cover_the_rows_in_whole_groups_of_16_values():
    from capture_sim.simulator import SENSOR_BLOCK, _draw_blocks

    for count, per_row in ((1, 1), (17, 1), (SENSOR_BLOCK + 5, 1), (3 * SENSOR_BLOCK + 20, 1), (144, 313_344 * 3), (1000, 3), (7, SENSOR_BLOCK * 2 + 1)):
        blocks = _draw_blocks(count, per_row)
        assert blocks[0][0] == 0 and blocks[-1][1] == count
        assert all(left[1] == right[0] for left, right in zip(blocks, blocks[1:]))
        assert all((stop - start) * per_row % 16 == 0 for start, stop in blocks[:-1])
        assert len(blocks) == 1 or (blocks[-1][1] - blocks[-1][0]) * per_row >= 16


def test_all_finite_finds_every_non_finite_value_whatever_the_dtype_and_layout():
    """The one-pass test behind check_array (min and max, which NaN and infinities reach) must
    agree with torch.isfinite on every dtype, position and layout."""
    from capture_sim.errors import all_finite, check_array

    for dtype in (torch.float16, torch.bfloat16, torch.float32, torch.float64):
        base = torch.rand(5, 7, 3, dtype=dtype)
        assert all_finite(base) and all_finite(base.permute(2, 0, 1)) and all_finite(base[:, ::2])
        for bad in (float("nan"), float("inf"), -float("inf")):
            for position in ((0, 0, 0), (4, 6, 2), (2, 3, 1)):
                values = base.clone()
                values[position] = bad
                assert not all_finite(values) and not all_finite(values.permute(2, 0, 1))
                with pytest.raises(InputError, match="patterns: contains NaN or infinite values"):
                    check_array("patterns", values)
    assert all_finite(torch.zeros(0)) and all_finite(torch.arange(4)) and all_finite(torch.ones(3, dtype=torch.bool))
    assert all_finite(torch.tensor([1 + 2j])) and not all_finite(torch.tensor([complex("nan")])) and not all_finite(torch.tensor([complex(1, float("inf"))]))
    with pytest.raises(InputError, match=r"values must lie in \[0, 1\], found \[-0.5, 2.0\]"):
        check_array("patterns", torch.tensor([0.5, -0.5, 2.0]), value_range=(0.0, 1.0))
