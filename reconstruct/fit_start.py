"""The inverse renderer's starting point (steps 1 to 3 of its fit, see ``reconstruct.inverse_render``):
normals and albedos from photometric stereo or, for OLAT captures, a near-field least squares with
reweighting against highlights; invalid pixels filled from their neighbours and every normal tilted
into the visible hemisphere; k-means clusters of hue and saturation as basis assignments; and the
least-squares basis albedos at those normals and clusters.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from capture_sim.errors import InputError, check_array
from capture_sim.geometry import light_geometry, view_directions
from capture_sim.rig import checked_falloff
from reconstruct.basis_render import NORM_FLOOR, EmissionPlan, render_under_patterns
from reconstruct.photometric_stereo import PSConfig, solve_ps



@dataclass(frozen=True, eq=False)
class InitialEstimate:
    """Per-pixel starting point shared by all candidate models of one scene.

    Attributes:
        normal: (N, 3) unit normals from analytic photometric stereo, camera frame.
        albedo: (N, 3) diffuse albedo rho_d = pi * a (PS albedo a absorbs the 1 / pi).
        valid: (N,) bool, the PS solution is usable.
        seconds: wall time of the estimate.
    """

    normal: torch.Tensor
    albedo: torch.Tensor
    valid: torch.Tensor
    seconds: float


def olat_least_squares(captures, plan: EmissionPlan, points, lights, falloff, shadow_threshold: float = 1e-5,
                       saturation_threshold: float = 0.999, reweight_steps: int = 3, chunk_pixels: int = 4096):
    """Near-field Woodham photometric stereo for captures that light one superpixel per pattern.

    Per pixel, y[m, c] = I[m, c] / E[m, k_m, c] = a_c f_m (l_m . n) on lit equations. The
    channel-mean of y is fitted by least squares for g = mean(a) n over equations that are lit
    (above ``shadow_threshold``: attached shadows read 0) and unsaturated; iteratively reweighted
    least squares with Cauchy weights then discounts specular highlights (large positive
    residuals). Finally a_c = sum_m w y s / sum_m w s^2 with s = f (l . n)+ and the final weights w.
    An equation counts as lit when at least one channel is above the threshold.

    Args:
        captures: (M, N, 3) captures in [0, 1].
        plan: emission plan of an OLAT-style emission (``plan.gain`` is not None).
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff, positive and finite over the scene (else ``InputError``).
        shadow_threshold: captures at or below this are shadowed. Deliberately tiny: with auto
            exposure set by specular highlights, the diffuse captures of a glossy object are dim
            (1e-4..1e-3) but carry the normal; a cut near 1e-3 leaves only highlights (40 degrees
            error on a glossy blob against 11 with this default).
        saturation_threshold: captures at or above this are saturated.
        reweight_steps: IRLS steps after the plain least squares.
        chunk_pixels: pixels solved at once.

    Returns:
        normal (N, 3) unit, albedo a (N, 3) (rho / pi), valid (N,) bool.
    """
    count = captures.shape[1]
    normal = torch.empty((count, 3), dtype=torch.float64)
    albedo = torch.empty((count, 3), dtype=torch.float64)
    valid = torch.empty(count, dtype=torch.bool)
    gain = plan.gain.detach().double()  # (M, 3)
    plan_lights = lights.double()[plan.light_index]
    for start in range(0, count, chunk_pixels):
        block = slice(start, start + chunk_pixels)
        observed = captures[:, block].double().permute(1, 0, 2)  # (B, M, 3)
        light_dirs, distance = light_geometry(points[block].double(), plan_lights, 1e-3)
        lighting = light_dirs * checked_falloff(falloff, distance)[..., None]  # f l, (B, M, 3)
        positive_gain = gain > 0
        ratio = torch.where(positive_gain, observed / gain.clamp_min(1e-30), torch.zeros((), dtype=torch.float64))  # y, (B, M, 3)
        grey = ratio.sum(-1) / positive_gain.sum(-1).clamp_min(1)
        # Lit in at least one channel (a saturated red object reads 0 in green and blue), none saturated.
        usable = ((observed > shadow_threshold).any(-1) & (observed < saturation_threshold).all(-1)).double()
        weight = usable
        solution = torch.zeros((observed.shape[0], 3), dtype=torch.float64)
        for step in range(reweight_steps + 1):
            system = torch.einsum("bm,bmi,bmj->bij", weight, lighting, lighting)
            rhs = torch.einsum("bm,bm,bmi->bi", weight, grey, lighting)
            damping = 1e-9 * system.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(1e-30) / 3
            system = system + damping[:, None, None] * torch.eye(3, dtype=torch.float64)
            solution = torch.linalg.solve(system, rhs[..., None]).squeeze(-1)
            if step == reweight_steps:
                break
            residual = grey - (lighting * solution[:, None]).sum(-1)
            scale = (residual.abs() * usable).sum(-1, keepdim=True) / usable.sum(-1, keepdim=True).clamp_min(1)
            weight = usable / (1.0 + (residual / (2.0 * scale + 1e-30)).square())
        length = solution.norm(dim=-1)
        unit = solution / length[:, None].clamp_min(1e-30)
        shading = (lighting * unit[:, None]).sum(-1).clamp_min(0.0) * usable  # (B, M)
        # The final IRLS weights keep specular highlights out of the per-channel albedo too (it
        # seeds the clustering of materials).
        weighted_shading = weight * shading
        channel_albedo = (ratio * weighted_shading[..., None]).sum(1) / (weighted_shading * shading).sum(1)[:, None].clamp_min(1e-30)
        good = (usable.sum(-1) >= 3) & (length > 0) & torch.isfinite(unit).all(-1)
        normal[block] = torch.where(good[:, None], unit, torch.zeros((), dtype=torch.float64))
        albedo[block] = torch.where(good[:, None], channel_albedo.clamp_min(0.0), torch.zeros((), dtype=torch.float64))
        valid[block] = good
    view = view_directions(points.double(), NORM_FLOOR)
    valid &= (normal * view).sum(-1) > 0
    return normal, albedo, valid


def fill_from_neighbours(values: torch.Tensor, known: torch.Tensor, pixel_index: torch.Tensor, height: int, width: int,
                         max_rounds: int = 1000) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill unknown pixels with the mean of their known 4-neighbours, growing inwards round by round.

    Args:
        values: (N, D) per-pixel values.
        known: (N,) bool, pixels whose values are trusted.
        pixel_index: (N,) flat indices of the pixels in the H x W image.
        height, width: image size.
        max_rounds: cap on rounds (each fills the unknown pixels next to known ones).

    Returns:
        filled values (N, D) and the (N,) bool of pixels that now have a value (unreachable
        pixels, in mask components without any known pixel, keep their value and stay False).
    """
    right_down = grid_neighbours(pixel_index, height, width)
    count = values.shape[0]
    pairs = torch.cat([torch.stack([torch.arange(count), right_down[:, i]], 1) for i in range(2)])
    pairs = pairs[pairs[:, 1] >= 0]
    source = torch.cat([pairs[:, 0], pairs[:, 1]])  # both directions: left/up are the reverse pairs
    target = torch.cat([pairs[:, 1], pairs[:, 0]])
    values, known = values.clone(), known.clone()
    for _ in range(max_rounds):
        if bool(known.all()):
            break
        usable = known[source] & ~known[target]
        if not bool(usable.any()):
            break
        total = torch.zeros_like(values).index_add_(0, target[usable], values[source[usable]])
        hits = torch.zeros(count, dtype=values.dtype).index_add_(0, target[usable], torch.ones(int(usable.sum()), dtype=values.dtype))
        newly = hits > 0
        values[newly] = total[newly] / hits[newly, None]
        known = known | newly
    return values, known


def into_visible_hemisphere(normal: torch.Tensor, view: torch.Tensor, margin: float) -> torch.Tensor:
    """Tilt unit normals (N, 3) towards the view (N, 3) until n . v >= margin, keeping their azimuth.

    A start with n . v <= 0 sits where the specular lobe is masked to zero (the surface is not
    seen), so it has no specular gradient to leave by.
    """
    cosine = (normal * view).sum(-1, keepdim=True)
    tangent = normal - cosine * view
    length = tangent.norm(dim=-1, keepdim=True)
    tilted = margin * view + math.sqrt(1.0 - margin * margin) * tangent / length.clamp_min(1e-12)
    return torch.where((cosine < margin) & (length > 1e-6), tilted, torch.where(cosine < margin, view, normal))


def initial_estimate(captures, emission, points, lights, falloff, ps_config: PSConfig = PSConfig(),
                     pixel_index: torch.Tensor | None = None, height: int | None = None, width: int | None = None,
                     visible_margin: float = 0.2) -> InitialEstimate:
    """Analytic photometric stereo as the starting point (DESIGN section 4).

    Multiplexed patterns use ``reconstruct.photometric_stereo.solve_ps``; emissions that light one
    superpixel per pattern (OLAT stacks) use ``olat_least_squares`` (Woodham), which is exact for
    them and much faster than treating M = K one-hot patterns as a multiplexed set. Invalid pixels
    (dark, ill-conditioned...) take the mean normal and albedo of valid 4-neighbours, grown inwards
    (``fill_from_neighbours``) when the image grid is given; otherwise, or where no valid pixel is
    reachable, they face the camera with the median albedo. Every normal is then tilted into
    n . v >= ``visible_margin`` (``into_visible_hemisphere``). The solve does not depend on the
    emission's units.

    Args:
        captures: (M, N, 3) captures in [0, 1].
        emission: (M, K, 3) effective emission.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.
        falloff: distance falloff.
        ps_config: photometric-stereo settings (multiplexed patterns).
        pixel_index: optional (N,) flat indices of the pixels in the H x W image.
        height, width: image size (with ``pixel_index``).
        visible_margin: least n . v of a starting normal.

    Returns:
        InitialEstimate (float32); ``valid`` marks the pixels photometric stereo solved itself.
    """
    start = time.perf_counter()
    check_array("emission", emission, ("M", "K", 3), value_range=(0.0, math.inf))
    if emission.shape[0] == 0:
        raise InputError("initial_estimate needs at least one pattern")
    # Solve with an emission peak near one (a power of two: exact), so that float32 moments
    # neither under- nor overflow whatever its units; the albedo scales back exactly.
    maximum = float(emission.detach().amax())
    peak = 2.0 ** math.frexp(maximum)[1] if maximum > 0 else 1.0
    emission = (emission.double() / peak).to(emission.dtype)
    with torch.no_grad():
        plan = EmissionPlan(emission.detach())
        if plan.gain is not None:
            normal, albedo, valid = olat_least_squares(captures.detach(), plan, points, lights, falloff,
                                                       saturation_threshold=ps_config.saturation_threshold)
        else:
            result = solve_ps(captures.detach(), emission.detach(), points, lights, falloff, ps_config)
            normal, albedo, valid = result.normal, result.albedo, result.valid
    valid = valid & torch.isfinite(normal).all(-1) & torch.isfinite(albedo).all(-1)
    points = points.float()
    view = view_directions(points, NORM_FLOOR)
    normal = torch.where(valid[:, None], normal.float(), view)
    albedo = torch.where(valid[:, None], math.pi * albedo.float(), torch.zeros((), dtype=torch.float32))
    filled = valid
    if pixel_index is not None and bool(valid.any()):
        both, filled = fill_from_neighbours(torch.cat([normal, albedo], 1), valid, pixel_index.long(), height, width)
        normal = torch.where(filled[:, None], both[:, :3], view)
        albedo = both[:, 3:]
    normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(NORM_FLOOR)
    fill = albedo[valid].median(0).values if bool(valid.any()) else torch.full((3,), 0.5)
    albedo = torch.where(filled[:, None], albedo, fill)
    normal = into_visible_hemisphere(normal, view, visible_margin)
    return InitialEstimate(normal, (albedo.double() / peak).float(), valid, time.perf_counter() - start)


def hue_saturation_features(albedo: torch.Tensor) -> np.ndarray:
    """(N, 2) colour-wheel coordinates (s cos h, s sin h) of RGB albedos (N, 3) (brightness-free).

    Hue is an angle, so it is clustered as a point on the colour wheel, not as a number that wraps.
    """
    from kornia.color import rgb_to_hsv

    scaled = albedo.detach().float().clamp_min(0.0)
    scaled = scaled / scaled.max().clamp_min(1e-12)
    hsv = rgb_to_hsv(scaled.T.reshape(1, 3, -1, 1)).reshape(3, -1)  # hue in [0, 2 pi], saturation in [0, 1]
    hue, saturation = hsv[0], hsv[1]
    return torch.stack([saturation * torch.cos(hue), saturation * torch.sin(hue)], dim=1).numpy().astype(np.float64)


def cluster_albedo(albedo: torch.Tensor, valid: torch.Tensor, num_basis: int, seed: int = 0,
                   restarts: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """k-means on hue and saturation: cluster labels and per-cluster diffuse albedos.

    Args:
        albedo: (N, 3) pseudo-diffuse albedo rho_d.
        valid: (N,) bool, pixels whose albedo is trusted (others are assigned to the nearest centre).
        num_basis: J clusters.
        seed: k-means seed (k-means++ initialisation); restart r uses seed + r.
        restarts: k-means runs; the one with the least within-cluster sum of squares is kept.

    Returns:
        labels: (N,) long in [0, J).
        centres: (J, 3) median rho_d of each cluster (the overall median for an empty cluster).
    """
    from scipy.cluster.vq import kmeans2, vq

    features = hue_saturation_features(albedo)
    trusted = features[valid.numpy()] if bool(valid.any()) else features
    overall = albedo[valid].median(0).values if bool(valid.any()) else albedo.median(0).values
    if num_basis == 1 or len(trusted) <= num_basis:
        labels = np.zeros(len(features), dtype=np.int64) if num_basis == 1 or len(trusted) == 0 else np.arange(len(features)) % num_basis
    else:
        best_distortion, centroids = math.inf, None
        for attempt in range(restarts):  # k-means++ lands in local minima: keep the tightest of a few
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # an empty cluster is handled below
                candidate, _ = kmeans2(trusted, num_basis, iter=20, minit="++", seed=seed + attempt)
            distortion = float(np.square(vq(trusted, candidate)[1]).sum())
            if distortion < best_distortion:
                best_distortion, centroids = distortion, candidate
        labels, _ = vq(features, centroids)
    labels = torch.as_tensor(labels, dtype=torch.int64)
    centres = torch.empty((num_basis, 3), dtype=albedo.dtype)
    for j in range(num_basis):
        members = (labels == j) & valid
        if not bool(members.any()):
            members = labels == j
        centres[j] = albedo[members].median(0).values if bool(members.any()) else overall
    return labels, centres.clamp_min(1e-4)


def least_squares_albedos(captures, emission, points, lights, falloff, normal, labels, num_basis: int, specular: bool,
                          roughness: float, saturation_threshold: float = 0.999, max_pixels: int = 16384, seed: int = 0):
    """Basis albedos that best explain the captures at fixed normals, hard labels and roughness.

    With normals, one-hot weights and roughness fixed, the images are linear in the albedos of
    each cluster j: I[m, n, c] = rho_d[j, c] A[m, n, c] + rho_s[j] S[m, n, c], A the image of a
    unit diffuse albedo and S that of a unit specular albedo. Each cluster's 4 x 4 (or, for
    Lambertian bases, per-channel 1 x 1) normal equations are solved over unsaturated equations of
    up to ``max_pixels`` random pixels; a negative rho_s is set to 0 and rho_d re-solved alone.

    Args:
        captures: (M, N, 3) captures.
        emission: (M, K, 3) effective emission.
        points, lights, falloff: geometry (see ``render_under_patterns``).
        normal: (N, 3) unit normals.
        labels: (N,) long cluster of each pixel in [0, J).
        num_basis: J.
        specular: also solve rho_s.
        roughness: the roughness the specular images are rendered with.
        saturation_threshold: captures at or above this are left out.
        max_pixels: pixels used (a seeded random subset when there are more).
        seed: seed of that subset.

    Returns:
        diffuse (J, 3) >= 0, specular (J,) >= 0 (zeros when ``specular`` is False), and
        ``solved`` (J,) bool: False for clusters without pixels, whose albedos are 0 and mean
        nothing (the caller keeps its own start there).
    """
    count = captures.shape[1]
    if count > max_pixels:
        subset = torch.randperm(count, generator=torch.Generator().manual_seed(seed))[:max_pixels]
        captures, points, normal, labels = captures[:, subset], points[subset], normal[subset], labels[subset]
    with torch.no_grad():
        ones = torch.ones((normal.shape[0], 1))
        unit_diffuse = render_under_patterns(normal, points, lights, emission, ones, torch.ones((1, 3)), None,
                                             torch.ones(1), falloff)
        unit_specular = None
        if specular:
            unit_specular = render_under_patterns(normal, points, lights, emission, ones, torch.zeros((1, 3)), torch.ones(1),
                                                  torch.full((1,), roughness), falloff)
    usable = (captures < saturation_threshold).to(captures.dtype)  # (M, N, 3)

    def per_cluster(values):  # (M, N, 3) -> (J, 3) sums over patterns and pixels of each cluster
        return torch.zeros((num_basis, 3), dtype=torch.float64).index_add_(0, labels, values.double().sum(0))

    a_a, a_i = per_cluster(usable * unit_diffuse**2), per_cluster(usable * unit_diffuse * captures)
    diffuse = a_i / a_a.clamp_min(1e-30)
    rho_s = torch.zeros(num_basis, dtype=torch.float64)
    if specular:
        a_s = per_cluster(usable * unit_diffuse * unit_specular)
        s_s = per_cluster(usable * unit_specular**2).sum(1)
        s_i = per_cluster(usable * unit_specular * captures).sum(1)
        # Eliminate rho_d per channel: (S.S - sum_c (A.S)_c^2 / (A.A)_c) rho_s = S.I - sum_c (A.S)_c (A.I)_c / (A.A)_c.
        ratio = a_s / a_a.clamp_min(1e-30)
        reduced = (s_s - (ratio * a_s).sum(1)).clamp_min(1e-30)
        rho_s = ((s_i - (ratio * a_i).sum(1)) / reduced).clamp_min(0.0)
        diffuse = (a_i - rho_s[:, None] * a_s) / a_a.clamp_min(1e-30)
    solved = torch.bincount(labels, minlength=num_basis) > 0
    return diffuse.clamp_min(0.0).float(), rho_s.float(), solved


def grid_neighbours(pixel_index: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Right and lower neighbours of masked pixels in the image grid.

    Args:
        pixel_index: (N,) flat indices into the H * W image of the masked pixels.
        height, width: image size.

    Returns:
        (N, 2) long: position (0..N-1) of the right and the lower neighbour, -1 where that
        neighbour is outside the image or the mask.
    """
    position = torch.full((height * width,), -1, dtype=torch.int64)
    position[pixel_index] = torch.arange(pixel_index.numel())
    row, col = pixel_index // width, pixel_index % width
    right = torch.where(col + 1 < width, position[(pixel_index + 1).clamp_max(height * width - 1)], torch.full_like(pixel_index, -1))
    down = torch.where(row + 1 < height, position[(pixel_index + width).clamp_max(height * width - 1)], torch.full_like(pixel_index, -1))
    return torch.stack([right, down], dim=1)
