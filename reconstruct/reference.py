"""Slow, readable per-pixel versions of the photometric-stereo solvers, for tests only.

Plain numpy float64 loops over pixels, lights and patterns, following the same algorithm as the
fast paths (``photometric_stereo``, ``woodham``) without restarts: start from the view direction,
fit the current attached-shadow mask to convergence, move to the fitted normal's own mask when
that lowers the true residual (halving the step otherwise), stop when the mask reproduces itself.
Only used on a few dozen pixels to check the fast paths.
"""
from __future__ import annotations

import numpy as np


def _pixel_lighting(point, lights, falloff):
    """Unit directions (K, 3) to the lights and falloff weights f_k (K,) of one point."""
    directions, weights = [], []
    for light in lights:
        offset = light - point
        distance = max(np.linalg.norm(offset), 1e-3)
        directions.append(offset / distance)
        weights.append(falloff(distance))
    return np.array(directions), np.array(weights)


def _lighting_vectors(directions, weights, emission, normal):
    """b[m, c] = sum_k E[m, k, c] f_k s_k l_k for the mask s of ``normal`` -> (M, 3, 3)."""
    num_patterns = emission.shape[0]
    vectors = np.zeros((num_patterns, 3, 3))
    for m in range(num_patterns):
        for k in range(len(weights)):
            if directions[k] @ normal > 0:  # attached shadow: lights behind the tangent plane add nothing
                for c in range(3):
                    vectors[m, c] += emission[m, k, c] * weights[k] * directions[k]
    return vectors


def _moments(vectors, captures, saturation_threshold):
    """Per-channel B_c, r_c and sum I^2 of one pixel, in normalised units (as the fast path)."""
    lighting_scale = max(np.sqrt(np.mean(vectors**2)), 1e-150)
    capture_scale = max(np.abs(captures).max(), 1e-150)
    b, values = vectors / lighting_scale, captures / capture_scale
    moment, projection, energy = np.zeros((3, 3, 3)), np.zeros((3, 3)), np.zeros(3)
    for m in range(len(values)):
        for c in range(3):
            if captures[m, c] >= saturation_threshold:
                continue
            moment[c] += np.outer(b[m, c], b[m, c])
            projection[c] += values[m, c] * b[m, c]
            energy[c] += values[m, c] ** 2
    return moment, projection, energy, capture_scale / lighting_scale


def _albedo(normal, moment, projection, damping):
    albedo = np.zeros(3)
    for c in range(3):
        denominator = normal @ moment[c] @ normal + damping * np.trace(moment[c]) / 3 + 1e-12
        albedo[c] = max(0.0, normal @ projection[c] / denominator)
    return albedo


def _residual(normal, moment, projection, energy, damping):
    total = 0.0
    for c in range(3):
        denominator = normal @ moment[c] @ normal + damping * np.trace(moment[c]) / 3 + 1e-12
        total += energy[c] - max(0.0, normal @ projection[c]) ** 2 / denominator
    return total


def _unit(vector):
    length = np.linalg.norm(vector)
    return vector / length if length > 0 else vector


def _ps_fit(albedo, moment, projection, damping, tolerance, max_alternations):
    """Alternate normal and albedo least squares for a fixed mask until the normal settles."""
    normal = None
    for _ in range(max_alternations):
        system = sum(albedo[c] ** 2 * moment[c] for c in range(3))
        rhs = sum(albedo[c] * projection[c] for c in range(3))
        scale = max(np.trace(system) / 3, 1e-150)
        new_normal = _unit(np.linalg.solve(system / scale + damping * np.eye(3), rhs / scale))
        albedo = _albedo(new_normal, moment, projection, damping)
        if normal is not None and np.linalg.norm(new_normal - normal) <= tolerance:
            return albedo, new_normal
        normal = new_normal
    return albedo, normal


def _woodham_fit(moment, projection, damping):
    """Per-channel least squares g_c, normal along sum_c g_c."""
    total = np.zeros(3)
    for c in range(3):
        scale = max(np.trace(moment[c]) / 3, 1e-150)
        total += np.linalg.solve(moment[c] / scale + damping * np.eye(3), projection[c] / scale)
    normal = _unit(total)
    return _albedo(normal, moment, projection, damping), normal


def _search(point, fit, moments_of, damping, max_iterations, line_search_steps):
    """Damped Gauss-Newton over shadow masks for one pixel (see ``reconstruct.shadow_search``).

    ``moments_of(normal)`` returns (moment, projection, energy, albedo scale, mask) of the normal's
    own shadow mask; ``fit(albedo or None, moment, projection)`` returns (albedo, normal).
    """
    normal = -point / np.linalg.norm(point)
    moment, projection, energy, to_albedo, mask = moments_of(normal)
    objective = _residual(normal, moment, projection, energy, damping)
    albedo = None
    for _ in range(max_iterations):
        albedo, target = fit(albedo, moment, projection)
        if np.array_equal(moments_of(target)[4], mask):
            return target, albedo * to_albedo
        for attempt in range(line_search_steps + 1):
            trial = target if attempt == 0 else _unit(normal + 0.5**attempt * (target - normal))
            trial_moments = moments_of(trial)
            trial_objective = _residual(trial, *trial_moments[:3], damping)
            if trial_objective < objective:
                normal, objective = trial, trial_objective
                moment, projection, energy, to_albedo, mask = trial_moments
                albedo = _albedo(normal, moment, projection, damping)
                break
        else:
            break
    return normal, _albedo(normal, moment, projection, damping) * to_albedo


def ps_reference(captures, emission, points, lights, falloff, damping=1e-9, tolerance_deg=1e-9, max_alternations=500,
                 max_shadow_iterations=50, line_search_steps=4, saturation_threshold=0.999):
    """Per-pixel analytic multiplexed photometric stereo with attached shadows (no restarts).

    Args:
        captures: (M, N, 3) captures.
        emission: (M, K, 3) effective emission.
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions.
        falloff: callable distance (float, metres) -> falloff factor.

    Returns:
        normals (N, 3) and albedo (N, 3) (rho / pi), numpy float64.
    """
    captures, emission = np.asarray(captures, np.float64), np.asarray(emission, np.float64)
    points, lights = np.asarray(points, np.float64), np.asarray(lights, np.float64)
    tolerance = np.radians(tolerance_deg)
    normals, albedos = np.zeros((len(points), 3)), np.zeros((len(points), 3))
    for n, point in enumerate(points):
        directions, weights = _pixel_lighting(point, lights, falloff)
        pixel_captures = captures[:, n]
        initial_albedo = np.maximum(pixel_captures.max(axis=0) / max(np.abs(pixel_captures).max(), 1e-150), 0)

        def moments_of(normal):
            vectors = _lighting_vectors(directions, weights, emission, normal)
            mask = directions @ normal > 0
            return (*_moments(vectors, pixel_captures, saturation_threshold), mask)

        def fit(albedo, moment, projection):
            start = initial_albedo if albedo is None else albedo
            return _ps_fit(start, moment, projection, damping, tolerance, max_alternations)

        normals[n], albedos[n] = _search(point, fit, moments_of, damping, max_shadow_iterations, line_search_steps)
    return normals, albedos


def woodham_olat_reference(captures, light_emission, points, lights, falloff, damping=1e-9, shadow_threshold=0.01,
                           max_shadow_iterations=50, line_search_steps=4, saturation_threshold=0.999):
    """Per-pixel Woodham least squares on an OLAT stack (capture k lit by light k alone).

    Args:
        captures: (K, N, 3) OLAT captures.
        light_emission: (K, 3) effective emission of light k in capture k.
        points: (N, 3) surface points; lights: (K, 3) positions; falloff: distance -> factor.

    Returns:
        normals (N, 3) and albedo (N, 3), numpy float64.
    """
    captures, light_emission = np.asarray(captures, np.float64), np.asarray(light_emission, np.float64)
    points, lights = np.asarray(points, np.float64), np.asarray(lights, np.float64)
    normals, albedos = np.zeros((len(points), 3)), np.zeros((len(points), 3))
    for n, point in enumerate(points):
        directions, weights = _pixel_lighting(point, lights, falloff)
        pixel_captures = captures[:, n]
        brightest = pixel_captures.max(axis=0)
        capture_scale = max(np.abs(pixel_captures).max(), 1e-150)

        def moments_of(normal):
            raw_moment, raw_projection, energy = np.zeros((3, 3, 3)), np.zeros((3, 3)), np.zeros(3)
            mask = directions @ normal > 0
            for k in range(len(lights)):
                for c in range(3):
                    value = pixel_captures[k, c]
                    if not shadow_threshold * brightest[c] < value < saturation_threshold:
                        continue
                    # A shadowed light predicts zero: its equation still counts in the residual.
                    energy[c] += (value / capture_scale) ** 2
                    if mask[k]:
                        b = light_emission[k, c] * weights[k] * directions[k]
                        raw_moment[c] += np.outer(b, b)
                        raw_projection[c] += value * b
            lighting_scale = max(np.sqrt(sum(np.trace(raw_moment[c]) for c in range(3)) / 9), 1e-150)
            moment = raw_moment / lighting_scale**2
            projection = raw_projection / (lighting_scale * capture_scale)
            return moment, projection, energy, capture_scale / lighting_scale, mask

        def fit(albedo, moment, projection):
            return _woodham_fit(moment, projection, damping)

        normals[n], albedos[n] = _search(point, fit, moments_of, damping, max_shadow_iterations, line_search_steps)
    return normals, albedos
