import math

import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.rig import Falloff, load_rig
from reconstruct.lighting import LightField, differentiable_vectors, extreme_lights, lighting_matrix, sees_all_lights


def test_a_flat_grid_of_lights_has_its_four_corners_as_hull():
    y, x = torch.meshgrid(torch.linspace(-0.2, 0.2, 5), torch.linspace(-0.3, 0.3, 7), indexing="ij")
    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.8, 0.6], [0.0, -0.6, 0.8]])  # the display plane is tilted
    lights = torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(35)], dim=1) @ tilt.T + torch.tensor([0.0, -0.1, 0.05])
    assert extreme_lights(lights.double()).tolist() == [0, 6, 28, 34]
    line = torch.stack([torch.linspace(0, 1, 6), torch.zeros(6), torch.zeros(6)], dim=1)
    assert extreme_lights(line).tolist() == [0, 5]


def test_sees_all_lights_never_claims_a_shadowed_light_in_front():
    # The reference rig's display is curved: its hull has rows of lights, not four corners.
    lights = load_rig().lights(torch.float64)
    corners = lights[extreme_lights(lights)]
    generator = torch.Generator().manual_seed(0)
    count = 20000
    points = torch.stack([0.1 * torch.randn(count, generator=generator), 0.1 * torch.randn(count, generator=generator), 0.5 + 0.05 * torch.randn(count, generator=generator)])
    normal = torch.randn(3, count, generator=generator, dtype=torch.float64)
    normal[2] = -normal[2].abs()  # facing the camera and display, some at grazing angles
    normal = normal / normal.norm(dim=0)
    for dtype in (torch.float64, torch.float32):
        claimed = sees_all_lights(normal.to(dtype), points.to(dtype), corners.to(dtype))
        exact = ((lights.to(dtype) @ normal.to(dtype)) > (normal.to(dtype) * points.to(dtype)).sum(0)).all(0)
        assert not bool((claimed & ~exact).any())
        assert float(claimed.double().mean()) > 0.2 and bool((exact & ~claimed).double().mean() < 0.01)


def test_light_field_skips_the_shadow_test_only_where_it_changes_nothing(monkeypatch):
    lights = load_rig().lights(torch.float64)
    generator = torch.Generator().manual_seed(1)
    count = 3000
    points = torch.stack([0.1 * torch.randn(count, generator=generator), 0.1 * torch.randn(count, generator=generator), 0.5 + 0.05 * torch.randn(count, generator=generator)], dim=1).double()
    points[:500, :2] *= 0.1  # near the optical axis: facing the camera, they see every light
    field = LightField(points, lights, Falloff(), 1e-3, block_size=1000)
    view = field.view.T.contiguous()  # every pixel sees every light: whole blocks skip the test
    tilted = torch.randn(3, count, generator=generator, dtype=torch.float64)
    tilted[2] = -tilted[2].abs()
    tilted = tilted / tilted.norm(dim=0)  # many pixels have lights behind their tangent plane
    first = torch.arange(500)
    assert field.sees_all(first, view[:, :500]).all() and not field.sees_all(first, tilted[:, :500]).all()
    for normal in (view, tilted):
        exact = ((lights @ normal) > (normal * points.T).sum(0)).T.double() * field.weights
        whole = field.sees_all(None, normal)
        assert not (whole & ~(exact == field.weights).all(1)).any()  # 'sees all' is never claimed for a shadowed pixel
        for rows in (slice(0, 500), torch.arange(0, count, 7)):
            assert torch.equal(field.sees_all(torch.arange(count)[rows], normal[:, rows]), whole[rows])
            assert torch.equal(field.shadowed_weights(rows, normal[:, rows], whole[rows]), exact[rows])
        with monkeypatch.context() as patch:
            patch.setattr("reconstruct.lighting.SEES_ALL_FLOATS", 1000)  # several chunks
            assert torch.equal(field.sees_all(None, normal), whole)
    exact_differ = (((lights @ view) > (view * points.T).sum(0)) != ((lights @ tilted) > (tilted * points.T).sum(0))).any(0)
    assert torch.equal(field.masks_differ(None, view, tilted), exact_differ) and exact_differ.any()
    assert not field.masks_differ(None, view, view).any()


def test_bad_inputs_are_refused():
    with pytest.raises(InputError):
        extreme_lights(torch.zeros(5, 2))
    with pytest.raises(InputError):
        extreme_lights(torch.zeros(0, 3))
    with pytest.raises(InputError):
        extreme_lights(torch.tensor([[0.0, 0.0, math.nan]]))
    with pytest.raises(InputError):
        sees_all_lights(torch.zeros(3, 4), torch.zeros(3, 5), torch.zeros(2, 3))
    field = LightField(torch.rand(4, 3) + torch.tensor([0.0, 0.0, 0.5]), load_rig().lights(), Falloff(), 1e-3, block_size=2)
    with pytest.raises(InputError, match="contiguous"):
        LightField.from_weights(field.points, field.lights, field.weights.T.contiguous().T, block_size=2)
    with pytest.raises(InputError):
        LightField.from_weights(field.points, field.lights, field.weights[:, :-1], block_size=2)


def test_a_field_over_given_weights_gives_the_same_lighting_vectors():
    lights = load_rig().lights(torch.float64)
    generator = torch.Generator().manual_seed(2)
    points = torch.stack([0.1 * torch.randn(300, generator=generator), 0.1 * torch.randn(300, generator=generator), 0.5 + 0.05 * torch.randn(300, generator=generator)], dim=1).double()
    normal = torch.randn(3, 300, generator=generator, dtype=torch.float64)
    normal[2] = -normal[2].abs()
    normal = normal / normal.norm(dim=0)
    lighting = lighting_matrix(torch.rand(2, lights.shape[0], 3, generator=generator, dtype=torch.float64), lights)
    field = LightField(points, lights, Falloff(), 1e-3, block_size=64)
    given = LightField.from_weights(points, lights, field.weights.clone(), block_size=100)
    index = torch.arange(0, 300, 3)
    for rows, part in ((None, slice(None)), (index, index)):
        blocks = [vectors for _, _, vectors in given.vector_blocks(rows, normal[:, part], lighting)]
        assert all(block.is_contiguous() for block in blocks)  # pixels last, as the per-pixel algebra wants
        expected = torch.cat([vectors for _, _, vectors in field.vector_blocks(rows, normal[:, part], lighting)], dim=-1)
        assert expected.shape == (2, 3, 3, 300 if rows is None else 100)
        torch.testing.assert_close(torch.cat(blocks, dim=-1), expected)


def test_lighting_vectors_and_their_gradient_match_the_dense_formula():
    # b[m, c] = sum_k E[m, k, c] s_k f_k / d_k (p_k - X), formed densely, against the blocked
    # vectors and the hand-written backward (which forms masks only for pixels with lights behind
    # them), over pixels of both kinds.
    lights = load_rig().lights(torch.float64)
    generator = torch.Generator().manual_seed(3)
    count = 400
    points = torch.stack([0.1 * torch.randn(count, generator=generator), 0.1 * torch.randn(count, generator=generator), 0.5 + 0.05 * torch.randn(count, generator=generator)], dim=1).double()
    normal = torch.randn(3, count, generator=generator, dtype=torch.float64)
    normal[2] = -normal[2].abs() - 1.5  # mostly facing the display
    normal[:, ::3] = torch.randn(3, (count + 2) // 3, generator=generator, dtype=torch.float64)  # some at any angle
    normal[2, ::3] = -normal[2, ::3].abs()
    normal = normal / normal.norm(dim=0)
    field = LightField(points, lights, Falloff(), 1e-3, block_size=64)
    whole = field.sees_all(None, normal)
    assert whole.any() and not whole.all()
    lighting = torch.rand(lights.shape[0], 24, generator=generator, dtype=torch.float64, requires_grad=True)
    out = torch.empty(2, 3, 3, count, dtype=torch.float64)
    for _ in field.vector_blocks(None, normal, lighting, out=out):
        pass
    vectors = differentiable_vectors(field, normal, lighting, out)
    lit = (lights @ normal > (normal * points.T).sum(0)).T.double()  # (N, K)
    summed = ((lit * field.weights) @ lighting).view(count, 2, 3, 4)
    dense = (summed[..., :3] - points[:, None, None, :] * summed[..., 3:]).permute(1, 2, 3, 0)
    torch.testing.assert_close(vectors, dense)
    upstream = torch.randn(dense.shape, generator=generator, dtype=torch.float64)
    (grad,) = torch.autograd.grad((vectors * upstream).sum(), lighting)
    (expected,) = torch.autograd.grad((dense * upstream).sum(), lighting)
    torch.testing.assert_close(grad, expected)


def test_lighting_gradient_of_a_point_on_a_light_behind_it_is_exact_in_float32():
    # A point within min_distance of a superpixel has its weight clamped (~1e9); with that light
    # behind its tangent plane the gradient must not be a difference of sums holding that weight.
    lights = load_rig().lights(torch.float64)
    generator = torch.Generator().manual_seed(4)
    points = torch.stack([0.05 * torch.randn(50, generator=generator), 0.05 * torch.randn(50, generator=generator), 0.5 + 0.0 * torch.randn(50, generator=generator)], dim=1).double()
    points[0] = lights[0] + torch.tensor([0.0, 0.0, 1e-4], dtype=torch.float64)
    normal = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64).repeat(50, 1).T.contiguous()
    normal[:, 0] = torch.tensor([1.0, 0.0, 0.0])
    field64 = LightField(points, lights, Falloff(), 1e-3, block_size=16)
    lighting = torch.rand(lights.shape[0], 12, generator=generator, dtype=torch.float64)
    upstream = torch.randn(1, 3, 3, 50, generator=generator, dtype=torch.float64)
    grads = []
    for dtype in (torch.float64, torch.float32):
        field = LightField.from_weights(points.to(dtype), lights.to(dtype), field64.weights.to(dtype).contiguous(), block_size=16)
        values = torch.cat([block for _, _, block in field.vector_blocks(None, normal.to(dtype), lighting.to(dtype))], dim=-1)
        assert not field.sees_all(None, normal.to(dtype))[0]
        weights = lighting.to(dtype).clone().requires_grad_()
        (differentiable_vectors(field, normal.to(dtype), weights, values) * upstream.to(dtype)).sum().backward()
        grads.append(weights.grad.double())
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-4 * float(grads[0].abs().max()))


def test_length_is_the_euclidean_norm_along_any_axis_of_size_3():
    """pixel_solve.length replaces torch's norm over a leading axis of size 3 (~90x slower there);
    it must agree with it to rounding, stay finite at 0 and keep float64."""
    from reconstruct.pixel_solve import length

    generator = torch.Generator().manual_seed(0)
    for dtype in (torch.float32, torch.float64):
        vectors = torch.randn(4, 3, 3, 50, generator=generator, dtype=dtype)
        for dim in (0, 1, 2, -2):
            if vectors.shape[dim] == 3:
                torch.testing.assert_close(length(vectors, dim=dim), vectors.norm(dim=dim))
        assert length(vectors, dim=2).dtype == dtype
    assert float(length(torch.zeros(3, 1))[0]) == 0.0
    with pytest.raises(InputError, match=r"axis 0 of a \(4, 5\) tensor does not hold 3-vectors"):
        length(torch.zeros(4, 5))
