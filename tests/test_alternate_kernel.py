"""The compiled alternation to convergence against its torch reference (pixel_solve.alternate)."""
import numpy as np
import pytest
import torch

from reconstruct import alternate_kernel, compiled
from reconstruct.pixel_solve import Moments, normalised_moments
from reconstruct.pixel_solve import alternate as reference
from tests.conftest import arrays_from_forked_process


def _inputs(count: int, dtype, seed: int = 0, nearly_rank_two: bool = False):
    """Start albedo (3, N) and the moments of M = 4 random lighting vectors with noisy captures;
    a few pixels dark (all-zero vectors). ``nearly_rank_two`` makes every pixel's third lighting
    direction almost the first's: slowly contracting alternations that stall in float32."""
    generator = torch.Generator().manual_seed(seed)
    vectors = torch.randn(4, 3, 3, count, generator=generator, dtype=torch.float64)
    if nearly_rank_two:
        vectors[..., 2, :] = 0.999 * vectors[..., 0, :] + 1e-3 * vectors[..., 2, :]
    vectors[..., :3] = 0
    normal = torch.randn(3, count, generator=generator, dtype=torch.float64)
    normal = normal / normal.norm(dim=0)
    albedo = torch.rand(3, count, generator=generator, dtype=torch.float64) + 0.1
    captures = albedo[None] * (vectors * normal[None, None]).sum(2) + 0.01 * torch.randn(4, 3, count, generator=generator, dtype=torch.float64)
    scale = captures.abs().amax(dim=(0, 1)).clamp_min(1e-3)
    moments = normalised_moments(vectors, captures, torch.ones(4, 3, count, dtype=torch.float64), scale).to(dtype)
    return (captures.amax(0) / scale).clamp_min(0).to(dtype), moments


_BITS = {torch.float32: torch.int32, torch.float64: torch.int64}


def _same_bits(result, expected) -> bool:
    """Results (albedo, normal, converged) equal bit for bit: -0.0 and +0.0 differ here, unlike in
    torch.equal."""
    return all(value.dtype == other.dtype and (torch.equal(value.view(_BITS[value.dtype]), other.view(_BITS[other.dtype]))
                                               if value.dtype in _BITS else torch.equal(value, other))
               for value, other in zip(result, expected, strict=True))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("nearly_rank_two", [False, True])
@pytest.mark.parametrize("max_alternations", [1, 2, 5, 50])
def test_kernel_equals_the_reference(dtype, nearly_rank_two, max_alternations):
    # The same float operations in the same order: equal values and flags, bit for bit.
    albedo, moments = _inputs(3000, dtype, nearly_rank_two=nearly_rank_two)
    expected = reference(albedo, moments, 1e-4, 0.05, max_alternations)
    with torch.no_grad():
        result = alternate_kernel.alternate(albedo, moments, 1e-4, 0.05, max_alternations)
    assert [value.dtype for value in result] == [dtype, dtype, torch.bool]
    assert _same_bits(result, expected)
    if max_alternations == 50:
        assert 0 < int(result[2].sum()) < 3000 or not nearly_rank_two


def test_float32_pixels_that_stall_are_iterated_in_float64(monkeypatch):
    albedo, moments = _inputs(3000, torch.float32, nearly_rank_two=True)
    widened = []
    original = alternate_kernel.alternate

    def counting(albedo, moments, *arguments):
        widened.append((albedo.dtype, albedo.shape[1]))
        return original(albedo, moments, *arguments)

    monkeypatch.setattr(alternate_kernel, "alternate", counting)
    result = original(albedo, moments, 1e-4, 0.05, 50)
    assert widened and widened[0][0] == torch.float64 and widened[0][1] > 0
    assert _same_bits(result, reference(albedo, moments, 1e-4, 0.05, 50))


def test_strided_empty_and_gradient_inputs():
    albedo, moments = _inputs(200, torch.float64, seed=3)
    every_other = Moments(*(getattr(moments, name)[..., ::2] for name in Moments._FIELDS))
    assert not every_other.moment.is_contiguous()
    assert _same_bits(alternate_kernel.alternate(albedo[:, ::2], every_other, 1e-4, 0.05, 20), reference(albedo[:, ::2], every_other, 1e-4, 0.05, 20))
    empty = alternate_kernel.alternate(albedo[:, :0], Moments(*(getattr(moments, name)[..., :0] for name in Moments._FIELDS)), 1e-4, 0.05, 20)
    assert [tuple(value.shape) for value in empty] == [(3, 0), (3, 0), (0,)]
    # Inputs that need a gradient take the reference, which keeps the graph.
    tracked = albedo.clone().requires_grad_()
    result = alternate_kernel.alternate(tracked, moments, 1e-4, 0.05, 3)
    assert result[0].requires_grad
    assert _same_bits([value.detach() for value in result], reference(albedo, moments, 1e-4, 0.05, 3))


def test_kernel_refuses_what_it_cannot_read():
    albedo, moments = _inputs(10, torch.float32)
    assert alternate_kernel.kernel_applies(albedo, moments)
    assert not alternate_kernel.kernel_applies(albedo.double(), moments)  # mixed dtypes
    assert not alternate_kernel.kernel_applies(albedo[:, :9], moments)  # a short pixel axis
    short = Moments(moments.moment[:, :5], *(getattr(moments, name) for name in Moments._FIELDS[1:]))
    assert not alternate_kernel.kernel_applies(albedo, short)
    half = Moments(*(getattr(moments, name).half() for name in Moments._FIELDS))
    assert not alternate_kernel.kernel_applies(albedo.half(), half)
    for name in ("moment", "projection"):  # the kernels read both over the albedo's pixel count
        for count in (9, 11):
            resized = torch.zeros(*getattr(moments, name).shape[:-1], count)
            changed = Moments(*(resized if field == name else getattr(moments, field) for field in Moments._FIELDS))
            assert not alternate_kernel.kernel_applies(albedo, changed), (name, count)
        wide = Moments(*(getattr(moments, field).double() if field == name else getattr(moments, field) for field in Moments._FIELDS))
        assert not alternate_kernel.kernel_applies(albedo, wide), name


def test_zero_albedo_and_dark_pixels_keep_the_sign_of_zero():
    # torch's sums start from +0.0: a sum of -0.0 terms is +0.0 (the kernel's sums start so too).
    albedo, moments = _inputs(500, torch.float32, seed=5)
    with torch.no_grad():
        assert _same_bits(alternate_kernel.alternate(torch.zeros_like(albedo), moments, 1e-4, 0.05, 20),
                          reference(torch.zeros_like(albedo), moments, 1e-4, 0.05, 20))
        assert _same_bits(alternate_kernel.alternate(-albedo, moments, 1e-4, 0.05, 20), reference(-albedo, moments, 1e-4, 0.05, 20))


def test_serial_kernel_in_a_forked_process_gives_the_same_values(monkeypatch):
    # compare forks its evaluation workers after the parallel kernel may have run (reconstruct.compiled).
    albedo, moments = _inputs(500, torch.float32, seed=7, nearly_rank_two=True)
    with torch.no_grad():
        parent = alternate_kernel.alternate(albedo, moments, 1e-4, 0.05, 50)

    def serial_in_child():
        assert compiled.forked()
        return [*alternate_kernel.alternate(albedo, moments, 1e-4, 0.05, 50)]

    def no_reference(*arguments):
        raise AssertionError("the forked process took the torch reference, not the serial kernel")

    monkeypatch.setattr(alternate_kernel, "reference_alternate", no_reference)  # the child inherits it
    values = arrays_from_forked_process(serial_in_child)
    assert all(np.array_equal(value, expected.numpy()) for value, expected in zip(values, parent, strict=True))
