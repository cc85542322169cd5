import math

import pytest
import torch

from capture_sim.errors import InputError
from capture_sim.rig import load_rig
from reconstruct.lighting import extreme_lights, sees_all_lights


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


def test_bad_inputs_are_refused():
    with pytest.raises(InputError):
        extreme_lights(torch.zeros(5, 2))
    with pytest.raises(InputError):
        extreme_lights(torch.zeros(0, 3))
    with pytest.raises(InputError):
        extreme_lights(torch.tensor([[0.0, 0.0, math.nan]]))
    with pytest.raises(InputError):
        sees_all_lights(torch.zeros(3, 4), torch.zeros(3, 5), torch.zeros(2, 3))
