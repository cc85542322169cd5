"""Independent test scenes for the reconstruction tests: an analytic Lambertian sphere.

Built here from first principles (ray-sphere intersection, Lambert's law with 1/d^2 falloff) so
that the solvers are checked against geometry they did not compute themselves.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from capture_sim.geometry import pixel_rays
from capture_sim.rig import load_rig

PATTERN_DIR = Path(__file__).resolve().parent.parent / "patterns" / "data" / "ddps"


@dataclass
class SphereScene:
    """A Lambertian sphere seen by the reference rig at a small resolution (float64 tensors)."""

    points: torch.Tensor  # (H, W, 3) metres, camera frame (plane at the sphere's centre off the sphere)
    normal: torch.Tensor  # (H, W, 3) true unit normals ((0, 0, -1) off the sphere)
    mask: torch.Tensor  # (H, W) bool, pixels on the sphere
    albedo: torch.Tensor  # (H, W, 3) rho / pi, the albedo the solvers estimate
    olat: torch.Tensor  # (K, H, W, 3) O[k] = rho / pi * max(0, n . l_k) / d_k^2
    lights: torch.Tensor  # (K, 3)
    backlight: torch.Tensor  # (K,)
    gamma: float
    scale: float


def sphere_scene(height: int = 40, width: int = 48, radius: float = 0.08, distance: float = 0.5) -> SphereScene:
    rig = load_rig().with_resolution(height, width)
    rays = pixel_rays(rig.camera.matrix(), height, width, dtype=torch.float64)
    centre = torch.tensor([0.0, 0.0, distance], dtype=torch.float64)
    # |t r - C|^2 = R^2  ->  t = (r.C - sqrt((r.C)^2 - |r|^2 (|C|^2 - R^2))) / |r|^2
    ray_sq = (rays * rays).sum(-1)
    along = rays @ centre
    discriminant = along**2 - ray_sq * (centre @ centre - radius**2)
    mask = discriminant > 0
    depth = torch.where(mask, (along - discriminant.clamp_min(0).sqrt()) / ray_sq, torch.full_like(along, distance))
    points = depth[..., None] * rays
    normal = torch.where(mask[..., None], (points - centre) / radius, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    u = torch.linspace(0, 1, width, dtype=torch.float64)[None, :].expand(height, width)
    reflectance = torch.stack([0.7 + 0.2 * u, 0.5 - 0.2 * u, 0.3 + 0.1 * u], dim=-1)
    albedo = torch.where(mask[..., None], reflectance / np.pi, torch.zeros(()))
    lights = rig.lights(torch.float64)
    offset = lights[:, None, None, :] - points[None]
    dist = offset.norm(dim=-1)
    cosine = ((offset / dist[..., None]) * normal[None]).sum(-1).clamp_min(0)
    olat = albedo[None] * (cosine / dist**2)[..., None]
    return SphereScene(points, normal, mask, albedo, olat, lights, rig.backlight_flat(torch.float64), rig.gamma, rig.scale)


def load_patterns(name: str) -> torch.Tensor:
    """(M, K, 3) float64 published pattern set ``name`` (file stem in patterns/data/ddps)."""
    values = np.load(PATTERN_DIR / f"{name}.npy").astype(np.float64)
    return torch.as_tensor(values.reshape(values.shape[0], -1, 3))


def pattern_names() -> list[str]:
    return sorted(path.stem for path in PATTERN_DIR.glob("*.npy"))


def emission_of(scene: SphereScene, patterns: torch.Tensor) -> torch.Tensor:
    """(M, K, 3) display emission scale * (P + B) ** gamma, without exposure."""
    return scene.scale * (patterns + scene.backlight[None, :, None]) ** scene.gamma


def capture(scene: SphereScene, emission: torch.Tensor, peak: float = 0.9) -> tuple[torch.Tensor, torch.Tensor]:
    """Noise-free unclipped captures (M, H, W, 3) and effective emission, exposure set so the max is ``peak``."""
    radiance = torch.einsum("mkc,khwc->mhwc", emission, scene.olat)
    exposure = peak / float(radiance.max())
    return radiance * exposure, emission * exposure
