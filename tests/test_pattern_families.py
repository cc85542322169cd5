import math
from pathlib import Path

import numpy as np
import pytest
import torch

from capture_sim.errors import InputError
from patterns.families import (
    DEFAULT_SHARPNESS,
    FAMILIES,
    bounds,
    default_vector,
    get_family,
    make_patterns,
)

DDPS_DIR = Path(__file__).resolve().parent.parent / "patterns" / "data" / "ddps"
DESIGN_NAMES = {
    "olat",
    "grouped_olat",
    "mono_gradient",
    "tri_gradient",
    "mono_complementary",
    "tri_complementary",
    "mono_random",
    "tri_random",
    "gray_noise",
}
GRIDS = [(9, 16), (4, 8), (5, 10), (2, 3)]


def _interior_vector(name, num_patterns, rows, cols, seed=0):
    """Defaults moved by a small random step into the interior of the bounds (away from clamp kinks)."""
    family = get_family(name)
    low, high = family.bounds(num_patterns, rows, cols)
    vector = default_vector(name, num_patterns, rows, cols).numpy()
    rng = np.random.default_rng(seed)
    span = high - low
    vector = vector + rng.uniform(-0.03, 0.03, vector.shape) * span
    return torch.tensor(np.clip(vector, low + 0.01 * span, high - 0.01 * span), dtype=torch.float64)


def _supported_counts(family, rows, cols):
    top = min(family.max_patterns(rows, cols), 12)
    return sorted({family.min_patterns, min(family.min_patterns + 1, top), min(4, top), top})


def test_every_design_family_is_registered():
    assert set(FAMILIES) == DESIGN_NAMES
    for name, family in FAMILIES.items():
        assert family.name == name and family.summary


def test_unknown_family_raises_with_valid_names():
    with pytest.raises(InputError, match="olat.*gray_noise"):
        get_family("flat")
    with pytest.raises(InputError):
        make_patterns("flat", 4)


def test_generate_takes_float32_values_at_the_bounds_and_refuses_overflowing_sharpness():
    """float32 rounding of a float64 bound (tri_gradient's radius sqrt(80), which rounds up) used to
    count as outside, and a sharpness finite as a Python float but not in float32 gave NaN patterns."""
    family = get_family("tri_gradient")
    for count, rows, cols in ((2, 2, 4), (4, 5, 7)):
        low, high = family.bounds(count, rows, cols)
        for edge in (low, high):
            assert torch.isfinite(family.generate(torch.tensor(edge, dtype=torch.float32), count, rows, cols)).all()
    low, high = get_family("olat").bounds(4, 9, 16)
    with pytest.raises(InputError, match="sharpness must be positive and at most"):
        get_family("olat").generate(torch.tensor((low + high) / 2, dtype=torch.float32), 4, 9, 16, sharpness=1e39)


@pytest.mark.parametrize("name", sorted(DESIGN_NAMES))
@pytest.mark.parametrize("grid", GRIDS)
def test_family_shapes_bounds_and_range(name, grid):
    rows, cols = grid
    family = get_family(name)
    for num_patterns in _supported_counts(family, rows, cols):
        for preset in ("default", "ddps"):
            params = family.parameters(num_patterns, rows, cols, preset)
            names = [p.name for p in params]
            assert len(set(names)) == len(names)
            assert all(p.low <= p.default <= p.high for p in params)
            low, high = bounds(name, num_patterns, rows, cols)
            assert low.shape == high.shape == (len(params),)
            try:
                patterns = make_patterns(name, num_patterns, rows, cols, preset=preset)
            except InputError as error:  # e.g. 9..12 halves of a 2 x 3 grid: some repeat
                assert "identical patterns" in str(error) and (rows, cols) == (2, 3), (name, num_patterns, grid)
                continue
            assert patterns.shape == (num_patterns, rows, cols, 3)
            assert patterns.dtype == torch.float32
            assert torch.isfinite(patterns).all()
            assert patterns.min() >= 0 and patterns.max() <= 1


@pytest.mark.parametrize(
    "name, num_patterns",
    [("olat", 0), ("olat", 145), ("grouped_olat", 99), ("mono_gradient", 13), ("tri_gradient", 0),
     ("mono_complementary", 1), ("tri_complementary", 13), ("mono_random", 0), ("gray_noise", -1)],
)
def test_unsupported_number_of_patterns_raises(name, num_patterns):
    assert not get_family(name).supports(num_patterns, 9, 16)
    with pytest.raises(InputError, match="M ="):
        make_patterns(name, num_patterns)


def test_bad_arguments_raise():
    with pytest.raises(InputError, match="integer"):
        make_patterns("olat", 2.5)
    with pytest.raises(InputError, match="grid"):
        make_patterns("olat", 1, rows=0, cols=16)
    with pytest.raises(InputError, match="preset"):
        make_patterns("olat", 4, preset="published")
    with pytest.raises(InputError, match="no parameter"):
        make_patterns("olat", 4, brightness=0.5)
    with pytest.raises(InputError, match="outside its bounds"):
        make_patterns("olat", 4, hi=1.5)
    with pytest.raises(InputError, match="sharpness"):
        make_patterns("mono_complementary", 4, sharpness=0.0)
    with pytest.raises(InputError, match="lo must be a number, got 'a'"):  # was float()'s ValueError
        make_patterns("mono_gradient", 4, lo="a")
    with pytest.raises(InputError, match="sharpness must be positive"):  # was a TypeError from the comparison
        make_patterns("mono_gradient", 4, sharpness="4")


def test_generate_rejects_bad_vectors():
    family = get_family("mono_gradient")
    vector = default_vector("mono_gradient", 4)
    with pytest.raises(InputError, match="shape"):
        family.generate(vector[:-1], 4)
    with pytest.raises(InputError, match="NaN"):
        family.generate(torch.full_like(vector, float("nan")), 4)
    with pytest.raises(InputError, match="outside its bounds"):
        family.generate(torch.cat([torch.tensor([-0.1]), vector[1:]]), 4)
    with pytest.raises(InputError, match="torch tensor"):
        family.generate(vector.numpy(), 4)


def test_overrides_set_named_parameters():
    patterns = make_patterns("olat", 4, lo=0.2, hi=0.7)
    assert patterns.min().item() == pytest.approx(0.2, abs=1e-6)
    assert patterns.max().item() == pytest.approx(0.7, abs=1e-6)
    moved = make_patterns("olat", 1, row_0=4.0, col_0=7.0)
    assert torch.nonzero(moved[0, ..., 0] > 0.5).tolist() == [[4, 7]]


# --- published patterns ------------------------------------------------------------------------

@pytest.mark.parametrize(
    "name, file_name, num_patterns",
    [
        ("olat", "initial_OLAT", 4),
        ("grouped_olat", "initial_group_OLAT", 4),
        ("mono_gradient", "initial_mono_gradient", 4),
        ("mono_complementary", "initial_mono_complementary", 4),
        ("tri_complementary", "initial_tri_complementary", 2),
        ("tri_gradient", "initial_tri_gradient", 2),
        # The random families reproduce too: the published code drew torch.rand / torch.randn
        # with seed 0 in float32, which the families' defaults do.
        ("mono_random", "initial_mono_random", 4),
        ("gray_noise", "initial_gray_noise", 4),
    ]
    + [("tri_random", f"initial_tri_random_{m}", m) for m in range(2, 7)],
)
def test_ddps_preset_reproduces_published_patterns(name, file_name, num_patterns):
    published = np.load(DDPS_DIR / f"{file_name}.npy")
    made = make_patterns(name, num_patterns, 9, 16, preset="ddps", seed=0).numpy()
    np.testing.assert_allclose(made, published, rtol=0, atol=1e-6)


def test_ddps_olat_corner_order():
    patterns = make_patterns("olat", 4, preset="ddps")
    lit = [tuple(torch.nonzero(p[..., 0] > 0.5)[0].tolist()) for p in patterns]
    assert lit == [(0, 15), (0, 0), (8, 15), (8, 0)]


# --- behaviour of each family ------------------------------------------------------------------

@pytest.mark.parametrize("grid", GRIDS)
def test_olat_lights_distinct_superpixels(grid):
    rows, cols = grid
    for num_patterns in (1, 3, 4, 7, rows * cols):
        if num_patterns > rows * cols:
            continue
        patterns = make_patterns("olat", num_patterns, rows, cols)
        lit = patterns[..., 0] > 0.5
        assert (lit.sum(dim=(1, 2)) == 1).all()
        assert torch.equal(patterns[..., 0], patterns[..., 2])
        coverage = lit.sum(dim=0)
        assert coverage.max() == 1
        if num_patterns == rows * cols:
            assert (coverage == 1).all()


def test_grouped_olat_blocks_are_three_by_three_and_spread():
    patterns = make_patterns("grouped_olat", 6)
    lit = patterns[..., 0] > 0.5
    assert (lit.sum(dim=(1, 2)) == 9).all()
    first_cells = [tuple(torch.nonzero(p)[0].tolist()) for p in lit]
    assert len(set(first_cells)) == 6
    wide = make_patterns("grouped_olat", 1, block_width=5.0, col_0=7.0)
    assert (wide[0, ..., 0] > 0.5).sum() == 15


def test_complementary_pairs_sum_to_lo_plus_hi():
    for name, num_patterns in (("mono_complementary", 6), ("tri_complementary", 4), ("tri_gradient", 5)):
        patterns = make_patterns(name, num_patterns, lo=0.1, hi=0.8).double()
        for j in range(num_patterns // 2):
            torch.testing.assert_close(patterns[2 * j] + patterns[2 * j + 1], torch.full_like(patterns[0], 0.9), atol=1e-6, rtol=0)


@pytest.mark.parametrize("num_patterns,rows,cols", [(2, 9, 16), (4, 9, 16), (10, 9, 16), (2, 5, 9), (4, 5, 9), (12, 4, 8)])
def test_tri_complementary_red_and_green_halves_are_complementary(num_patterns, rows, cols):
    """R and G light opposite halves of every pattern, also where an odd number of cells lies
    across the split (the middle row used to be dark in both)."""
    patterns = make_patterns("tri_complementary", num_patterns, rows, cols).double()
    torch.testing.assert_close(patterns[..., 0] + patterns[..., 1], torch.ones_like(patterns[..., 0]), atol=1e-6, rtol=0)


def test_gradient_directions_are_spread_in_opposite_pairs():
    directions = get_family("mono_gradient").directions
    assert directions(4) == [-90.0, 90.0, 180.0, 0.0]
    for num_patterns in (2, 6, 8, 10):
        angles = directions(num_patterns)
        for j in range(num_patterns // 2):
            assert math.isclose(abs(angles[2 * j] - angles[2 * j + 1]), 180.0)
    assert len(set(np.round(directions(5), 6))) == 5


def test_random_families_follow_the_seed():
    for name in ("mono_random", "tri_random", "gray_noise"):
        first, again, other = (make_patterns(name, 3, seed=s) for s in (1, 1, 2))
        assert torch.equal(first, again)
        assert not torch.equal(first, other)


def test_random_family_statistics():
    mono = make_patterns("mono_random", 200)
    assert torch.equal(mono[..., 0], mono[..., 1]) and torch.equal(mono[..., 0], mono[..., 2])
    assert abs(mono.mean().item() - 0.5) < 0.01
    assert abs(mono.std().item() - math.sqrt(1 / 12)) < 0.01
    tri = make_patterns("tri_random", 200)
    assert not torch.equal(tri[..., 0], tri[..., 1])
    noise = make_patterns("gray_noise", 200)
    assert abs(noise.mean().item() - 0.5) < 1e-3
    assert abs(noise.std().item() - 0.01) < 1e-3


# --- values against plain-loop references ------------------------------------------------------

def _sigmoid(t):
    return 1.0 / (1.0 + math.exp(-t))


def _cell_xy(r, c, rows, cols):
    return c + 0.5 - cols / 2, r + 0.5 - rows / 2


def _ramp_reference(r, c, rows, cols, angle, offset, length):
    x, y = _cell_xy(r, c, rows, cols)
    theta = math.radians(angle)
    u = 0.5 + (x * math.cos(theta) + y * math.sin(theta) + offset) / length
    return min(1.0, max(0.0, u))


def _split_reference(r, c, rows, cols, angle, offset, sharpness):
    x, y = _cell_xy(r, c, rows, cols)
    theta = math.radians(angle)
    return _sigmoid(sharpness * (x * math.cos(theta) + y * math.sin(theta) - offset))


def _box_reference(d, half, sharpness):
    return _sigmoid(sharpness * (d + half)) - _sigmoid(sharpness * (d - half))


def _reference_patterns(name, values, num_patterns, rows, cols, sharpness):
    v = values.tolist()
    lo, hi = v[0], v[1]
    out = np.zeros((num_patterns, rows, cols, 3))
    for m in range(num_patterns):
        for r in range(rows):
            for c in range(cols):
                if name == "olat":
                    w = _box_reference(r - v[2 + 2 * m], 0.5, sharpness) * _box_reference(c - v[3 + 2 * m], 0.5, sharpness)
                    rgb = [w] * 3
                elif name == "grouped_olat":
                    w = _box_reference(r - v[4 + 2 * m], v[2] / 2, sharpness) * _box_reference(c - v[5 + 2 * m], v[3] / 2, sharpness)
                    rgb = [w] * 3
                elif name == "mono_gradient":
                    rgb = [_ramp_reference(r, c, rows, cols, *v[2 + 3 * m : 5 + 3 * m])] * 3
                elif name == "mono_complementary":
                    j = m // 2
                    w = _split_reference(r, c, rows, cols, v[2 + 2 * j], v[3 + 2 * j], sharpness)
                    rgb = [w if m % 2 == 0 else 1 - w] * 3
                elif name == "tri_complementary":
                    j = m // 2
                    rgb = []
                    for ch in range(3):
                        base = 2 + 6 * j + 2 * ch
                        w = _split_reference(r, c, rows, cols, v[base], v[base + 1], sharpness)
                        rgb.append(w if m % 2 == 0 else 1 - w)
                elif name == "tri_gradient":
                    j = m // 2
                    rgb = []
                    for ch in range(3):
                        a, b, s = v[2 + 9 * j + 3 * ch : 5 + 9 * j + 3 * ch]
                        if ch == (1 + j) % 3:
                            x, y = _cell_xy(r, c, rows, cols)
                            w = min(1.0, max(0.0, 1 - math.sqrt((x - a) ** 2 + (y - b) ** 2 + 1e-6) / s))
                        else:
                            w = _ramp_reference(r, c, rows, cols, a, b, s)
                        rgb.append(w if m % 2 == 0 else 1 - w)
                out[m, r, c] = [lo + (hi - lo) * w for w in rgb]
    return out


@pytest.mark.parametrize(
    "name, num_patterns",
    [("olat", 3), ("grouped_olat", 2), ("mono_gradient", 3), ("mono_complementary", 3), ("tri_complementary", 4), ("tri_gradient", 3)],
)
def test_generation_matches_plain_loop_reference(name, num_patterns):
    rows, cols = 5, 7
    values = _interior_vector(name, num_patterns, rows, cols, seed=3)
    made = get_family(name).generate(values, num_patterns, rows, cols, sharpness=2.5)
    expected = _reference_patterns(name, values, num_patterns, rows, cols, 2.5)
    np.testing.assert_allclose(made.numpy(), expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", sorted(DESIGN_NAMES))
def test_generation_is_differentiable(name):
    family = get_family(name)
    rows, cols = 3, 4
    num_patterns = max(family.min_patterns, 2) if name not in ("tri_gradient", "tri_complementary") else 3
    values = _interior_vector(name, num_patterns, rows, cols, seed=1).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: family.generate(v, num_patterns, rows, cols, sharpness=3.0), (values,))


def test_float32_generation_keeps_dtype():
    values = default_vector("tri_gradient", 2).float()
    assert get_family("tri_gradient").generate(values, 2).dtype == torch.float32


def test_default_sharpness_gives_binary_edges():
    patterns = make_patterns("mono_complementary", 4, 9, 16, sharpness=DEFAULT_SHARPNESS).double()
    assert ((patterns < 1e-6) | (patterns > 1 - 1e-6)).all()
    # Oblique splits (M = 5, 6, 9..12) pass within 0.0032 cells of a cell centre on this grid: the
    # halves must still be binary, as DESIGN section 6 says.
    for rows, cols in ((9, 16), (4, 8)):
        for family in ("mono_complementary", "tri_complementary"):
            for count in range(2, 13):
                patterns = make_patterns(family, count, rows, cols).double()
                assert ((patterns < 1e-6) | (patterns > 1 - 1e-6)).all(), (family, count, rows, cols)


def test_a_grid_too_small_for_a_family_is_refused():
    # Top/bottom halves or vertical ramps on one row are flat: a split's edge passed through every
    # cell (all at the half level) and a ramp gave one value; such sets were made without a word.
    for name, count, rows, cols in (("mono_complementary", 4, 1, 6), ("mono_complementary", 3, 1, 6), ("tri_complementary", 4, 1, 6),
                                    ("tri_complementary", 2, 6, 1), ("mono_gradient", 3, 1, 6), ("tri_gradient", 2, 1, 2)):
        with pytest.raises(InputError, match=f"{name}: M = {count}: a pattern varying towards .* would be flat on a {rows} x {cols} grid"):
            make_patterns(name, count, rows, cols)
    with pytest.raises(InputError, match="identical patterns"):  # five splits of a 2 x 2 grid: two repeat
        make_patterns("mono_complementary", 5, 2, 2)
    assert make_patterns("mono_complementary", 2, 1, 6).shape == (2, 1, 6, 3)  # left/right halves still work
    assert make_patterns("mono_gradient", 2, 6, 1).shape == (2, 6, 1, 3)  # as do vertical ramps on a column
