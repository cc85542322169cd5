import numpy as np
import pytest
import torch

from capture_sim.display import display_emission
from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from capture_sim.synth import lambertian_sphere
from reconstruct import lighting as lighting_module
from reconstruct.lighting import SYMMETRIC_PAIRS, extreme_lights
from reconstruct.metrics import angular_error_deg
from reconstruct.unrolled_alternation import _step, alternate, symmetric_direction
from reconstruct.unrolled_ps import UnrolledPSConfig, light_reach, solve_ps_unrolled
from tests.conftest import arrays_from_forked_process
from train.scene_pixels import scene_pixels


def _sphere_captures(patterns, dtype=torch.float64):
    rig = load_rig()
    pixels = scene_pixels(lambertian_sphere(rig, height=32, width=38), rig, require_normals=True)
    emission = display_emission(torch.as_tensor(patterns, dtype=dtype), rig.backlight_flat(dtype), rig.gamma)
    transport = pixels.transport.matrix.to(dtype)
    captures = torch.matmul(emission.permute(2, 0, 1), transport).permute(1, 2, 0)
    scale = 0.9 / float(captures.max())
    return pixels, captures * scale, emission * scale


def test_adjugate_solve_matches_linalg():
    generator = torch.Generator().manual_seed(0)
    factor = torch.randn(50, 3, 3, dtype=torch.float64, generator=generator)
    system = factor @ factor.transpose(1, 2) + 0.1 * torch.eye(3, dtype=torch.float64)
    rhs = torch.randn(50, 3, dtype=torch.float64, generator=generator)
    rows, cols = zip(*SYMMETRIC_PAIRS)
    unique = system[:, rows, cols].T  # (6, N): the solver's storage of symmetric systems
    torch.testing.assert_close(symmetric_direction(unique, rhs.T).T, torch.linalg.solve(system, rhs))
    # Only |det| is used, so a determinant that rounds negative cannot flip the direction: the
    # adjugate of -S equals that of S, and so does the result.
    torch.testing.assert_close(symmetric_direction(-unique, rhs.T), symmetric_direction(unique, rhs.T))


def _alternation_inputs(count=40, seed=3):
    generator = torch.Generator().manual_seed(seed)
    vectors = torch.randn(4, 3, 3, count, dtype=torch.float64, generator=generator)
    captures = torch.rand(4, 3, count, dtype=torch.float64, generator=generator)
    captures[:, 0, :5] *= -1  # channel 0 of 5 pixels fits a negative albedo: clamped to 0
    rows, cols = zip(*SYMMETRIC_PAIRS)
    moments = torch.einsum("mcin,mcjn->cijn", vectors, vectors)[:, rows, cols]  # (3c, 6, N)
    rhs = torch.einsum("mcin,mcn->cin", vectors, captures)
    rhs[:, :, 7] = 0  # a pixel with no light: zero direction, keeps its normal
    normal = torch.nn.functional.normalize(torch.randn(3, count, dtype=torch.float64, generator=generator), dim=0)
    return normal, moments, rhs


def test_alternation_backward_matches_autograd():
    # The hand-written backward against autograd through the same steps, over two chained
    # alternations with clamped albedo and a dark pixel.
    normal, moments, rhs = _alternation_inputs()
    weights = torch.randn(2, 3, 40, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    grads = []
    for hand_written in (True, False):
        inputs = [value.clone().requires_grad_() for value in (normal, moments, rhs)]
        if hand_written:
            new_normal, albedo = alternate(*inputs[:1], None, *inputs[1:], 1e-6, 2)
        else:
            tiny = 1e-12 * moments.abs().amax() + torch.finfo(torch.float64).tiny ** 0.5
            new_normal, albedo = _step(*inputs, 1e-6, tiny)
            new_normal, albedo = _step(new_normal, *inputs[1:], 1e-6, tiny)
        ((new_normal * weights[0]).sum() + (albedo * weights[1]).sum()).backward()
        grads.append([value.grad for value in inputs])
    assert all(torch.isfinite(grad).all() for grad in grads[0])
    for hand, auto in zip(*grads):
        torch.testing.assert_close(hand, auto, rtol=1e-9, atol=1e-12)


def _reference_alternations(normal, moments, rhs, steps, damping=1e-6):
    tiny = 1e-12 * moments.abs().amax() + torch.finfo(moments.dtype).tiny ** 0.5
    for _ in range(steps):
        normal, albedo = _step(normal, moments, rhs, damping, tiny)
    return normal, albedo


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_alternation_matches_the_torch_reference(dtype):
    # Clamped albedo channels and a dark pixel among random pixels; moments given as a
    # non-contiguous view (the kernels take contiguous copies).
    normal, moments, rhs = (value.to(dtype) for value in _alternation_inputs(count=300, seed=5))
    moments = moments.permute(2, 0, 1).contiguous().permute(1, 2, 0)
    assert not moments.is_contiguous()
    with torch.no_grad():
        compiled = alternate(normal, None, moments, rhs, 1e-6, 3)
    for value, expected in zip(compiled, _reference_alternations(normal, moments, rhs, 3)):
        assert value.dtype == dtype and value.is_contiguous()
        torch.testing.assert_close(value, expected)
    # Pixels are independent: the thread count changes nothing.
    previous = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with torch.no_grad():
            single = alternate(normal, None, moments, rhs, 1e-6, 3)
    finally:
        torch.set_num_threads(previous)
    assert all(torch.equal(one, many) for one, many in zip(single, compiled))


def test_compiled_alternation_refuses_shapes_it_would_read_past():
    # Compiled code has no bounds checks: a short axis would read or write out of bounds.
    from reconstruct.alternation_kernels import alternation_backward, alternation_forward

    normal, moments, rhs = _alternation_inputs(count=20, seed=5)
    for bad in ((normal[:2], moments, rhs), (normal, moments[:2], rhs), (normal, moments[:, :5], rhs),
                (normal, moments[..., :10], rhs), (normal, moments, rhs[:, :2]), (normal, moments.float(), rhs)):
        with pytest.raises(ValueError, match="alternation kernels need"):
            alternation_forward(*bad, 1e-6, 1e-20)
    with pytest.raises(ValueError, match="alternation kernels need"):
        alternation_backward(normal, moments, rhs, 1e-6, 1e-20, normal[:, :10], None)
    with pytest.raises(ValueError, match="alternation kernels need"):
        alternation_backward(normal, moments, rhs, 1e-6, 1e-20, normal, rhs[:, 0, :10])
    with pytest.raises(ValueError, match="float32 or float64"):
        alternation_forward(normal.half(), moments.half(), rhs.half(), 1e-6, 1e-20)


def test_compiled_alternation_keeps_nan_and_signed_zero_as_the_reference():
    # The albedo's clamp is torch's clamp_min: NaN stays NaN (a bad input is not hidden as a dark
    # pixel) and a ratio of -0.0 stays -0.0.
    normal, moments, rhs = _alternation_inputs(count=20, seed=5)
    moments, rhs = moments.clone(), rhs.clone()
    moments[0, 1, 4] = float("nan")
    rhs[:, :, 7] = 0.0
    normal[:, 7] = -normal[:, 7].abs() - 0.1  # n . r_c = -0.0 for every channel
    from reconstruct.alternation_kernels import alternation_forward

    compiled = alternation_forward(normal, moments, rhs, 1e-6, 1e-20)
    expected = _step(normal, moments, rhs, 1e-6, 1e-20)
    assert torch.isnan(compiled[1][0, 4]) and torch.isnan(expected[1][0, 4])
    assert torch.isfinite(compiled[1][1:, 4]).all()  # the other channels of that pixel are solved
    assert torch.equal(torch.signbit(compiled[1][:, 7]), torch.signbit(expected[1][:, 7]))
    assert bool(torch.signbit(compiled[1][:, 7]).all())


def test_alternation_refuses_double_backward():
    normal, moments, rhs = _alternation_inputs(count=10, seed=5)
    moments.requires_grad_()
    new_normal, _ = alternate(normal, None, moments, rhs, 1e-6, 1)
    # Without the refusal the gradient would silently come back as a constant.
    with pytest.raises(RuntimeError, match="no second derivative"):
        torch.autograd.grad(new_normal.sum(), moments, create_graph=True)


def test_kernels_compile_without_a_writable_cache_folder(monkeypatch):
    # numba raises on cache=True when neither the source's folder nor the user's cache is
    # writable; the module must still load (and compile in each process).
    import importlib.util

    import numba

    import reconstruct.alternation_kernels as kernels

    real = numba.njit

    def njit_without_cache(*args, **options):
        if options.get("cache"):
            raise RuntimeError("cannot cache function: no locator available")
        return real(*args, **options)

    monkeypatch.setattr(numba, "njit", njit_without_cache)
    spec = importlib.util.spec_from_file_location("kernels_without_cache", kernels.__file__)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    normal, moments, rhs = _alternation_inputs(count=9, seed=5)
    assert all(torch.equal(one, other) for one, other in
               zip(module.alternation_forward(normal, moments, rhs, 1e-6, 1e-20), kernels.alternation_forward(normal, moments, rhs, 1e-6, 1e-20)))


def test_compiled_alternation_runs_in_a_forked_process():
    # compare forks its evaluation workers; GNU OpenMP aborts a forked child of a process that ran
    # parallel kernels, so forked processes take the serial kernels.
    normal, moments, rhs = _alternation_inputs(count=300, seed=5)
    with torch.no_grad():
        parent = alternate(normal, None, moments, rhs, 1e-6, 2)
    values = arrays_from_forked_process(lambda: alternate(normal, None, moments, rhs, 1e-6, 2))
    assert all(np.array_equal(value, expected.numpy()) for value, expected in zip(values, parent))


def test_alternation_backward_drops_the_terms_of_masked_pixels():
    # A clamped albedo channel whose terms overflow float32 must not turn the pixel's gradient
    # into NaN (inf * 0): the masks select, as autograd's clamp does.
    normal = torch.tensor([[0.0], [0.0], [1.0]])
    moments = torch.tensor([1.0, 1, 1, 0, 0, 0]).repeat(3, 1)[..., None]
    rhs = torch.tensor([[-1e33] * 3, [3e-4, 2e-4, 1e-3], [1e-4, -2e-4, 1e-3]])[..., None]
    inputs = [value.clone().requires_grad_() for value in (normal, moments, rhs)]
    new_normal, albedo = alternate(inputs[0], None, inputs[1], inputs[2], 1e-6, 1)
    (new_normal[0].sum() + albedo.sum()).backward()
    assert all(torch.isfinite(value.grad).all() for value in inputs)
    empty = alternate(torch.zeros(3, 0), None, torch.zeros(3, 6, 0), torch.zeros(3, 3, 0), 1e-6, 2)
    assert [tuple(value.shape) for value in empty] == [(3, 0), (3, 0)]


def test_gradcheck_alternation():
    # Pixels whose normal moves (a dark one keeps its input normal, detached by design), among
    # them ones with a clamped albedo channel.
    normal, moments, rhs = _alternation_inputs()
    moved = alternate(normal, None, moments, rhs, 1e-6, 2)[1].amax(0) > 0
    pixels = torch.nonzero(moved).squeeze(1)[:6]
    assert int(pixels.min()) < 5
    normal, moments, rhs = (value[..., pixels].clone().requires_grad_() for value in (normal, moments, rhs))
    assert torch.autograd.gradcheck(lambda *inputs: alternate(inputs[0], None, *inputs[1:], 1e-6, 2), (normal, moments, rhs), eps=1e-6, atol=1e-6)


def test_noise_free_sphere_recovers_normals():
    patterns = np.load("patterns/data/ddps/initial_mono_gradient.npy")
    pixels, captures, emission = _sphere_captures(patterns)
    normal, albedo = solve_ps_unrolled(captures, emission, pixels.points, pixels.lights(), pixels.rig.falloff, UnrolledPSConfig(alternations=20, shadow_iterations=6))
    assert float(angular_error_deg(normal, pixels.normal.double()).mean()) < 0.5
    assert torch.isfinite(albedo).all() and (albedo >= 0).all()


def test_gradcheck_unrolled():
    rig = load_rig()
    generator = torch.Generator().manual_seed(1)
    points = torch.tensor([[0.01, 0.02, 0.5], [-0.02, 0.0, 0.48], [0.0, -0.03, 0.52]], dtype=torch.float64)
    lights = rig.lights(torch.float64)[::24]  # 6 lights
    emission = (0.2 + torch.rand(3, lights.shape[0], 3, dtype=torch.float64, generator=generator)).requires_grad_()
    captures = (0.1 + 0.5 * torch.rand(3, 3, 3, dtype=torch.float64, generator=generator)).requires_grad_()

    def normals(captures_in, emission_in):
        normal, albedo = solve_ps_unrolled(captures_in, emission_in, points, lights, rig.falloff, UnrolledPSConfig(shadow_iterations=1, alternations=0, grad_alternations=4))
        return normal, albedo

    assert torch.autograd.gradcheck(normals, (captures, emission), eps=1e-6, atol=1e-5)


def test_geometry_gets_no_gradient():
    """Points and lights are constants, as in solve_ps: lights that require grad got a partial,
    wrong gradient through the lighting matrix (its p_k term only)."""
    pixels, captures, emission = _sphere_captures(np.load("patterns/data/ddps/initial_mono_gradient.npy"))
    points, lights = pixels.points.double().requires_grad_(), pixels.lights().double().requires_grad_()
    normal, albedo = solve_ps_unrolled(captures, emission, points, lights, pixels.rig.falloff)
    assert not normal.requires_grad and not albedo.requires_grad


def test_degenerate_inputs_stay_finite():
    rig = load_rig()
    lights = rig.lights()
    points = torch.tensor([[0.0, 0.0, 0.5], [0.1, 0.1, 0.5], [0.0, 0.0, -0.1]])
    for emission in (torch.zeros(1, 144, 3), torch.ones(2, 144, 3), torch.rand(3, 144, 3)):
        emission = emission.requires_grad_()
        captures = torch.zeros(emission.shape[0], 3, 3, requires_grad=True)
        normal, albedo = solve_ps_unrolled(captures, emission, points, lights, rig.falloff)
        (normal.sum() + albedo.sum()).backward()
        assert torch.isfinite(normal).all() and torch.isfinite(albedo).all()
        assert torch.isfinite(emission.grad).all() and torch.isfinite(captures.grad).all()


def test_inputs_are_checked_and_any_float_dtype_works():
    import pytest

    from capture_sim.errors import InputError

    pixels, captures, emission = _sphere_captures(np.load("patterns/data/ddps/initial_mono_gradient.npy"), torch.float32)
    points, lights, falloff = pixels.points, pixels.lights(), pixels.rig.falloff
    reference, _ = solve_ps_unrolled(captures, emission, points, lights, falloff)
    for values, emitted in ((captures.half(), emission.half()), (captures, emission.double())):
        normal, albedo = solve_ps_unrolled(values, emitted, points, lights, falloff)
        assert torch.isfinite(normal).all() and torch.isfinite(albedo).all()
        assert angular_error_deg(normal.float(), reference).max() < 1.0
    normal, albedo = solve_ps_unrolled(captures[:, :0], emission, points[:0], lights, falloff)
    assert normal.shape == albedo.shape == (0, 3)
    bad_points = points.clone()
    bad_points[0, 0] = float("nan")
    for args in ((captures, emission, bad_points), (captures, -emission, points), (captures[:0], emission[:0], points)):
        with pytest.raises(InputError):
            solve_ps_unrolled(*args, lights, falloff)


def test_precomputed_reach_and_chunks_give_the_same_solution():
    patterns = np.load("patterns/data/ddps/initial_tri_gradient.npy")[:2]
    pixels, captures, emission = _sphere_captures(patterns, torch.float32)
    lights, falloff = pixels.lights(), pixels.rig.falloff
    plain, _ = solve_ps_unrolled(captures, emission, pixels.points, lights, falloff)
    reach = light_reach(pixels.points, lights, falloff)
    distance = torch.cdist(pixels.points, lights).T
    torch.testing.assert_close(reach, falloff(distance) / distance)
    chunked, _ = solve_ps_unrolled(captures, emission, pixels.points, lights, falloff, UnrolledPSConfig(chunk_pixels=100), reach=reach)
    torch.testing.assert_close(chunked, plain)
    with pytest.raises(InputError, match="floating-point torch tensor"):  # numpy passed the shape check, then failed in .to
        solve_ps_unrolled(captures, emission, pixels.points, lights, falloff, reach=reach.numpy())


def test_pixels_that_see_every_light_skip_the_shadow_test_without_changing_the_solution(monkeypatch):
    # The sphere's silhouette pixels have attached shadows, its centre none: both paths are used.
    patterns = np.load("patterns/data/ddps/initial_tri_gradient.npy")
    pixels, captures, emission = _sphere_captures(patterns)
    lights, falloff = pixels.lights().double(), pixels.rig.falloff
    points = pixels.points.double()
    config = UnrolledPSConfig(chunk_pixels=97)

    def solve_and_differentiate(part=slice(None)):
        inputs = (captures[:, part].clone().requires_grad_(), emission.clone().requires_grad_())
        normal, albedo = solve_ps_unrolled(*inputs, points[part], lights, falloff, config)
        (normal[:, 0].sum() + albedo.sum()).backward()
        return normal.detach(), albedo.detach(), *(value.grad for value in inputs)

    fast = solve_and_differentiate()
    whole = lighting_module.sees_all_lights(fast[0].T, points.T, lights[extreme_lights(lights)])
    assert 0.2 < float(whole.double().mean()) < 0.95
    centre = torch.nonzero(whole).squeeze(1)  # every update after the first keeps all of them
    fast_centre = solve_and_differentiate(centre)
    # Without the test every pixel takes the full shadow test at every update (the all-stale path).
    monkeypatch.setattr(lighting_module, "sees_all_lights", lambda normal, *_: torch.zeros(normal.shape[1], dtype=torch.bool))
    full = solve_and_differentiate()
    for fast_value, full_value in zip(fast + fast_centre, full + solve_and_differentiate(centre)):
        torch.testing.assert_close(fast_value, full_value, rtol=1e-9, atol=1e-9)


def test_saturated_captures_are_left_out():
    """Pixels with 1 to 3 of their 12 equations clipped keep an exact normal (using the clipped
    values would cost several degrees)."""
    pixels, captures, emission = _sphere_captures(np.load("patterns/data/ddps/initial_mono_gradient.npy"))
    clipped = (captures * 1.3).clamp(max=1.0)
    count = (clipped >= 0.999).sum(dim=(0, 2))
    some = (count > 0) & (count <= 3)
    assert some.sum() > 20
    config = UnrolledPSConfig(alternations=20, shadow_iterations=6)
    normal, _ = solve_ps_unrolled(clipped, emission * 1.3, pixels.points, pixels.lights(), pixels.rig.falloff, config)
    assert float(angular_error_deg(normal, pixels.normal.double())[some].max()) < 0.01
