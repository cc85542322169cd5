"""Near-field effective lighting of display superpixels at surface points, and its moments.

Symbols (DESIGN sections 3 and 4), per pixel with surface point X and superpixel k at p_k:
    d_k = |p_k - X|                   distance, metres
    l_k = (p_k - X) / d_k             unit direction towards the light
    f_k = falloff(d_k)                distance falloff
    s_k = [l_k . n > 0]               attached-shadow mask for the normal n
    b[m, c] = sum_k E[m, k, c] f_k s_k l_k      effective lighting vector of pattern m, channel c

so that a Lambertian point with albedo a (RGB, absorbing the BRDF's 1 / pi) and normal n reads
I[m, c] = a_c * b[m, c] . n.

Never build (N, K, 3) tensors: with the (N, K) matrix w_k = s_k f_k / d_k,
    b[m, c] = sum_k w_k E[m, k, c] p_k - X * sum_k w_k E[m, k, c],
so every b of every pixel comes from one matrix product with the (K, 12 M) "lighting matrix"
G[k, (m, c, :)] = (E[m, k, c] p_k, E[m, k, c]). The shadow test is a matrix product too:
l_k . n > 0  <=>  p_k . n - X . n > 0.

``LightField`` keeps one (pixels x lights) matrix, the unshadowed weights f_k / d_k; shadow masks
and their products are formed in blocks of pixels that stay in the CPU cache and never stored.

Layout: per-pixel quantities keep pixels on the last, contiguous axis (b is (M, 3, 3, N), the
moments (3, 6, N)) so that the per-pixel 3x3 algebra runs as wide elementwise operations.
Symmetric 3x3 moments store their 6 distinct entries in the order of ``SYMMETRIC_PAIRS``.
"""
from __future__ import annotations

import numpy as np
import torch

from capture_sim.errors import InputError, check_array
from capture_sim.geometry import view_directions
from capture_sim.rig import Falloff, check_falloff, falloff_at

SYMMETRIC_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
"""(row, column) of the 6 stored entries of a symmetric 3x3 matrix: xx, yy, zz, xy, xz, yz."""


CACHE_FLOATS = 1 << 18
"""Entries of one (pixels x lights) temporary in the blocked loops: 1 MB in float32, about one
core's L2 cache (larger blocks spill to memory and run ~2x slower)."""


SEES_ALL_FLOATS = 1 << 20
"""Entries of one (hull lights x pixels) temporary of ``LightField.sees_all`` (4 MB in float32)."""


class LightField:
    """The superpixels' light at N surface points, evaluated in blocks of pixels.

    Geometry is a constant: no gradients flow to points, lights or the falloff.

    Attributes:
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        view: (N, 3) unit vectors towards the camera centre.
        bad: (N,) bool, the point is not in front of the camera (z <= min_distance), lies within
            ``min_distance`` of a superpixel (its distances are clamped to stay finite), or the
            falloff is unusable there (its weights are zeroed).
    """

    def __init__(self, points: torch.Tensor, lights: torch.Tensor, falloff, min_distance: float, block_size: int):
        """
        Args:
            points: (N, 3) surface points, metres, camera frame.
            lights: (K, 3) superpixel positions, metres, camera frame.
            falloff: callable mapping distances (any shape, metres) to falloff factors, e.g.
                ``capture_sim.rig.Falloff``.
            min_distance: metres; distances are clamped to at least this.
            block_size: pixels per block of (pixels x lights) work.

        Raises:
            InputError: the falloff is not positive and finite at a pixel with good geometry.
        """
        check_falloff(falloff)
        self._set_geometry(points, lights, block_size)
        # The unshadowed weights f_k / d_k are computed once and kept (N x K floats): every later
        # evaluation then costs a shadow test and a matrix product instead of the distances again.
        self.weights, self.bad = self._unshadowed_weights(falloff, min_distance)

    @classmethod
    def from_weights(cls, points: torch.Tensor, lights: torch.Tensor, weights: torch.Tensor, block_size: int) -> "LightField":
        """A field over unshadowed weights computed elsewhere, for callers that solve the same
        pixels many times and keep them (learning: ``reconstruct.unrolled_ps.light_reach``).

        Args:
            points: (N, 3) surface points, metres, camera frame.
            lights: (K, 3) superpixel positions, metres, camera frame.
            weights: (N, K) contiguous f_k / d_k, positive and finite (not checked: a scan of
                N x K values would cost more than the solve it serves). Used as is, not copied.
            block_size: pixels per block of (pixels x lights) work.

        No pixel is marked ``bad``: the caller vouches for the geometry.
        """
        check_array("weights", weights, (points.shape[0], lights.shape[0]), finite=False)
        if not weights.is_contiguous():
            raise InputError("LightField.from_weights needs contiguous (N, K) weights (pixel-major)")
        if weights.dtype != points.dtype:
            raise InputError(f"LightField.from_weights: weights are {weights.dtype} but points are {points.dtype}")
        field = cls.__new__(cls)
        field._set_geometry(points, lights, block_size)
        field.weights, field.bad = weights, torch.zeros(points.shape[0], dtype=torch.bool)
        return field

    def _set_geometry(self, points: torch.Tensor, lights: torch.Tensor, block_size: int) -> None:
        self.points = points
        self.lights = lights
        self.block_size = block_size
        self.cache_block = min(block_size, max(64, CACHE_FLOATS // max(1, lights.shape[0])))
        self._lights_t = lights.T.contiguous()
        self.view = view_directions(points, torch.finfo(points.dtype).tiny ** 0.5)
        self._corners = lights[extreme_lights(lights)]

    @property
    def num_pixels(self) -> int:
        return self.points.shape[0]

    def _unshadowed_weights(self, falloff, min_distance: float):
        """(N, K) f_k / d_k (zeroed where the falloff is unusable) and the (N,) bad-geometry flags."""
        light_norms = (self.lights * self.lights).sum(1)[None, :]
        # f / d = d^-3 for the physical falloff: cheaper than a generic call, positive after the clamp.
        inverse_square = isinstance(falloff, Falloff) and falloff.kind == "inverse_square"
        weights = torch.empty((self.num_pixels, self.lights.shape[0]), dtype=self.points.dtype)
        bad = self.points[:, 2] <= min_distance
        for start, stop, block in self.cache_rows(None):
            points = self.points[block]
            # d^2 = |p|^2 + |X|^2 - 2 X.p as one matrix product; the mild cancellation is harmless
            # at the rig's scales (d >= ~0.1 m for points the camera can see).
            squared = torch.addmm(light_norms, points, self._lights_t, alpha=-2.0)
            squared.add_((points * points).sum(1, keepdim=True))
            bad[block] |= squared.amin(1) < min_distance**2
            squared.clamp_(min=min_distance**2)
            if inverse_square:
                inverse = squared.rsqrt_()
                torch.mul(inverse, inverse, out=weights[block]).mul_(inverse)
                continue
            distance = squared.sqrt_()
            weight = falloff_at(falloff, distance) / distance
            usable = torch.isfinite(weight) & (weight > 0)
            unusable = ~usable.all(1)
            if bool((unusable & ~bad[block]).any()):
                good = distance[~bad[block]]
                raise InputError(
                    f"falloff is not positive and finite over light distances {float(good.min()):.3f}..{float(good.max()):.3f} m"
                )
            bad[block] |= unusable
            weights[block] = torch.where(usable, weight, torch.zeros((), dtype=weight.dtype))
        return weights, bad

    def _lit(self, rows, normal: torch.Tensor) -> torch.Tensor:
        """(n, K) shadow masks of pixels ``rows`` with normals (3, n) as 1.0 / 0.0 in the working
        dtype: p_k . n - X . n > 0. The comparison runs in place on the float product (a bool
        mask would need a type promotion in every later product)."""
        return self._heights(_take_rows(self.points, rows), normal).gt_(0)

    def _heights(self, points: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
        """(n, K) (p_k - X) . n of points (n, 3) with normals (3, n), metres: one matrix product."""
        return torch.addmm(-(points * normal.T).sum(1, keepdim=True), normal.T, self._lights_t)

    def near_tangent(self, rows, normal: torch.Tensor, sine: float) -> tuple[torch.Tensor, torch.Tensor]:
        """(falloff f_k (n, K), near (n, K) bool) of pixels ``rows`` (slice or indices) with
        normals (3, n): near where |l_k . n| <= ``sine``, superpixel k within asin(sine) of the
        pixel's tangent plane. Zero falloff where the weights were zeroed (bad geometry)."""
        points = _take_rows(self.points, rows)
        distance = torch.cdist(points, self.lights).clamp_min(torch.finfo(points.dtype).tiny)
        return _take_rows(self.weights, rows) * distance, self._heights(points, normal).abs() <= sine * distance

    def sees_all(self, index, normal: torch.Tensor) -> torch.Tensor:
        """(n,) bool: whether pixels ``index`` ((n,) long indices, or None for all) with normals
        (3, n) see every light (``sees_all_lights``: a test on the few hull lights that never
        claims a shadowed light is lit). Runs in chunks whose (hull lights x pixels) product
        stays near ``SEES_ALL_FLOATS`` entries: per cache block, the calls' overhead would cost
        more than the test; in one piece, the product of a full frame would take ~100 MB."""
        points = self.points.T if index is None else _take_rows(self.points, index).T
        count = normal.shape[1]
        step = max(1, SEES_ALL_FLOATS // self._corners.shape[0])
        if count <= step:
            return sees_all_lights(normal, points, self._corners)
        return torch.cat([sees_all_lights(normal[:, start : start + step], points[:, start : start + step], self._corners)
                          for start in range(0, count, step)])

    def block_rows(self, index, block_size: int | None = None):
        """Yield (start, stop, rows): blocks of entries start:stop of ``index`` ((n,) long pixel
        indices, or None for all N pixels) and their pixel rows (a slice or index tensor).
        Blocks have ``block_size`` entries (default: the field's block size)."""
        size = block_size or self.block_size
        count = self.num_pixels if index is None else index.numel()
        for start in range(0, count, size):
            stop = min(start + size, count)
            yield start, stop, (slice(start, stop) if index is None else index[start:stop])

    def cache_rows(self, index):
        """``block_rows`` in blocks whose (pixels x lights) temporaries fit the CPU's L2 cache."""
        return self.block_rows(index, self.cache_block)

    def masks_differ(self, index, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """(n,) bool: whether normals ``first`` and ``second`` (3, n) of pixels ``index`` (or all)
        have different shadow masks. Compared block by block, never stored."""
        differ = torch.empty(first.shape[1], dtype=torch.bool)
        both_whole = self.sees_all(index, first) & self.sees_all(index, second)
        for start, stop, rows in self.cache_rows(index):
            if bool(both_whole[start:stop].all()):
                differ[start:stop] = False  # both masks are all ones
                continue
            lit = self._lit(rows, first[:, start:stop])
            differ[start:stop] = lit.ne_(self._lit(rows, second[:, start:stop])).amax(dim=1) > 0
        return differ

    def shadowed_weights(self, rows, normal: torch.Tensor, whole: torch.Tensor) -> torch.Tensor:
        """(n, K) s_k f_k / d_k of pixels ``rows`` (slice or indices) with normals (3, n); a view
        of the stored weights (not to be modified) when every pixel of the block sees every
        light (``whole``, their (n,) ``sees_all``), which skips the (n, K) shadow test for most
        pixels facing the display."""
        if bool(whole.all()):
            return _take_rows(self.weights, rows)
        return self._lit(rows, normal).mul_(_take_rows(self.weights, rows))

    def vector_blocks(self, index, normal: torch.Tensor, lighting: torch.Tensor, whole: torch.Tensor | None = None,
                      out: torch.Tensor | None = None):
        """Effective lighting vectors with the attached shadows of the given normals, by blocks.

        Args:
            index: (n,) long pixel indices, or None for all N pixels.
            normal: (3, n) normals of those pixels.
            lighting: (K, 12 M) lighting matrix from ``lighting_matrix`` (used as a constant).
            whole: optional (n,) ``sees_all(index, normal)``, if the caller has it already.
            out: optional (M, 3, 3, n) tensor that receives the vectors of all blocks (the yielded
                blocks are views of it), so a caller that keeps them copies nothing.

        Yields:
            (start, stop, vectors): the block covers entries start:stop of ``index``; vectors
            (M, 3, 3, stop - start) b[m, c, :, n] = sum_k E[m, k, c] f_k s_k l_k.
        """
        lighting = lighting.detach()
        if whole is None:
            whole = self.sees_all(index, normal)
        for start, stop, rows in self.block_rows(index):
            # The (pixels x lights) work runs in cache-sized sub-blocks, the per-pixel algebra on
            # the caller's larger blocks (fewer small operations).
            # Pixels last and contiguous, as the per-pixel algebra wants them (on a pixel-major
            # layout it runs several times slower): each product G^T W^T writes its columns of
            # the (12 M, n) sums directly (a transposing copy of W G cost ~1.7x the products).
            summed = torch.empty((lighting.shape[1], stop - start), dtype=lighting.dtype)
            for sub_start in range(0, stop - start, self.cache_block):
                sub_stop = min(sub_start + self.cache_block, stop - start)
                sub_rows = slice(start + sub_start, start + sub_stop) if index is None else rows[sub_start:sub_stop]
                block = slice(start + sub_start, start + sub_stop)
                torch.mm(lighting.T, self.shadowed_weights(sub_rows, normal[:, block], whole[block]).T, out=summed[:, sub_start:sub_stop])
            summed = summed.view(-1, 3, 4, stop - start)
            vectors = summed.new_empty((summed.shape[0], 3, 3, stop - start)) if out is None else out[..., start:stop]
            torch.mul(_take_rows(self.points, rows).T[None, None], summed[:, :, 3:], out=vectors)
            yield start, stop, torch.sub(summed[:, :, :3], vectors, out=vectors)


def _take_rows(values: torch.Tensor, rows) -> torch.Tensor:
    """values[rows] for a slice or (n,) long indices; ``index_select`` gathers rows several times
    faster than advanced indexing on CPU."""
    return values[rows] if isinstance(rows, slice) else values.index_select(0, rows)


PLANAR_TOLERANCE_M = 1e-7
"""Lights within this distance (metres) of their best-fitting plane are treated as coplanar."""


def extreme_lights(lights: torch.Tensor) -> torch.Tensor:
    """Indices of the lights at the vertices of their convex hull.

    A tangent plane has every light in front of it exactly when it has these in front of it
    (l_k . n > 0 is linear in p_k, and a linear function's minimum over the lights is attained at
    a hull vertex), so the test whether a pixel sees every light needs only these. Lights in a
    plane (a flat display) have their hull taken in that plane. Cached by light positions: a
    rig's lights are fixed, and learning asks every step.

    Args:
        lights: (K, 3) superpixel positions, metres, camera frame.

    Returns:
        (E,) long indices into the lights, sorted (all K if the hull cannot be formed).

    Raises:
        InputError: ``lights`` is not a non-empty finite (K, 3) array.
    """
    check_array("lights", lights, ("K", 3))
    if lights.shape[0] < 1:
        raise InputError("lights must hold at least one superpixel")
    positions = lights.detach().double().cpu().numpy()
    key = positions.tobytes()
    if key not in _EXTREME_CACHE:
        _EXTREME_CACHE[key] = _hull_vertices(positions)
    return _EXTREME_CACHE[key]


_EXTREME_CACHE: dict = {}


def _hull_vertices(positions: np.ndarray) -> torch.Tensor:
    from scipy.spatial import ConvexHull, QhullError

    centred = positions - positions.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    spread = np.abs(centred @ axes.T).max(axis=0)  # extent along the principal axes, metres
    dimensions = int((spread > PLANAR_TOLERANCE_M).sum())
    if dimensions <= 1:  # one light, or lights on a line: its two ends
        along = centred @ axes[0]
        return torch.tensor(sorted({int(along.argmin()), int(along.argmax())}))
    try:
        vertices = ConvexHull(centred @ axes[:dimensions].T).vertices
    except QhullError:
        return torch.arange(positions.shape[0])
    return torch.as_tensor(np.sort(vertices), dtype=torch.long)


def sees_all_lights(normal: torch.Tensor, points: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """Whether every light is certainly in front of each pixel's tangent plane.

    Args:
        normal: (3, n) normals.
        points: (3, n) surface points, metres, camera frame.
        corners: (E, 3) the lights ``extreme_lights`` selects.

    Returns:
        (n,) bool. True means the shadow mask s_k = [p_k . n - X . n > 0] is all ones. The test
        keeps a margin of 64 rounding units over the shadow test's own rounding, so pixels whose
        tangent plane passes within it of a hull light answer False (and take the full test);
        so do pixels with non-finite values.

    Raises:
        InputError: shapes do not match. Values are not scanned (a hot path of learning).
    """
    check_array("normal", normal, (3, "n"), finite=False)
    check_array("points", points, (3, normal.shape[1]), finite=False)
    check_array("corners", corners, ("E", 3), finite=False)
    scale = corners.abs().amax() + points.abs().amax(dim=0)
    margin = 64 * torch.finfo(normal.dtype).eps * scale
    height = (normal * points).sum(0)
    return (corners @ normal).amin(dim=0) - height > margin


def emission_scale(emission: torch.Tensor) -> torch.Tensor:
    """The largest |emission| of an effective emission of any shape (e.g. (M, K, 3) or an OLAT
    stack's (K, 3)), in the emission's units, as a detached 0-d tensor; 1 for an all-zero emission.

    Solvers divide the emission by it and the albedo by it afterwards (``unscale_albedo``): the
    model I = a b . n is unchanged, and squared lighting terms stay inside the dtype's range for
    any overall radiance scale (an OLAT stack in other units, an exposure of 1e-30 or 1e20).
    The solution is homogeneous in the emission, so the gradient through the detached scale is
    exact."""
    peak = emission.detach().abs().amax()
    return torch.where(peak > 0, peak, torch.ones_like(peak))


def finite_albedo(albedo: torch.Tensor) -> torch.Tensor:
    """Albedo (any shape, >= 0; callers have divided it back by ``emission_scale``) with +inf (from
    an emission near the dtype's smallest normal number) replaced by the dtype's largest finite
    value. A clamp, not ``nan_to_num``: a NaN would be a solver bug, not something to turn into a
    plausible 0."""
    return albedo.clamp(max=torch.finfo(albedo.dtype).max)


def lighting_matrix(emission: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
    """The matrix G that turns shadowed falloff weights into effective lighting vectors.

    Args:
        emission: (M, K, 3) effective emission E (exposure included).
        lights: (K, 3) superpixel positions, metres, camera frame.

    Returns:
        (K, M * 3 * 4) with G[k, (m, c, 0:3)] = E[m, k, c] p_k and G[k, (m, c, 3)] = E[m, k, c];
        differentiable in ``emission``.
    """
    num_patterns, num_lights, _ = emission.shape
    per_light = emission.permute(1, 0, 2)[..., None]  # (K, M, 3, 1)
    homogeneous = torch.cat([lights, torch.ones_like(lights[:, :1])], dim=1)  # (K, 4)
    return (per_light * homogeneous[:, None, None, :]).reshape(num_lights, num_patterns * 12)


class _ShadowedLighting(torch.autograd.Function):
    """b = vectors(G) for fixed geometry and normals; the value is supplied, and the shadowed
    (pixels x lights) weights are re-formed block by block in the backward pass instead of being
    kept in the autograd graph."""

    @staticmethod
    def forward(ctx, lighting, values, field, normal, whole):
        ctx.field, ctx.normal, ctx.whole = field, normal, whole
        return values  # autograd returns an input as a view of it: no copy

    @staticmethod
    def backward(ctx, grad_vectors):
        field, normal = ctx.field, ctx.normal
        # b = S[:3] - X S[3] with S = (w G)^T, so dL/dS[:3] = dL/db and dL/dS[3] = -X . dL/db,
        # written into one buffer: the products below then read the (N, K) weights once.
        grad_summed = grad_vectors.new_empty((*grad_vectors.shape[:2], 4, field.num_pixels))
        grad_summed[:, :, :3] = grad_vectors
        x, y, z = field.points.T
        torch.mul(grad_vectors[:, :, 0], x, out=grad_summed[:, :, 3]).addcmul_(grad_vectors[:, :, 1], y).addcmul_(grad_vectors[:, :, 2], z).neg_()
        grad_summed = grad_summed.view(-1, field.num_pixels)  # (12 M, N)
        # The pixels that see every light in one product over the stored weights (the others'
        # gradients zeroed there), then those others with their shadow masks: masks are formed
        # for them alone (the pixels are mixed, so almost every block of the whole set would
        # need them), and nothing cancels (a clamped weight of a light behind a point on the
        # display is ~1e9: subtracting it from a sum would leave float32 rounding noise).
        whole = field.sees_all(None, normal) if ctx.whole is None else ctx.whole
        shadowed = torch.nonzero(~whole).squeeze(1)
        grad_shadowed = grad_summed.index_select(1, shadowed)
        grad_lighting = torch.mm(field.weights.T, grad_summed.index_fill_(1, shadowed, 0.0).T)  # (K, 12 M)
        for start, stop, rows in field.cache_rows(shadowed):
            lit = field.shadowed_weights(rows, normal.index_select(1, rows), whole[rows])
            grad_lighting.addmm_(lit.T, grad_shadowed[:, start:stop].T)
        return grad_lighting, None, None, None, None


def differentiable_vectors(field: LightField, normal: torch.Tensor, lighting: torch.Tensor, values: torch.Tensor, whole: torch.Tensor | None = None) -> torch.Tensor:
    """Lighting vectors of all N pixels as a differentiable function of the lighting matrix.

    Args:
        field: the pixels' light field.
        normal: (3, N) normals that fix the shadow masks.
        lighting: (K, 12 M) lighting matrix carrying gradients.
        values: (M, 3, 3, N) the vectors of ``field.vector_blocks(None, normal, lighting)``,
            already computed.
        whole: optional (N,) ``field.sees_all(None, normal)``, if the caller has it already.

    Returns:
        (M, 3, 3, N) equal to ``values``, with gradients to ``lighting``.
    """
    return _ShadowedLighting.apply(lighting, values.detach(), field, normal.detach(), whole)


def _moments_forward(vectors, captures, weight):
    # Accumulating pattern by pattern keeps the temporaries small (several times faster than
    # forming (M, ...) products and reducing them).
    weighted = vectors * weight[:, :, None]
    entries = [weighted[0, :, i] * vectors[0, :, j] for i, j in SYMMETRIC_PAIRS]
    projection = weighted[0] * captures[0, :, None]
    for m in range(1, vectors.shape[0]):
        for entry, (i, j) in zip(entries, SYMMETRIC_PAIRS):
            entry.addcmul_(weighted[m, :, i], vectors[m, :, j])
        projection.addcmul_(weighted[m], captures[m, :, None])
    energy = (weight * captures * captures).sum(0)
    return torch.stack(entries, dim=1), projection, energy


class _LightingMoments(torch.autograd.Function):
    """Moments with a hand-written backward: autograd through the sliced in-place accumulation
    would allocate a full-size gradient per slice and be ~10x slower."""

    @staticmethod
    def forward(ctx, vectors, captures, weight, known):
        ctx.save_for_backward(vectors, captures, weight)
        ctx.set_materialize_grads(False)  # an unused output (the unrolled solver's energy) costs nothing
        count = vectors.shape[-1]
        if known is not None:  # clones: the outputs get this node as their history
            return known[0].clone(), known[1].clone(), (weight * captures * captures).sum(0)
        if count <= MOMENT_BLOCK:
            return _moments_forward(vectors, captures, weight)
        outputs = (vectors.new_empty((3, 6, count)), vectors.new_empty((3, 3, count)), vectors.new_empty((3, count)))
        for block in _pixel_blocks(count):
            for output, value in zip(outputs, _moments_forward(vectors[..., block], captures[..., block], weight[..., block])):
                output[..., block] = value
        return outputs

    @staticmethod
    def backward(ctx, grad_moment, grad_projection, grad_energy):
        vectors, captures, weight = ctx.saved_tensors
        grad_vectors, grad_captures = torch.empty_like(vectors), torch.empty_like(captures)
        if grad_projection is None:
            grad_projection = torch.zeros((3, 3, vectors.shape[-1]), dtype=vectors.dtype)
        for block in _pixel_blocks(vectors.shape[-1]):
            _moments_backward(
                vectors[..., block], captures[..., block], weight[..., block],
                None if grad_moment is None else grad_moment[..., block], grad_projection[..., block],
                None if grad_energy is None else grad_energy[..., block], grad_vectors[..., block], grad_captures[..., block],
            )
        return grad_vectors, grad_captures, None, None


MOMENT_BLOCK = 8192
"""Pixels per block of the moments' elementwise work (temporaries stay in cache)."""


def _pixel_blocks(count: int):
    return (slice(start, min(start + MOMENT_BLOCK, count)) for start in range(0, count, MOMENT_BLOCK))


_FULL_SYMMETRIC = torch.tensor([0, 3, 4, 3, 1, 5, 4, 5, 2])
"""Entries of SYMMETRIC_PAIRS at the 9 places (row-major) of the full symmetric matrix."""
_DIAGONAL_TWICE = torch.tensor([2.0, 1, 1, 1, 2, 1, 1, 1, 2])[:, None]


def _moments_backward(vectors, captures, weight, grad_moment, grad_projection, grad_energy, grad_vectors, grad_captures):
    """Writes dL/db into ``grad_vectors`` (M, 3, 3, n) and dL/dI into ``grad_captures`` (M, 3, n);
    ``grad_moment`` and ``grad_energy`` may be None (the output was not used)."""
    # dB_c/db: d(b_i b_j)/db_i = b_j, so dL/db_i = q sum_j S_ij b_j with S the symmetric
    # gradient (diagonal entries doubled); dr_c/db_i = q I; dr_c/dI = q b; d(q I^2)/dI = 2 q I.
    torch.mul(grad_projection[None], captures[:, :, None], out=grad_vectors)
    if grad_moment is not None:
        symmetric = (grad_moment[:, _FULL_SYMMETRIC] * _DIAGONAL_TWICE.to(grad_moment.dtype)).view(3, 3, 3, -1)  # (3 c, 3 i, 3 j, n)
        for j in range(3):
            grad_vectors.addcmul_(symmetric[None, :, :, j], vectors[:, :, None, j])
    grad_vectors *= weight[:, :, None]
    through = (grad_projection[None] * vectors).sum(2)
    if grad_energy is not None:
        through.addcmul_(grad_energy[None].expand_as(captures), captures, value=2)
    torch.mul(weight, through, out=grad_captures)


def lighting_moments(lighting_vectors: torch.Tensor, captures: torch.Tensor, equation_weight: torch.Tensor, known=None):
    """Per-channel normal-equation moments of the model I[m, c] = a_c b[m, c] . n.

    Args:
        lighting_vectors: (M, 3, 3, N) effective lighting vectors b (pattern, channel, xyz, pixel).
        captures: (M, 3, N) captured values.
        equation_weight: (M, 3, N) weight of each equation (0 drops it, e.g. when saturated);
            a constant.
        known: optional (moment, projection) the caller already formed from these same values
            without gradient (not checked): they are returned, with gradients, instead of being
            formed again.

    Returns:
        moment: (3, 6, N) symmetric B_c = sum_m q b b^T (channel, entry of SYMMETRIC_PAIRS, pixel).
        projection: (3, 3, N) r_c = sum_m q I b.
        energy: (3, N) sum_m q I^2.
        Differentiable in ``lighting_vectors`` and ``captures``.
    """
    if torch.is_grad_enabled() and (lighting_vectors.requires_grad or captures.requires_grad):
        return _LightingMoments.apply(lighting_vectors, captures, equation_weight.detach(), known)
    if known is not None:
        return known[0], known[1], (equation_weight * captures * captures).sum(0)
    return _moments_forward(lighting_vectors, captures, equation_weight)


def olat_moments(weight, light_emission, captures, equation_weight, points, lights):
    """The moments of ``lighting_moments`` for one-light-at-a-time captures, without b vectors.

    With capture k lit by superpixel k alone (emission e[k, c]), b[k, c] = e_kc w_k (p_k - X) and
    B_c = sum_k u_kc (p_k - X)(p_k - X)^T, u_kc = q_kc e_kc^2 w_k^2, which expands into products
    of (N, K) weights with per-light tables of p p^T, p and 1: no (N, K, 3) tensor is formed.

    Args:
        weight: (N, K) shadowed falloff weights s_k f_k / d_k.
        light_emission: (K, 3) effective emission e of light k in capture k.
        captures: (3, N, K) OLAT captures of the block, channel-major.
        equation_weight: (3, N, K) weight of each equation (0 drops it).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.

    Returns:
        moment (3, 6, N), projection (3, 3, N) and energy (3, N), as ``lighting_moments``.
    """
    scaled = weight[None, :, :] * light_emission.T[:, None, :]  # (3, N, K): e_kc w_k
    weighted = scaled * equation_weight
    products = torch.stack([lights[:, i] * lights[:, j] for i, j in SYMMETRIC_PAIRS], dim=1)
    table = torch.cat([products, lights, torch.ones_like(lights[:, :1])], dim=1)  # (K, 10)
    moment_terms = torch.matmul(weighted * scaled, table).permute(0, 2, 1)  # (3, 10, N)
    projection_terms = torch.matmul(weighted * captures, table[:, 6:]).permute(0, 2, 1)  # (3, 4, N)
    x = points.T  # (3, N)
    first, total = moment_terms[:, 6:9], moment_terms[:, 9]
    # B_ij = sum u p_i p_j - X_j sum u p_i - X_i sum u p_j + X_i X_j sum u
    moment = torch.stack(
        [
            moment_terms[:, entry] - x[j] * first[:, i] - x[i] * first[:, j] + x[i] * x[j] * total
            for entry, (i, j) in enumerate(SYMMETRIC_PAIRS)
        ],
        dim=1,
    )
    projection = projection_terms[:, :3] - projection_terms[:, 3:] * x[None]
    energy = (equation_weight * captures * captures).sum(2)
    return moment, projection, energy
