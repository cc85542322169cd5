import math

import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from patterns.families import make_patterns
from patterns.parameterization import logits_to_patterns, patterns_to_logits
from tests.conftest import TOLERANCE


def test_round_trip_on_interior_values():
    patterns = torch.rand(3, 2, 4, 3, dtype=torch.float64) * 0.9 + 0.05
    logits = patterns_to_logits(patterns)
    assert logits.shape == patterns.shape and logits.dtype == torch.float64
    torch.testing.assert_close(logits_to_patterns(logits), patterns, **TOLERANCE[torch.float64])


def test_exact_zero_and_one_stay_movable():
    olat = make_patterns("olat", 4)  # default preset: exact 0 and 1 values
    logits = patterns_to_logits(olat, eps=1e-3).requires_grad_()
    bound = math.log((1 - 1e-3) / 1e-3)
    assert torch.isfinite(logits).all()
    assert logits.abs().max().item() == pytest.approx(bound, rel=1e-5)
    logits_to_patterns(logits).sum().backward()
    assert (logits.grad > 1e-4).all()  # sigmoid'(z) = p (1 - p) >= eps (1 - eps) everywhere


def test_numpy_input_and_closed_form():
    values = np.array([0.0, 0.25, 0.5, 1.0])
    logits = patterns_to_logits(values, eps=0.01)
    expected = [math.log(0.01 / 0.99), math.log(0.25 / 0.75), 0.0, math.log(0.99 / 0.01)]
    np.testing.assert_allclose(logits.numpy(), expected, rtol=1e-6, atol=1e-6)


def test_gradcheck():
    patterns = (torch.rand(2, 2, 3, 3, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    assert torch.autograd.gradcheck(patterns_to_logits, (patterns,))
    logits = torch.randn(2, 2, 3, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(logits_to_patterns, (logits,))


def test_bad_input_raises():
    with pytest.raises(InputError, match=r"\[0, 1\]"):
        patterns_to_logits(torch.tensor([0.5, 1.2]))
    with pytest.raises(InputError, match="NaN"):
        patterns_to_logits(torch.tensor([float("nan")]))
    with pytest.raises(InputError, match="eps"):
        patterns_to_logits(torch.tensor([0.5]), eps=0.5)
    with pytest.raises(InputError, match="NaN"):
        logits_to_patterns(torch.tensor([float("inf")]))
