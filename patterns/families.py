"""Heuristic pattern families (DESIGN section 6) as differentiable functions of bounded parameters.

Every family maps a flat vector of named continuous parameters, each with bounds, to a pattern set
P of shape (M, R, C, 3) with values in [0, 1] (display set values, before the display gamma). An
NLopt search optimises that vector; generation is written in torch so that the same function gives
gradients by autograd wherever it is continuous.

Panel coordinates (DESIGN section 2: row 0 at the top; columns grow with camera x, rows with
camera y): superpixel (r, c) sits at x = c + 0.5 - C/2, y = r + 0.5 - R/2 cells from the panel
centre. Angles are in degrees from +x towards +y, so -90 points up (-y) and 180 left (-x).

Smooth constructions:
- linear ramp: u = 0.5 + (x cos(theta) + y sin(theta) + offset) / length, clamped to [0, 1]. The
  clamp is exact (piecewise linear): saturated superpixels pass no gradient. A smooth clamp cannot
  keep a ramp value of exactly 1 at the bright end, which the published patterns need.
- split (half plane): sigma(k (p - s)) with p the projection on the bright direction, s the edge
  position and k the edge sharpness in 1/cells.
- block window (a superpixel or a group of them): sigma(k (d + h)) - sigma(k (d - h)) per axis, d
  the distance in cells from the block centre and h the half width.
- radial falloff: 1 - sqrt(dx^2 + dy^2 + eps^2) / radius, clamped to [0, 1] (eps keeps the centre
  differentiable).
The default sharpness (1e6 per cell, ``DEFAULT_SHARPNESS``) makes edges binary, as DESIGN's "binary
halves" are, which also reproduces the published patterns; a gradient-based search of split or
block positions needs a low sharpness (2..8, ``train.search`` uses 4), at the cost of soft edges.

Presets: "default" uses off level lo = 0 and on level hi = 1 (an off level of 0.1 emits 0.1**2.2 after
the display gamma, so the 143 off superpixels of an OLAT pattern would emit about half its light);
"ddps" uses the published lo = 0.1, hi = 0.9 and reproduces the published initial patterns
(patterns/data/ddps/initial_*.npy) for M = 4 (olat, grouped_olat, mono_gradient,
mono_complementary, mono_random, gray_noise), M = 2 (tri_gradient, tri_complementary) and
M = 2..6 (tri_random). The published tri gradient used lo = 0, hi = 1, so both presets agree there.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from capture_sim.errors import InputError, check_array, check_seed, is_real_number

DEFAULT_SHARPNESS = 1e6
"""Slope of sigmoid edges in 1/cells: binary (to float rounding) for every cell centre more than
~2e-5 cells from an edge. Oblique default splits pass within 0.0032 cells of a centre on the
reference 9 x 16 grid (M = 9, 10), where a slope of 40 left values like 0.18 and 0.82."""

MAX_SHARPNESS = 1e12
"""Largest edge sharpness per cell: already a step at float32 resolution; far beyond, sharpness x
cells overflows float32 and the sigmoid gives NaN."""


def check_sharpness(sharpness, name: str = "sharpness") -> None:
    """Raise ``InputError`` unless ``sharpness`` is a number in (0, MAX_SHARPNESS]."""
    if not (is_real_number(sharpness) and 0 < sharpness <= MAX_SHARPNESS):
        raise InputError(f"{name} must be positive and at most {MAX_SHARPNESS:g} per cell, got {sharpness!r}")


PRESETS = ("default", "ddps")

PRESET_LEVELS = {"default": (0.0, 1.0), "ddps": (0.1, 0.9)}
"""(off, on) set levels of each preset (families that need other levels override them)."""

_RADIAL_EPS = 1e-3  # cells; changes a published value by < 1e-7
_GRAY_NOISE_MEAN = 0.5
_GRAY_NOISE_STD = 0.01  # the published grey noise: 0.5 + 0.01 * N(0, 1)
_MAX_PAIRED_PATTERNS = 12
_MAX_RANDOM_PATTERNS = 1000


@dataclass(frozen=True)
class Parameter:
    """One continuous parameter of a family, with its search bounds."""

    name: str
    """Unique name within the family's vector, e.g. ``"lo"`` or ``"angle_deg_2"``."""
    low: float
    """Smallest value the search may use (inclusive)."""
    high: float
    """Largest value the search may use (inclusive)."""
    default: float
    """Starting value for the preset the list was made for."""


class Family:
    """A heuristic pattern family: named bounded parameters and a differentiable generator.

    Subclasses set ``name`` and ``summary`` and implement ``_parameters``, ``_generate`` and
    ``max_patterns``; the public methods validate their inputs and call those.
    """

    name: str = ""
    summary: str = ""
    min_patterns: int = 1
    values_are_parameters: bool = False
    """The parameters are the pattern values themselves (random families): a file's meta need not
    repeat them."""

    def max_patterns(self, rows: int, cols: int) -> int:
        """Largest M this family supports on an R x C grid."""
        raise NotImplementedError

    def supports(self, num_patterns: int, rows: int = 9, cols: int = 16) -> bool:
        """Whether the family can make ``num_patterns`` patterns on a ``rows`` x ``cols`` grid."""
        return rows >= 1 and cols >= 1 and self.min_patterns <= num_patterns <= self.max_patterns(rows, cols)

    def check(self, num_patterns: int, rows: int, cols: int) -> None:
        """Raise ``InputError`` unless ``supports(num_patterns, rows, cols)``."""
        if not isinstance(num_patterns, (int, np.integer)) or isinstance(num_patterns, bool):
            raise InputError(f"{self.name}: the number of patterns M must be an integer, got {num_patterns!r}")
        if not (isinstance(rows, (int, np.integer)) and isinstance(cols, (int, np.integer))) or rows < 1 or cols < 1:
            raise InputError(f"{self.name}: the grid must be at least 1 x 1, got {rows} x {cols}")
        if not self.supports(num_patterns, rows, cols):
            raise InputError(
                f"{self.name} supports M = {self.min_patterns}..{self.max_patterns(rows, cols)} on a "
                f"{rows} x {cols} grid, got M = {num_patterns}"
            )

    def parameters(
        self, num_patterns: int, rows: int = 9, cols: int = 16, preset: str = "default", seed: int = 0
    ) -> list[Parameter]:
        """The parameter vector's layout: names, bounds and the preset's defaults.

        Args:
            num_patterns: M.
            rows, cols: display grid R x C.
            preset: ``"default"`` or ``"ddps"`` (see the module docstring).
            seed: seed of the random families' default values (ignored by the others).

        Returns:
            P parameters in vector order.
        """
        self.check(num_patterns, rows, cols)
        if preset not in PRESETS:
            raise InputError(f"unknown preset {preset!r}; presets: {', '.join(PRESETS)}")
        return self._named_parameters(int(num_patterns), int(rows), int(cols), preset, check_seed("seed", seed))

    def _named_parameters(self, num_patterns: int, rows: int, cols: int, preset: str, seed: int) -> list[Parameter]:
        """``_parameters``, with the family and M in its errors (a grid too small for a pattern)."""
        try:
            return self._parameters(num_patterns, rows, cols, preset, seed)
        except InputError as err:
            raise InputError(f"{self.name}: M = {num_patterns}: {err}") from None

    def bounds(self, num_patterns: int, rows: int = 9, cols: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """(low, high): two (P,) float64 arrays of the search bounds."""
        self.check(num_patterns, rows, cols)
        low, high, _ = self._bounds(int(num_patterns), int(rows), int(cols))
        return low.copy(), high.copy()

    def generate(
        self,
        values: torch.Tensor,
        num_patterns: int,
        rows: int = 9,
        cols: int = 16,
        sharpness: float = DEFAULT_SHARPNESS,
    ) -> torch.Tensor:
        """Patterns from a parameter vector, differentiable with respect to ``values``.

        Args:
            values: (P,) float32 or float64 parameter vector in the order of ``parameters``, within
                its bounds.
            num_patterns: M.
            rows, cols: display grid R x C.
            sharpness: slope of sigmoid edges in 1/cells (splits and block windows; ignored by
                ramps, radial falloffs and random families). Must be positive.

        Returns:
            (M, R, C, 3) display set values in [0, 1], same dtype and device as ``values``.
        """
        self.check(num_patterns, rows, cols)
        if not isinstance(values, torch.Tensor) or not values.is_floating_point():
            raise InputError(f"{self.name}: parameter values must be a floating-point torch tensor")
        low, high, names = self._bounds(int(num_patterns), int(rows), int(cols))
        check_array(f"{self.name} parameter values", values, (len(names),))
        detached = values.detach().cpu()
        # The bounds rounded as the values are: a float32 vector at a float64 bound is inside.
        outside = torch.nonzero((detached < torch.as_tensor(low, dtype=detached.dtype)) | (detached > torch.as_tensor(high, dtype=detached.dtype)))
        if outside.numel():
            i = int(outside[0])
            raise InputError(
                f"{self.name}: parameter {names[i]} = {float(detached[i]):.6g} is outside its bounds [{low[i]:g}, {high[i]:g}]"
            )
        check_sharpness(sharpness, f"{self.name}: sharpness")
        return self._generate(values, int(num_patterns), int(rows), int(cols), float(sharpness))

    @functools.lru_cache(maxsize=32)
    def _bounds(self, num_patterns: int, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
        params = self._named_parameters(num_patterns, rows, cols, "default", 0)
        low = np.array([p.low for p in params], dtype=np.float64)
        high = np.array([p.high for p in params], dtype=np.float64)
        return low, high, tuple(p.name for p in params)

    def _parameters(self, num_patterns: int, rows: int, cols: int, preset: str, seed: int) -> list[Parameter]:
        raise NotImplementedError

    def _generate(self, values: torch.Tensor, num_patterns: int, rows: int, cols: int, sharpness: float) -> torch.Tensor:
        raise NotImplementedError


# ---------------------------------------------------------------------------------------------
# Building blocks shared by the families (internal: callers have validated their inputs)
# ---------------------------------------------------------------------------------------------


def _cell_coordinates(rows: int, cols: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, C) x and y of every superpixel centre, cells from the panel centre (x right, y down)."""
    x = torch.arange(cols, dtype=like.dtype, device=like.device) + 0.5 - cols / 2
    y = torch.arange(rows, dtype=like.dtype, device=like.device) + 0.5 - rows / 2
    return x.expand(rows, cols), y[:, None].expand(rows, cols)


def _projection(x: torch.Tensor, y: torch.Tensor, angle_deg: torch.Tensor) -> torch.Tensor:
    """(..., R, C) signed distance in cells along the direction ``angle_deg`` (...,)."""
    theta = torch.deg2rad(angle_deg)[..., None, None]
    return x * torch.cos(theta) + y * torch.sin(theta)


def _ramp(x, y, angle_deg, offset, length) -> torch.Tensor:
    """(..., R, C) linear ramp in [0, 1], rising along ``angle_deg``; 0.5 at ``-offset`` cells."""
    u = 0.5 + (_projection(x, y, angle_deg) + offset[..., None, None]) / length[..., None, None]
    return u.clamp(0.0, 1.0)


def _split(x, y, angle_deg, offset, sharpness: float) -> torch.Tensor:
    """(..., R, C) half plane: ~1 where the projection on ``angle_deg`` exceeds ``offset`` cells."""
    return torch.sigmoid(sharpness * (_projection(x, y, angle_deg) - offset[..., None, None]))


def _window(distance: torch.Tensor, half_width: torch.Tensor, sharpness: float) -> torch.Tensor:
    """Smooth box: ~1 where |distance| < half_width, ~0 outside, sigmoid edges."""
    return torch.sigmoid(sharpness * (distance + half_width)) - torch.sigmoid(sharpness * (distance - half_width))


def _radial(x, y, center_x, center_y, radius) -> torch.Tensor:
    """(..., R, C) cone: 1 at (center_x, center_y), falling linearly to 0 at ``radius`` cells."""
    dx = x - center_x[..., None, None]
    dy = y - center_y[..., None, None]
    distance = torch.sqrt(dx * dx + dy * dy + _RADIAL_EPS**2)
    return (1.0 - distance / radius[..., None, None]).clamp(0.0, 1.0)


def _levels(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """lo + (hi - lo) * weights, with lo = values[0] and hi = values[1]."""
    return values[0] + (values[1] - values[0]) * weights


def _level_parameters(preset: str, levels: dict | None = None) -> list[Parameter]:
    lo, hi = (levels or PRESET_LEVELS)[preset]
    return [
        Parameter("lo", 0.0, 0.5, lo),
        Parameter("hi", 0.5, 1.0, hi),
    ]


def _wrap_deg(angle: float) -> float:
    """Angle in (-180, 180]."""
    wrapped = math.fmod(angle, 360.0)
    if wrapped <= -180.0:
        wrapped += 360.0
    elif wrapped > 180.0:
        wrapped -= 360.0
    return wrapped


def _extent(angle_deg: float, rows: int, cols: int) -> float:
    """Panel extent in cells along a direction: the ramp length spanning the whole panel."""
    theta = math.radians(angle_deg)
    return round(cols * abs(math.cos(theta)) + rows * abs(math.sin(theta)), 9)


def _distinct_projections(angle_deg: float, rows: int, cols: int) -> np.ndarray:
    """Sorted distinct positions (cells) of the superpixel centres along a direction.

    Raises:
        InputError: fewer than two (a single row or column across the direction): a ramp or split
            along it would be flat (a split's edge would pass through every cell, leaving them all
            at the half level), so the grid is too small for the pattern.
    """
    theta = math.radians(angle_deg)
    x = np.arange(cols) + 0.5 - cols / 2
    y = np.arange(rows) + 0.5 - rows / 2
    projections = np.unique(np.round((x[None, :] * math.cos(theta) + y[:, None] * math.sin(theta)).ravel(), 9))
    if projections.size < 2:
        raise InputError(f"a pattern varying towards {angle_deg:g} deg would be flat on a {rows} x {cols} grid "
                         f"(its superpixels lie on one line across that direction): the grid is too small for this family at this M")
    return projections


def _default_split_offset(angle_deg: float, rows: int, cols: int) -> float:
    """Edge position midway between the two projected cell centres around the panel centre.

    Ties (an odd number of rows, e.g. 9) go to the positive side, which leaves the middle row in
    the dark half, as in the published top/bottom patterns (rows 0..3 against 4..8).
    """
    projections = _distinct_projections(angle_deg, rows, cols)
    midpoints = (projections[1:] + projections[:-1]) / 2
    best = min(midpoints, key=lambda mid: (round(abs(mid), 9), -mid))
    return float(best)


def _spread_positions(candidates: np.ndarray, num_patterns: int) -> np.ndarray:
    """Pick ``num_patterns`` well-spread (row, col) positions from ``candidates`` (N, 2).

    The four corners of the candidate set come first in the published OLAT order (top-right,
    top-left, bottom-right, bottom-left); further positions follow by farthest-point sampling
    (ties to the earliest candidate in row-major order).
    """
    rows_min, cols_min = candidates.min(axis=0)
    rows_max, cols_max = candidates.max(axis=0)
    chosen: list[int] = []
    for corner in ((rows_min, cols_max), (rows_min, cols_min), (rows_max, cols_max), (rows_max, cols_min)):
        index = int(np.flatnonzero((candidates == corner).all(axis=1))[0])
        if index not in chosen:
            chosen.append(index)
    chosen = chosen[:num_patterns]
    nearest = np.min(np.linalg.norm(candidates[:, None, :] - candidates[None, chosen, :], axis=-1), axis=1)
    while len(chosen) < num_patterns:
        index = int(np.argmax(nearest))
        chosen.append(index)
        nearest = np.minimum(nearest, np.linalg.norm(candidates - candidates[index], axis=1))
    return candidates[chosen]


def _pair_count(num_patterns: int) -> int:
    return (num_patterns + 1) // 2


def _with_complements(base: torch.Tensor, num_patterns: int) -> torch.Tensor:
    """Interleave base patterns w (A, ...) with their complements 1 - w; keep the first M."""
    paired = torch.stack([base, 1.0 - base], dim=1)
    return paired.reshape(-1, *base.shape[1:])[:num_patterns]


def _grey(weights: torch.Tensor) -> torch.Tensor:
    """(M, R, C) -> (M, R, C, 3) with equal channels."""
    return weights[..., None].expand(*weights.shape, 3)


# ---------------------------------------------------------------------------------------------
# Families
# ---------------------------------------------------------------------------------------------


class Olat(Family):
    """One superpixel per pattern at ``hi``, the rest at ``lo``.

    M = 1..K. Positions: the four corners first, in the published order top-right, top-left,
    bottom-right, bottom-left, then farthest-point sampling over the grid. Parameters: lo, hi, and
    per pattern m the lit position ``row_m``, ``col_m`` (continuous, grid index units) of a smooth
    one-cell window.
    """

    name = "olat"
    summary = "one superpixel per pattern (corners first, then spread out); M = 1..K"

    def max_patterns(self, rows, cols):
        return rows * cols

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        grid = np.stack(np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij"), axis=-1).reshape(-1, 2)
        positions = _spread_positions(grid.astype(np.float64), num_patterns)
        params = _level_parameters(preset)
        for m, (row, col) in enumerate(positions):
            params.append(Parameter(f"row_{m}", 0.0, rows - 1.0, float(row)))
            params.append(Parameter(f"col_{m}", 0.0, cols - 1.0, float(col)))
        return params

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        centres = values[2:].reshape(num_patterns, 2)
        half = torch.full((), 0.5, dtype=values.dtype, device=values.device)
        return _grey(_levels(values, _block_weights(centres, half, half, rows, cols, sharpness)))


def _block_weights(centres, half_height, half_width, rows, cols, sharpness) -> torch.Tensor:
    """(M, R, C) product of smooth row and column windows around centres (M, 2) (row, col)."""
    row_index = torch.arange(rows, dtype=centres.dtype, device=centres.device)
    col_index = torch.arange(cols, dtype=centres.dtype, device=centres.device)
    in_rows = _window(row_index[None, :] - centres[:, :1], half_height, sharpness)
    in_cols = _window(col_index[None, :] - centres[:, 1:], half_width, sharpness)
    return in_rows[:, :, None] * in_cols[:, None, :]


class GroupedOlat(Family):
    """A block of superpixels per pattern at ``hi``, the rest at ``lo``.

    The block is 3 x 3 by default (smaller on grids with fewer than 3 rows or columns). Block
    centres are chosen like ``olat`` positions among the places where the block fits (M = 4: the
    four corner blocks, as published), so M = 1..(R - 2)(C - 2) for 3 x 3 blocks (on a grid
    under 3 rows or columns the block is as high or wide as the grid: M = 1..(R - h + 1)(C - w + 1)
    for h = min(3, R), w = min(3, C)). Parameters: lo,
    hi, ``block_height``, ``block_width`` (cells, shared by all patterns) and per pattern m the
    block centre ``row_m``, ``col_m`` (grid index units).
    """

    name = "grouped_olat"
    summary = "a 3 x 3 block per pattern (corner blocks first, then spread out; smaller on grids under 3 x 3); M = 1..(R - 2)(C - 2) on 3 x 3 grids and larger"

    @staticmethod
    def _block(rows, cols):
        return min(3, rows), min(3, cols)

    def max_patterns(self, rows, cols):
        height, width = self._block(rows, cols)
        return (rows - height + 1) * (cols - width + 1)

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        height, width = self._block(rows, cols)
        centre_rows = np.arange(rows - height + 1) + (height - 1) / 2
        centre_cols = np.arange(cols - width + 1) + (width - 1) / 2
        grid = np.stack(np.meshgrid(centre_rows, centre_cols, indexing="ij"), axis=-1).reshape(-1, 2)
        positions = _spread_positions(grid, num_patterns)
        params = _level_parameters(preset)
        params.append(Parameter("block_height", 1.0, float(rows), float(height)))
        params.append(Parameter("block_width", 1.0, float(cols), float(width)))
        for m, (row, col) in enumerate(positions):
            params.append(Parameter(f"row_{m}", 0.0, rows - 1.0, float(row)))
            params.append(Parameter(f"col_{m}", 0.0, cols - 1.0, float(col)))
        return params

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        centres = values[4:].reshape(num_patterns, 2)
        weights = _block_weights(centres, values[2] / 2, values[3] / 2, rows, cols, sharpness)
        return _grey(_levels(values, weights))


def _ramp_parameters(angle: float, rows: int, cols: int, prefix: str = "", suffix: str = "") -> list[Parameter]:
    """angle_deg, offset (0.5 cell: the published ramps end at hi on the bright row) and length.
    Raises InputError if the ramp would be flat on the grid (``_distinct_projections``)."""
    _distinct_projections(angle, rows, cols)
    size = float(max(rows, cols))
    return [
        Parameter(f"{prefix}angle_deg{suffix}", -360.0, 360.0, _wrap_deg(angle)),
        Parameter(f"{prefix}offset{suffix}", -size, size, 0.5),
        Parameter(f"{prefix}length{suffix}", 1.0, 4.0 * size, _extent(angle, rows, cols)),
    ]


class MonoGradient(Family):
    """Grey linear ramps from ``lo`` to ``hi``, one direction per pattern.

    Even M: M/2 axes evenly spaced over 180 deg, each giving a pair of opposite ramps, starting
    vertical (M = 4: bright towards -y, +y, -x, +x, as published). Odd M: M directions evenly
    spaced around the circle, starting at -y. M = 1..12. Ramp values along an axis-aligned ramp:
    the superpixel nearest the bright end gets ``hi`` and the far end lo + (hi - lo)/N (N cells
    along the ramp), as published; diagonal ramps stop slightly short of ``hi`` (about 0.99 at the
    default hi = 1), because their length spans the grid's bounding box, not its cell centres.
    Parameters: lo, hi and per pattern m ``angle_deg_m`` (bright direction), ``offset_m`` (cells
    added to the projection; positive brightens) and ``length_m`` (cells from 0 to 1).
    """

    name = "mono_gradient"
    summary = "grey linear ramps in opposite pairs (M = 4: -y, +y, -x, +x); M = 1..12"

    def max_patterns(self, rows, cols):
        return _MAX_PAIRED_PATTERNS

    @staticmethod
    def directions(num_patterns: int) -> list[float]:
        """Default bright directions in degrees (0 = +x, 90 = +y = down), in pattern order."""
        if num_patterns % 2 == 0:
            axes = num_patterns // 2
            angles = []
            for j in range(axes):
                axis = -90.0 - j * 180.0 / axes
                angles += [axis, axis + 180.0]
        else:
            angles = [-90.0 - m * 360.0 / num_patterns for m in range(num_patterns)]
        return [_wrap_deg(a) for a in angles]

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        params = _level_parameters(preset)
        for m, angle in enumerate(self.directions(num_patterns)):
            params += _ramp_parameters(angle, rows, cols, suffix=f"_{m}")
        return params

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        x, y = _cell_coordinates(rows, cols, values)
        ramps = values[2:].reshape(num_patterns, 3)
        weights = _ramp(x, y, ramps[:, 0], ramps[:, 1], ramps[:, 2])
        return _grey(_levels(values, weights))


_CHANNELS = "rgb"


class TriGradient(Family):
    """Colour patterns of two linear ramps and one radial falloff, each followed by its complement.

    ceil(M/2) base patterns; pattern 2j is base j and pattern 2j + 1 its complement lo + hi - P (odd
    M drops the last complement). M = 1..12. Base 0 is the published one: R ramps bright towards -x,
    G falls off radially from near the panel centre, B ramps bright towards -y. Base j moves the
    radial role to channel (1 + j) mod 3 and rotates the two ramps (first and second in RGB order)
    by -j * 180 / A deg, A = ceil(M/2). Parameters: lo, hi, then per base j and channel X in r, g, b
    either ``pairJ_X_angle_deg``, ``pairJ_X_offset``, ``pairJ_X_length`` (ramp, as in
    mono_gradient) or ``pairJ_X_center_x``, ``pairJ_X_center_y`` (cells from the panel centre) and
    ``pairJ_X_radius`` (cells). Default centre (0.5, 0.5) and radius reproduce the published cone.
    """

    name = "tri_gradient"
    summary = "R/B colour ramps and a G radial cone, with complements; M = 1..12"

    def max_patterns(self, rows, cols):
        return _MAX_PAIRED_PATTERNS

    @staticmethod
    def radial_channel(pair: int) -> int:
        """Channel (0 = R, 1 = G, 2 = B) carrying the radial falloff in base pattern ``pair``."""
        return (1 + pair) % 3

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        params = _level_parameters(preset, levels={"default": (0.0, 1.0), "ddps": (0.0, 1.0)})
        pairs = _pair_count(num_patterns)
        for j in range(pairs):
            ramp_angles = iter((180.0 - j * 180.0 / pairs, -90.0 - j * 180.0 / pairs))
            for channel in range(3):
                prefix = f"pair{j}_{_CHANNELS[channel]}_"
                if channel == self.radial_channel(j):
                    params += [
                        Parameter(f"{prefix}center_x", -cols / 2, cols / 2, 0.5 if cols > 1 else 0.0),
                        Parameter(f"{prefix}center_y", -rows / 2, rows / 2, 0.5 if rows > 1 else 0.0),
                        Parameter(f"{prefix}radius", 1.0, 2.0 * math.hypot(rows, cols), max(1.0, math.hypot(rows / 2, cols / 2))),
                    ]
                else:
                    params += _ramp_parameters(next(ramp_angles), rows, cols, prefix=prefix)
        return params

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        x, y = _cell_coordinates(rows, cols, values)
        pairs = _pair_count(num_patterns)
        per_pair = values[2:].reshape(pairs, 3, 3)
        bases = []
        for j in range(pairs):
            channels = []
            for channel in range(3):
                a, b, c = per_pair[j, channel]
                if channel == self.radial_channel(j):
                    channels.append(_radial(x, y, a, b, c))
                else:
                    channels.append(_ramp(x, y, a, b, c))
            bases.append(torch.stack(channels, dim=-1))
        return _levels(values, _with_complements(torch.stack(bases), num_patterns))


class MonoComplementary(Family):
    """Grey binary halves (``hi`` on one side, ``lo`` on the other) in complementary pairs.

    ceil(M/2) split orientations evenly spaced over 180 deg, starting with the bright side at +x;
    pattern 2j is split j and 2j + 1 its complement (M = 4: right, left, top, bottom halves, as
    published; odd M drops the last complement). M = 2..12. Parameters: lo, hi and per split j
    ``angle_deg_j`` (bright direction) and ``offset_j`` (edge position in cells along it from the
    panel centre; the default puts the edge between two rows or columns).
    """

    name = "mono_complementary"
    summary = "grey binary halves with complements (M = 4: right, left, top, bottom); M = 2..12"
    min_patterns = 2

    def max_patterns(self, rows, cols):
        return _MAX_PAIRED_PATTERNS

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        params = _level_parameters(preset)
        pairs = _pair_count(num_patterns)
        size = float(max(rows, cols))
        for j in range(pairs):
            angle = _wrap_deg(-j * 180.0 / pairs)
            params.append(Parameter(f"angle_deg_{j}", -360.0, 360.0, angle))
            params.append(Parameter(f"offset_{j}", -size, size, _default_split_offset(angle, rows, cols)))
        return params

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        x, y = _cell_coordinates(rows, cols, values)
        splits = values[2:].reshape(-1, 2)
        weights = _split(x, y, splits[:, 0], splits[:, 1], sharpness)
        return _grey(_levels(values, _with_complements(weights, num_patterns)))


class TriComplementary(Family):
    """Colour patterns whose R, G and B halves are complementary, each followed by its complement.

    ceil(M/2) base patterns; pattern 2j is base j, 2j + 1 its complement. Base 0 is published: R
    lights the left half, G the right half, B the top half. Base j rotates all three splits by
    -j * 180 / A deg, A = ceil(M/2). M = 2..12. Parameters: lo, hi and per base j and channel X
    ``pairJ_X_angle_deg`` (bright direction) and ``pairJ_X_offset`` (edge position, cells).
    """

    name = "tri_complementary"
    summary = "R/G/B halves (R left, G right, B top) with complements; M = 2..12"
    min_patterns = 2

    def max_patterns(self, rows, cols):
        return _MAX_PAIRED_PATTERNS

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        params = _level_parameters(preset)
        pairs = _pair_count(num_patterns)
        size = float(max(rows, cols))
        for j in range(pairs):
            offsets = {}
            for channel, base_angle in zip(_CHANNELS, (180.0, 0.0, -90.0)):
                angle = _wrap_deg(base_angle - j * 180.0 / pairs)
                # G faces R's opposite direction: the negated offset puts its edge on R's, so the
                # halves stay complementary where the tie rule would shift each edge its own way
                # (an odd number of cells across the split).
                offset = -offsets["r"] if channel == "g" else _default_split_offset(angle, rows, cols)
                offsets[channel] = offset
                params.append(Parameter(f"pair{j}_{channel}_angle_deg", -360.0, 360.0, angle))
                params.append(Parameter(f"pair{j}_{channel}_offset", -size, size, offset))
        return params

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        x, y = _cell_coordinates(rows, cols, values)
        splits = values[2:].reshape(-1, 3, 2)
        weights = _split(x, y, splits[..., 0], splits[..., 1], sharpness)  # (A, 3, R, C)
        return _levels(values, _with_complements(weights.permute(0, 2, 3, 1), num_patterns))


class _RandomFamily(Family):
    """Random set values per superpixel; the values themselves are the parameters, in [0, 1].

    The defaults are drawn with a ``torch.Generator`` seeded with ``seed`` in float32, exactly as the
    published patterns were (seed 0 reproduces them), so they are identical for both presets.
    M = 1..1000.
    """

    channels = 3
    values_are_parameters = True

    def max_patterns(self, rows, cols):
        return _MAX_RANDOM_PATTERNS

    def _draw(self, shape: tuple[int, ...], generator: torch.Generator) -> torch.Tensor:
        raise NotImplementedError

    def _parameters(self, num_patterns, rows, cols, preset, seed):
        shape = (num_patterns, rows, cols, self.channels)
        drawn = self._draw(shape, torch.Generator().manual_seed(seed)).clamp(0.0, 1.0)
        defaults = drawn.double().reshape(-1).tolist()
        names = (
            f"value_{m}_{r}_{c}" + (f"_{_CHANNELS[ch]}" if self.channels == 3 else "")
            for m, r, c, ch in np.ndindex(*shape)
        )
        return [Parameter(name, 0.0, 1.0, value) for name, value in zip(names, defaults)]

    def _generate(self, values, num_patterns, rows, cols, sharpness):
        patterns = values.reshape(num_patterns, rows, cols, self.channels)
        return patterns.expand(num_patterns, rows, cols, 3)


class MonoRandom(_RandomFamily):
    """Uniform random grey value per superpixel (``torch.rand``), equal in all channels."""

    name = "mono_random"
    summary = "uniform random grey per superpixel (seeded); M = 1..1000"
    channels = 1

    def _draw(self, shape, generator):
        return torch.rand(shape, generator=generator, dtype=torch.float32)


class TriRandom(_RandomFamily):
    """Uniform random value per superpixel and channel (``torch.rand``)."""

    name = "tri_random"
    summary = "uniform random colour per superpixel (seeded); M = 1..1000"

    def _draw(self, shape, generator):
        return torch.rand(shape, generator=generator, dtype=torch.float32)


class GrayNoise(_RandomFamily):
    """Grey with small noise: 0.5 + 0.01 N(0, 1) per superpixel and channel (``torch.randn``)."""

    name = "gray_noise"
    summary = "0.5 grey plus 0.01-std Gaussian noise per superpixel and channel (seeded); M = 1..1000"

    def _draw(self, shape, generator):
        return _GRAY_NOISE_MEAN + _GRAY_NOISE_STD * torch.randn(shape, generator=generator, dtype=torch.float32)


FAMILIES: dict[str, Family] = {
    family.name: family
    for family in (
        Olat(),
        GroupedOlat(),
        MonoGradient(),
        TriGradient(),
        MonoComplementary(),
        TriComplementary(),
        MonoRandom(),
        TriRandom(),
        GrayNoise(),
    )
}
"""Every family by its command-line name (DESIGN section 6)."""


def get_family(name: str) -> Family:
    """The family called ``name``; an unknown name raises ``InputError`` listing the valid ones."""
    family = FAMILIES.get(name)
    if family is None:
        raise InputError(f"unknown pattern family {name!r}; families: {', '.join(FAMILIES)}")
    return family


def default_vector(
    name: str, num_patterns: int, rows: int = 9, cols: int = 16, preset: str = "default", seed: int = 0, **overrides: float
) -> torch.Tensor:
    """The preset's starting parameter vector, with some parameters set by name.

    Args:
        name: family name.
        num_patterns: M.
        rows, cols: display grid R x C.
        preset: ``"default"`` or ``"ddps"``.
        seed: seed of the random families' defaults.
        **overrides: parameter name -> value (e.g. ``lo=0.05``), each within its bounds.

    Returns:
        (P,) float64 parameter vector.
    """
    params = get_family(name).parameters(num_patterns, rows, cols, preset, seed)
    index = {p.name: i for i, p in enumerate(params)}
    vector = [p.default for p in params]
    for key, value in overrides.items():
        if key not in index:
            shown = ", ".join(list(index)[:12]) + (", ..." if len(index) > 12 else "")
            raise InputError(f"{name} has no parameter {key!r}; parameters: {shown}")
        param = params[index[key]]
        if not is_real_number(value):
            raise InputError(f"{name}: {key} must be a number, got {value!r}")
        value = float(value)
        if not param.low <= value <= param.high:
            raise InputError(f"{name}: {key} = {value:g} is outside its bounds [{param.low:g}, {param.high:g}]")
        vector[index[key]] = value
    return torch.tensor(vector, dtype=torch.float64)


def bounds(name: str, num_patterns: int, rows: int = 9, cols: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(low, high): (P,) float64 search bounds of the family's parameter vector."""
    return get_family(name).bounds(num_patterns, rows, cols)


def make_patterns(
    name: str,
    num_patterns: int,
    rows: int = 9,
    cols: int = 16,
    preset: str = "default",
    seed: int = 0,
    sharpness: float = DEFAULT_SHARPNESS,
    **overrides: float,
) -> torch.Tensor:
    """A pattern set of one family at its preset's default parameters.

    Args:
        name: family name (``FAMILIES``).
        num_patterns: M.
        rows, cols: display grid R x C.
        preset: ``"default"`` (lo = 0, hi = 1) or ``"ddps"`` (published lo = 0.1, hi = 0.9).
        seed: seed of the random families.
        sharpness: sigmoid edge slope in 1/cells (see ``Family.generate``).
        **overrides: parameter values by name (see ``default_vector``).

    Returns:
        (M, R, C, 3) float32 display set values in [0, 1].

    Raises:
        InputError: besides bad arguments, a grid too small for the family at this M: a set with
            two identical patterns (a capture would repeat another and the set could not give M
            independent measurements), or one whose ramps or splits run across a single row or
            column (top/bottom halves or vertical ramps on a 1 x N grid are flat, in every
            channel for the grey families and in one for the colour ones; a line of lights cannot
            fix a normal in any case).

    Example:
        >>> make_patterns("olat", 4, preset="ddps")[0, 0, 15, 0].item()  # top-right corner lit
        0.8999999761581421
    """
    vector = default_vector(name, num_patterns, rows, cols, preset, seed, **overrides)
    patterns = get_family(name).generate(vector, num_patterns, rows, cols, sharpness).float().contiguous()
    if torch.unique(patterns.reshape(num_patterns, -1), dim=0).shape[0] < num_patterns:
        raise InputError(f"{name}: M = {num_patterns} on a {rows} x {cols} grid gives identical patterns "
                         f"(the grid is too small for this family at this M, or the parameters make them equal)")
    return patterns
