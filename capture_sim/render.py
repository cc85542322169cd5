"""Shading of OLAT images from geometry and basis BRDFs (DESIGN section 3).

    O[k](x) = f(l_k, v) * max(0, n . l_k) * falloff(d_k),   f = sum_j w_j(x) f_j

Used to synthesise OLAT stacks (the baseline inverse renderer shades with its own factorised form of
the same model, ``reconstruct.basis_render``, tested against this one). Diffuse and specular parts are
returned separately (what a polarisation camera separates); their sum is the OLAT stack.
"""
from __future__ import annotations

import math

import torch

from capture_sim.brdf import check_fresnel, cook_torrance_specular
from capture_sim.errors import InputError, check_array
from capture_sim.geometry import light_geometry, view_directions
from capture_sim.rig import Falloff, checked_falloff


def render_olat(
    points: torch.Tensor,
    normals: torch.Tensor,
    lights: torch.Tensor,
    weights: torch.Tensor,
    diffuse_albedo: torch.Tensor,
    specular_albedo: torch.Tensor,
    roughness: torch.Tensor,
    falloff: Falloff = Falloff(),
    visibility: torch.Tensor | None = None,
    fresnel: str = "constant",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render the diffuse and specular OLAT images of a set of surface points.

    Args:
        points: (N, 3) surface points, metres, camera frame.
        normals: (N, 3) unit normals, camera frame (visible ones have n_z < 0).
        lights: (K, 3) superpixel positions, metres, camera frame.
        weights: (N, J) basis weights per point (on the simplex for physical mixtures).
        diffuse_albedo: (J, 3) or (N, J, 3) diffuse albedo rho_d of each basis BRDF.
        specular_albedo: (J,) or (N, J) specular albedo rho_s (0 for a Lambertian basis).
        roughness: (J,) or (N, J) perceptual GGX roughness.
        falloff: distance falloff of the superpixels.
        visibility: optional (N, K) cast-shadow visibility in [0, 1] (1 = light reaches the point).
        fresnel: ``"constant"`` or ``"schlick"`` (see ``capture_sim.brdf``).

    Returns:
        diffuse, specular: (K, N, 3) radiance per unit display intensity, in the points' dtype
        (float16 and bfloat16 inputs are rendered in float32, whose small denominators they cannot
        hold, and the result is clamped to their range).
    """
    if isinstance(points, torch.Tensor) and points.dtype in (torch.float16, torch.bfloat16):
        def wide(value):
            return value.float() if isinstance(value, torch.Tensor) and value.is_floating_point() else value

        rendered = render_olat(*(wide(value) for value in (points, normals, lights, weights, diffuse_albedo, specular_albedo, roughness)),
                               falloff, wide(visibility), fresnel)
        limit = torch.finfo(points.dtype).max
        return tuple(image.clamp(max=limit).to(points.dtype) for image in rendered)
    _check_inputs(points, normals, lights, weights, diffuse_albedo, specular_albedo, roughness, visibility, fresnel)
    light_dirs, distance = light_geometry(points, lights)  # (N, K, 3), (N, K)
    falloff_values = checked_falloff(falloff, distance).to(distance.dtype)  # DESIGN section 3: a fitted falloff can be negative or infinite
    view_dir = view_directions(points)[:, None, :]  # (N, 1, 3)
    n_dot_l = (normals[:, None, :] * light_dirs).sum(-1)
    irradiance = n_dot_l.clamp_min(0.0) * falloff_values  # (N, K)
    if visibility is not None:
        irradiance = irradiance * visibility
    rho_d = weights @ diffuse_albedo if diffuse_albedo.dim() == 2 else (weights[..., None] * diffuse_albedo).sum(1)
    diffuse = irradiance[..., None] * (rho_d / math.pi)[:, None, :]  # (N, K, 3)
    specular_albedo = specular_albedo.expand(weights.shape)
    roughness = roughness.expand(weights.shape)
    lobe = torch.zeros_like(irradiance)
    for j in range(weights.shape[1]):
        if bool((specular_albedo[:, j] == 0).all()) and not specular_albedo.requires_grad:
            continue  # a Lambertian basis has no lobe to evaluate
        lobe_j = cook_torrance_specular(normals[:, None, :], light_dirs, view_dir, roughness[:, j, None], fresnel)
        lobe = lobe + (weights[:, j] * specular_albedo[:, j])[:, None] * lobe_j
    specular = (lobe * irradiance)[..., None].expand(-1, -1, 3)
    return diffuse.permute(1, 0, 2), specular.permute(1, 0, 2)


UNIT_TOLERANCE = 1e-2
"""How far from 1 the length of a normal given to ``render_olat`` may be (float16 normals are
rounded to about 1e-3)."""


def _check_inputs(points, normals, lights, weights, diffuse_albedo, specular_albedo, roughness, visibility, fresnel) -> None:
    """``InputError`` for the shapes and ranges ``render_olat`` documents (NaN anywhere included)."""
    named = {"points": points, "normals": normals, "lights": lights, "weights": weights, "diffuse_albedo": diffuse_albedo,
             "specular_albedo": specular_albedo, "roughness": roughness, "visibility": visibility}
    for name, value in named.items():
        if value is not None and not isinstance(value, torch.Tensor):
            raise InputError(f"{name}: expected a torch tensor, got {type(value).__name__}")
        if value is not None and not value.is_floating_point():
            raise InputError(f"{name}: expected a floating-point tensor, got {value.dtype}")
    check_array("points", points, ("N", 3))
    count = points.shape[0]
    check_array("normals", normals, (count, 3))
    lengths = normals.detach().norm(dim=-1)
    if lengths.numel() and float((lengths - 1).abs().max()) > UNIT_TOLERANCE:  # a longer normal would scale the radiance
        raise InputError(f"normals: expected unit vectors, got lengths from {float(lengths.min()):g} to {float(lengths.max()):g}")
    check_array("lights", lights, ("K", 3))
    check_array("weights", weights, (count, "J"), value_range=(0.0, math.inf))
    bases = weights.shape[1]
    per_point = (count, bases)
    check_array("diffuse_albedo", diffuse_albedo, (bases, 3) if diffuse_albedo.dim() == 2 else (*per_point, 3), value_range=(0.0, math.inf))
    for name, value, value_range in (("specular_albedo", specular_albedo, (0.0, math.inf)), ("roughness", roughness, (0.0, 1.0))):
        # one value, one per basis, or one per point and basis (broadcast to weights' shape)
        check_array(name, value, ((), (bases,), per_point)[min(value.dim(), 2)], value_range=value_range)
    if visibility is not None:
        check_array("visibility", visibility, (count, lights.shape[0]), value_range=(0.0, 1.0))
    check_fresnel(fresnel)
