"""Camera rays, 3D points and per-pixel light geometry in the OpenCV camera frame (metres)."""
from __future__ import annotations

import numpy as np
import torch


def pixel_rays(K_cam, height: int, width: int, dtype=torch.float32) -> torch.Tensor:
    """Rays through pixel centres, scaled so that their z component is 1.

    Args:
        K_cam: (3, 3) intrinsics (array or tensor) for an image of ``height`` x ``width``.
        height, width: image size in pixels; pixel (v, u) has its centre at (u, v) in pixel units.

    Returns:
        (H, W, 3) rays (x/z, y/z, 1) in the camera frame; a point at depth z is ``z * ray``.
    """
    k = torch.as_tensor(np.asarray(K_cam, dtype=np.float64))
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij")
    x = (u - k[0, 2] - k[0, 1] * (v - k[1, 2]) / k[1, 1]) / k[0, 0]
    y = (v - k[1, 2]) / k[1, 1]
    return torch.stack([x, y, torch.ones_like(x)], dim=-1).to(dtype)


def points_from_depth(depth: torch.Tensor, K_cam) -> torch.Tensor:
    """3D points of a depth map.

    Args:
        depth: (H, W) z-depth in metres.
        K_cam: (3, 3) intrinsics for that resolution.

    Returns:
        (H, W, 3) points in metres, camera frame.
    """
    rays = pixel_rays(K_cam, depth.shape[0], depth.shape[1], dtype=depth.dtype)
    return depth[..., None] * rays


def light_geometry(points: torch.Tensor, lights: torch.Tensor, eps: float = 1e-9) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit directions and distances from surface points to every light.

    Args:
        points: (N, 3) surface points, metres, camera frame.
        lights: (K, 3) superpixel positions, metres, camera frame.

    Returns:
        light_dirs: (N, K, 3) unit vectors from each point towards each light.
        distance: (N, K) metres.
    """
    offset = lights[None, :, :] - points[:, None, :]
    distance = offset.norm(dim=-1).clamp_min(eps)
    return offset / distance[..., None], distance


def view_directions(points: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """(…, 3) unit vectors from points (…, 3) towards the camera centre: v = -x / |x|."""
    return -points / points.norm(dim=-1, keepdim=True).clamp_min(eps)
