"""Synthetic shapes and the ray casting that images them (OpenCV camera frame, metres, float64).

Every shape is a solid described by a signed distance function (SDF, or a lower bound of one:
``sdf(p) <= distance(p, surface)`` outside, negative inside), which is enough to sphere-trace camera
rays and shadow rays. The sphere and the ellipsoid also intersect camera rays analytically, so their
images are exact. Normals are the normalised gradient of the SDF (analytic where written out,
autograd otherwise), pointing out of the solid.

Shapes sit about ``distance`` metres in front of the camera (the rig's working distance) and are
0.1-0.2 m across, so that at the reference camera (fx = 1141.8 px at 612 x 512) they fill a good part
of the image. Seeded shapes (blob bumps, relief bumps, vase profile, poses) are reproducible from the
seed.

Visibility rule used by ``cast_camera_rays``: a pixel is in the mask when its ray hits the shape,
the surface is not seen at a grazing angle (n . v >= ``GRAZING_COS``) and its normal faces the
camera in the sense of DESIGN section 2 (n_z < 0). The last two drop a thin rim of silhouette pixels
(and, on the torus, the few hole-wall pixels whose true normal leans away from the camera), which a
real capture could not measure reliably either.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from capture_sim.errors import InputError, check_array, check_seed
from capture_sim.geometry import light_geometry, pixel_rays

GRAZING_COS = 0.05
"""Smallest n . v (cosine between normal and view direction) for a pixel to count as visible."""

_TRACE_EPS = 1e-9
"""Camera rays stop when the SDF falls below this many metres."""
_TRACE_STEPS = 800
_SHADOW_OFFSET = 1e-4
"""Shadow rays start this far (metres) above the surface, along the normal, to leave it cleanly."""
_SHADOW_EPS = 1e-5
_SHADOW_STEPS = 300
_SHADOW_CHUNK_RAYS = 1 << 18


def rotation_matrix(rx_deg: float = 0.0, ry_deg: float = 0.0, rz_deg: float = 0.0) -> np.ndarray:
    """(3, 3) rotation R = Rz @ Ry @ Rx from angles in degrees about the camera's x, y, z axes.

    Columns of R are the shape's local axes expressed in the camera frame: p_cam = c + R @ q_local.
    """
    ax, ay, az = (math.radians(a) for a in (rx_deg, ry_deg, rz_deg))
    rot_x = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    rot_y = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    rot_z = np.array([[math.cos(az), -math.sin(az), 0], [math.sin(az), math.cos(az), 0], [0, 0, 1]])
    return rot_z @ rot_y @ rot_x


class Shape:
    """A solid in the camera frame, with an SDF for sphere tracing.

    Subclasses set ``name``, ``center`` (3,) metres, ``rotation`` (3, 3) local-to-camera,
    ``bound_radius`` (a sphere about ``center`` containing the solid), ``lipschitz`` (a bound on
    |grad sdf_local| outside the solid; sphere-tracing steps are divided by it), ``convex`` (no cast
    shadows possible), optionally ``box_local``, and implement ``sdf_local``.
    """

    name: str = "shape"
    convex: bool = False
    lipschitz: float = 1.0
    box_local: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    """Optional (low, high) corners of a local-frame box containing the solid: ends shadow rays early."""

    def __init__(self, center, rotation, bound_radius: float):
        self.center = torch.as_tensor(np.asarray(center, dtype=np.float64))
        self.rotation = torch.as_tensor(np.asarray(rotation, dtype=np.float64))
        self.bound_radius = float(bound_radius)

    def exit_distance(self, origins: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """(N,) distance, metres, along the rays from ``origins`` (N, 3) in unit directions ``dirs``
        (N, 3), camera frame, past which they never meet the solid again."""
        _, t_exit = _bound_interval(origins, dirs, self.center, self.bound_radius)
        if self.box_local is None:
            return t_exit
        # Slab method in the local frame: the ray leaves the box at its nearest far-side plane.
        low, high = (torch.tensor(corner, dtype=torch.float64) for corner in self.box_local)
        origins_local, dirs_local = self.to_local(origins), dirs @ self.rotation
        far_plane = torch.where(dirs_local > 0, high, low)
        parallel = dirs_local.abs() < 1e-12  # never leaves through this pair of planes
        safe = torch.where(parallel, torch.ones_like(dirs_local), dirs_local)
        t_planes = torch.where(parallel, torch.full_like(dirs_local, math.inf), (far_plane - origins_local) / safe)
        t_box = t_planes.amin(dim=-1)
        return torch.minimum(t_exit, t_box)

    def to_local(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) camera-frame points -> shape-local coordinates q = R^T (p - c)."""
        return (points - self.center) @ self.rotation

    def sdf_local(self, q: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distance bound (metres) at camera-frame points (..., 3); negative inside."""
        return self.sdf_local(self.to_local(points))

    def outward_normals(self, points: torch.Tensor) -> torch.Tensor:
        """(N, 3) unit outward normals at surface points (N, 3), camera frame (SDF gradient)."""
        with torch.enable_grad():
            p = points.detach().clone().requires_grad_(True)
            (grad,) = torch.autograd.grad(self.sdf(p).sum(), p)
        return grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-300)

    def camera_hits(self, dirs: torch.Tensor) -> torch.Tensor:
        """Distance t (N,) along unit rays (N, 3) from the camera centre to the first hit; inf = miss."""
        origins = torch.zeros_like(dirs)
        t_in, t_out = _bound_interval(origins, dirs, self.center, self.bound_radius)
        t_in = t_in.clamp_min(0.0)
        t, hit = sphere_trace(self.sdf, origins, dirs, t_in, t_out, _TRACE_EPS, _TRACE_STEPS, 1.0 / self.lipschitz)
        return torch.where(hit, t, torch.full_like(t, math.inf))

    def describe(self) -> dict:
        """JSON-ready description: name, pose and the shape's own parameters."""
        return {
            "name": self.name,
            "center_m": [float(v) for v in self.center],
            "rotation": [[float(v) for v in row] for row in self.rotation],
            **self.parameters(),
        }

    def parameters(self) -> dict:
        return {}


@dataclass(frozen=True, eq=False)
class SurfaceHits:
    """What the camera sees of a shape, per pixel (camera frame, metres, float64).

    Attributes:
        mask: (H, W) bool, True where a visible surface point was found.
        depth: (H, W) z-depth in metres; 0 outside the mask.
        points: (H, W, 3) surface points; 0 outside the mask.
        normals: (H, W, 3) unit normals facing the camera (n_z < 0, n . v > 0); 0 outside the mask.
    """

    mask: torch.Tensor
    depth: torch.Tensor
    points: torch.Tensor
    normals: torch.Tensor


# --------------------------------------------------------------------------------------------
# Sphere tracing
# --------------------------------------------------------------------------------------------


def _bound_interval(origins, dirs, center, radius):
    """Entry and exit distances (N,) of unit rays through a bounding sphere; (inf, -inf) on a miss."""
    offset = origins - center
    b = (offset * dirs).sum(-1)
    c = (offset * offset).sum(-1) - radius * radius
    disc = b * b - c
    root = disc.clamp_min(0.0).sqrt()
    miss = disc < 0
    t_in = torch.where(miss, torch.full_like(b, math.inf), -b - root)
    t_out = torch.where(miss, torch.full_like(b, -math.inf), -b + root)
    return t_in, t_out


def sphere_trace(sdf, origins, dirs, t_start, t_end, eps: float, max_steps: int, step_scale: float = 1.0):
    """March unit rays through an SDF bound until it falls below ``eps`` or t passes ``t_end``.

    Args:
        sdf: callable (M, 3) -> (M,) signed distance bound, metres.
        origins, dirs: (N, 3) ray origins and unit directions.
        t_start, t_end: (N,) search interval along each ray.
        eps: hit threshold in metres.
        max_steps: rays still marching after this many steps count as misses.
        step_scale: fraction of the SDF value stepped (1 / Lipschitz bound of a non-exact SDF).

    Returns:
        t: (N,) distance reached; hit: (N,) bool.
    """
    t = t_start.clone()
    hit = torch.zeros(t.shape, dtype=torch.bool)
    active = torch.nonzero(t_start < t_end).squeeze(-1)
    with torch.no_grad():
        for _ in range(max_steps):
            if active.numel() == 0:
                break
            t_active = t[active]
            distance = sdf(origins[active] + t_active[:, None] * dirs[active])
            landed = distance < eps
            hit[active[landed]] = True
            t_next = t_active + step_scale * distance
            t[active] = torch.where(landed, t_active, t_next)
            active = active[~landed & (t_next <= t_end[active])]
    return t, hit


def shadow_visibility(shape: Shape, points: torch.Tensor, normals: torch.Tensor, lights: torch.Tensor) -> torch.Tensor:
    """Cast-shadow visibility of every light from every surface point (hard shadows).

    A shadow ray leaves ``points + 1e-4 m * normals`` towards each light and is sphere-traced
    against the shape's SDF until it reaches the light or leaves the shape's bounds.
    Only lights above the tangent plane (n . l > 0) are traced; the others are shaded out by the
    clamped cosine anyway and get visibility 1. Convex shapes cannot shadow themselves: all ones.

    Args:
        shape: the shape the points lie on.
        points: (N, 3) surface points, metres, camera frame.
        normals: (N, 3) unit outward normals.
        lights: (K, 3) light positions, metres, camera frame.

    Returns:
        (N, K) float64 visibility in {0, 1} (1 = the light reaches the point).
    """
    points, normals, lights = (x.to(torch.float64) for x in (points, normals, lights))
    visibility = torch.ones(points.shape[0], lights.shape[0], dtype=torch.float64)
    if shape.convex or points.shape[0] == 0:
        return visibility
    origins = points + _SHADOW_OFFSET * normals
    dirs, distance = light_geometry(origins, lights, eps=0.0)  # (N, K, 3), (N, K)
    facing = (normals[:, None, :] * dirs).sum(-1) > 0
    pixel_idx, light_idx = torch.nonzero(facing, as_tuple=True)
    for start in range(0, pixel_idx.numel(), _SHADOW_CHUNK_RAYS):
        rows = pixel_idx[start:start + _SHADOW_CHUNK_RAYS]
        cols = light_idx[start:start + _SHADOW_CHUNK_RAYS]
        ray_origins, ray_dirs = origins[rows], dirs[rows, cols]
        t_end = torch.minimum(distance[rows, cols], shape.exit_distance(ray_origins, ray_dirs))
        _, blocked = sphere_trace(
            shape.sdf, ray_origins, ray_dirs, torch.zeros_like(t_end), t_end,
            _SHADOW_EPS, _SHADOW_STEPS, 1.0 / shape.lipschitz,
        )
        visibility[rows[blocked], cols[blocked]] = 0.0
    return visibility


def cast_camera_rays(shape: Shape, K_cam, height: int, width: int) -> SurfaceHits:
    """Ray-cast a shape from the camera centre through every pixel centre.

    Args:
        shape: a shape from ``make_shape``.
        K_cam: (3, 3) intrinsics for an image of ``height`` x ``width`` pixels.
        height, width: image size in pixels.

    Returns:
        ``SurfaceHits`` with float64 depth (H, W), points (H, W, 3) and normals (H, W, 3) in the
        OpenCV camera frame, metres; the mask follows the visibility rule of this module.
    """
    check_array("K_cam", np.asarray(K_cam, dtype=np.float64), (3, 3))
    if height <= 0 or width <= 0:
        raise InputError(f"image size must be positive, got {height} x {width}")
    rays = pixel_rays(K_cam, height, width, dtype=torch.float64).reshape(-1, 3)
    dirs = rays / rays.norm(dim=-1, keepdim=True)
    t = shape.camera_hits(dirs)
    hit = torch.isfinite(t)
    points = torch.zeros_like(dirs)
    normals = torch.zeros_like(dirs)
    points[hit] = t[hit, None] * dirs[hit]
    normals[hit] = shape.outward_normals(points[hit])
    view_cos = -(normals * dirs).sum(-1)
    mask = hit & (view_cos >= GRAZING_COS) & (normals[:, 2] < 0)
    points[~mask] = 0.0
    normals[~mask] = 0.0
    return SurfaceHits(
        mask=mask.reshape(height, width),
        depth=points[:, 2].reshape(height, width).clone(),
        points=points.reshape(height, width, 3),
        normals=normals.reshape(height, width, 3),
    )


# --------------------------------------------------------------------------------------------
# Shapes
# --------------------------------------------------------------------------------------------


class Sphere(Shape):
    """Sphere of ``radius`` about ``center``; camera rays and normals are analytic."""

    name = "sphere"
    convex = True

    def __init__(self, center, radius: float):
        super().__init__(center, np.eye(3), radius)
        self.radius = float(radius)

    def sdf_local(self, q):
        return q.norm(dim=-1) - self.radius

    def camera_hits(self, dirs):
        # |t d - c|^2 = r^2 with |d| = 1: t = d.c - sqrt((d.c)^2 - |c|^2 + r^2), the nearer root.
        d_dot_c = dirs @ self.center
        disc = d_dot_c**2 - (self.center @ self.center) + self.radius**2
        t = d_dot_c - disc.clamp_min(0.0).sqrt()
        return torch.where((disc >= 0) & (t > 0), t, torch.full_like(t, math.inf))

    def outward_normals(self, points):
        offset = points - self.center
        return offset / offset.norm(dim=-1, keepdim=True)

    def parameters(self):
        return {"radius_m": self.radius}


class Ellipsoid(Shape):
    """Ellipsoid with semi-axes ``axes`` along its local x, y, z; analytic camera rays and normals."""

    name = "ellipsoid"
    convex = True

    def __init__(self, center, rotation, axes):
        self.axes = torch.as_tensor(np.asarray(axes, dtype=np.float64))
        super().__init__(center, rotation, float(self.axes.max()))

    def sdf_local(self, q):
        # (|q / a| - 1) * min(a) is 1-Lipschitz and zero on the surface: a valid SDF bound.
        return ((q / self.axes).norm(dim=-1) - 1.0) * self.axes.min()

    def camera_hits(self, dirs):
        # In coordinates scaled by 1/a the ellipsoid is the unit sphere: solve |o' + t d'|^2 = 1.
        origin = self.to_local(torch.zeros(3, dtype=torch.float64)) / self.axes
        dirs_scaled = (dirs @ self.rotation) / self.axes
        a = (dirs_scaled * dirs_scaled).sum(-1)
        b = (dirs_scaled * origin).sum(-1)
        c = origin @ origin - 1.0
        disc = b * b - a * c
        t = (-b - disc.clamp_min(0.0).sqrt()) / a
        return torch.where((disc >= 0) & (t > 0), t, torch.full_like(t, math.inf))

    def outward_normals(self, points):
        gradient = (self.to_local(points) / self.axes**2) @ self.rotation.T
        return gradient / gradient.norm(dim=-1, keepdim=True)

    def parameters(self):
        return {"semi_axes_m": [float(v) for v in self.axes]}


class Capsule(Shape):
    """Capsule: points within ``radius`` of the local-x segment of half-length ``half_length``."""

    name = "capsule"
    convex = True

    def __init__(self, center, rotation, half_length: float, radius: float):
        super().__init__(center, rotation, half_length + radius)
        self.half_length, self.radius = float(half_length), float(radius)

    def sdf_local(self, q):
        along = q[..., 0].clamp(-self.half_length, self.half_length)
        offset = q - torch.stack([along, torch.zeros_like(along), torch.zeros_like(along)], dim=-1)
        return offset.norm(dim=-1) - self.radius

    def parameters(self):
        return {"half_length_m": self.half_length, "radius_m": self.radius}


class Blob(Shape):
    """Sphere with smooth low-frequency bumps: radius r0 * (1 + sum_i a_i exp(kappa_i (u_i . q^ - 1))).

    Each bump is a spherical Gaussian lobe about direction u_i; the SDF bound is |q| - r(q^) divided
    by its Lipschitz bound.
    """

    name = "blob"

    def __init__(self, center, radius: float, lobe_dirs, lobe_amplitudes, lobe_sharpness):
        self.radius = float(radius)
        self.lobe_dirs = torch.as_tensor(np.asarray(lobe_dirs, dtype=np.float64))
        self.lobe_amplitudes = torch.as_tensor(np.asarray(lobe_amplitudes, dtype=np.float64))
        self.lobe_sharpness = torch.as_tensor(np.asarray(lobe_sharpness, dtype=np.float64))
        super().__init__(center, np.eye(3), self.radius * (1.0 + float(self.lobe_amplitudes.clamp_min(0.0).sum())))
        # Outside the solid |q| >= r0 rho(q^), so |grad sdf|^2 <= 1 + (|grad_S rho| / rho)^2: sample
        # that ratio over a dense Fibonacci sphere and keep a 10% margin for the gaps between samples.
        index = torch.arange(4000, dtype=torch.float64) + 0.5
        polar = torch.acos(1.0 - 2.0 * index / 4000)
        azimuth = math.pi * (1.0 + math.sqrt(5.0)) * index
        unit = torch.stack([polar.sin() * azimuth.cos(), polar.sin() * azimuth.sin(), polar.cos()], dim=-1)
        unit.requires_grad_(True)
        rho = self.relative_radius(unit)
        (grad,) = torch.autograd.grad(rho.sum(), unit)
        unit, rho = unit.detach(), rho.detach()
        tangential = grad - (grad * unit).sum(-1, keepdim=True) * unit
        ratio = float((tangential.norm(dim=-1) / rho).max())
        self.lipschitz = math.sqrt(1.0 + (1.1 * ratio) ** 2)

    def relative_radius(self, unit: torch.Tensor) -> torch.Tensor:
        """rho(u) = 1 + sum_i a_i exp(kappa_i (u_i . u - 1)) for unit directions (..., 3)."""
        lobes = torch.exp(self.lobe_sharpness * (unit @ self.lobe_dirs.T - 1.0))
        return 1.0 + lobes @ self.lobe_amplitudes

    def sdf_local(self, q):
        length = q.norm(dim=-1)
        unit = q / length.clamp_min(1e-12)[..., None]
        return length - self.radius * self.relative_radius(unit)

    def parameters(self):
        return {
            "radius_m": self.radius,
            "lobe_dirs": self.lobe_dirs.tolist(),
            "lobe_amplitudes": self.lobe_amplitudes.tolist(),
            "lobe_sharpness": self.lobe_sharpness.tolist(),
        }


class Torus(Shape):
    """Torus about the local z axis: tube radius ``minor`` around a circle of radius ``major``."""

    name = "torus"

    def __init__(self, center, rotation, major: float, minor: float):
        super().__init__(center, rotation, major + minor)
        self.major, self.minor = float(major), float(minor)
        reach = self.major + self.minor
        self.box_local = ((-reach, -reach, -self.minor), (reach, reach, self.minor))

    def sdf_local(self, q):
        ring = q[..., :2].norm(dim=-1) - self.major
        return torch.stack([ring, q[..., 2]], dim=-1).norm(dim=-1) - self.minor

    def parameters(self):
        return {"major_radius_m": self.major, "minor_radius_m": self.minor}


class Bowl(Shape):
    """Hemispherical shell opening towards the camera, seen from inside (concave).

    A shell of mid radius ``radius`` and ``thickness`` about ``center``, keeping the cap within
    ``rim_deg`` of the local +z pole (which points away from the camera). The rim angle plus the
    tilt stays below 90 degrees so the whole inside faces the camera (n_z < 0).
    """

    name = "bowl"

    def __init__(self, center, rotation, radius: float, thickness: float, rim_deg: float):
        super().__init__(center, rotation, radius + thickness)
        self.radius, self.thickness, self.rim_deg = float(radius), float(thickness), float(rim_deg)
        self.cut_z = self.radius * math.cos(math.radians(self.rim_deg))
        outer = self.radius + 0.5 * self.thickness
        self.box_local = ((-outer, -outer, self.cut_z), (outer, outer, outer))

    def sdf_local(self, q):
        shell = (q.norm(dim=-1) - self.radius).abs() - 0.5 * self.thickness
        return torch.maximum(shell, self.cut_z - q[..., 2])

    def parameters(self):
        return {"radius_m": self.radius, "thickness_m": self.thickness, "rim_deg": self.rim_deg}


class Relief(Shape):
    """A tile facing the camera whose front face carries smooth Gaussian height bumps.

    Front surface z = z0 - h(x, y) in local coordinates (bumps come towards the camera),
    h = sum_i A_i exp(-|xy - mu_i|^2 / (2 sigma_i^2)), over |x| <= half_width, |y| <= half_height;
    the tile is ``thickness`` deep behind z0. The SDF bound divides (z - z0 + h) by
    sqrt(1 + max |grad h|^2).
    """

    name = "relief"

    def __init__(self, center, half_width, half_height, thickness, bump_centers, bump_heights, bump_widths):
        self.half_width, self.half_height, self.thickness = float(half_width), float(half_height), float(thickness)
        self.bump_centers = torch.as_tensor(np.asarray(bump_centers, dtype=np.float64))
        self.bump_heights = torch.as_tensor(np.asarray(bump_heights, dtype=np.float64))
        self.bump_widths = torch.as_tensor(np.asarray(bump_widths, dtype=np.float64))
        reach = float(self.bump_heights.abs().sum()) + self.thickness
        super().__init__(center, np.eye(3), math.sqrt(half_width**2 + half_height**2 + reach**2))
        # Steepest slope of h sampled on a 1 mm grid over the tile (bumps are >= 10 mm wide), with a
        # 10% margin for the gaps between samples.
        xs = torch.linspace(-self.half_width, self.half_width, int(1000 * self.half_width) + 1, dtype=torch.float64)
        ys = torch.linspace(-self.half_height, self.half_height, int(1000 * self.half_height) + 1, dtype=torch.float64)
        grid = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1).reshape(-1, 2)
        self.lipschitz = math.sqrt(1.0 + (1.1 * float(self.height_gradient(grid).norm(dim=-1).max())) ** 2)
        rise = float(self.bump_heights.clamp_min(0.0).sum())
        self.box_local = ((-self.half_width, -self.half_height, -rise),
                          (self.half_width, self.half_height, self.thickness))

    def height(self, xy: torch.Tensor) -> torch.Tensor:
        """Bump height h (metres, towards the camera) at local (..., 2) positions."""
        sq = ((xy[..., None, :] - self.bump_centers) ** 2).sum(-1)
        return torch.exp(-sq / (2.0 * self.bump_widths**2)) @ self.bump_heights

    def height_gradient(self, xy: torch.Tensor) -> torch.Tensor:
        """(..., 2) gradient of h at local (..., 2) positions: sum_i -A_i g_i (xy - mu_i) / sigma_i^2."""
        offset = xy[..., None, :] - self.bump_centers  # (..., B, 2)
        bumps = torch.exp(-(offset**2).sum(-1) / (2.0 * self.bump_widths**2)) * self.bump_heights
        return -((bumps / self.bump_widths**2)[..., None] * offset).sum(-2)

    def sdf_local(self, q):
        front = -(q[..., 2] + self.height(q[..., :2])) / self.lipschitz
        sides = torch.maximum(q[..., 0].abs() - self.half_width, q[..., 1].abs() - self.half_height)
        back = q[..., 2] - self.thickness
        return torch.maximum(torch.maximum(front, sides), back)

    def parameters(self):
        return {
            "half_size_m": [self.half_width, self.half_height],
            "thickness_m": self.thickness,
            "bump_centers_m": self.bump_centers.tolist(),
            "bump_heights_m": self.bump_heights.tolist(),
            "bump_widths_m": self.bump_widths.tolist(),
        }


class Vase(Shape):
    """Solid of revolution about the local y axis with a smooth radius profile and flat caps.

    Radius r(s) = base + belly * exp(-((s - s_b) / 0.5)^2) + lip * exp(-((s + 1) / 0.25)^2),
    s = y / half_height in [-1, 1] (s = -1 is the top, which the tilt turns towards the camera).
    """

    name = "vase"

    def __init__(self, center, rotation, half_height, base, belly, belly_at, lip):
        self.half_height, self.base, self.belly, self.belly_at, self.lip = (
            float(half_height), float(base), float(belly), float(belly_at), float(lip))
        samples = torch.linspace(-1.0, 1.0, 2001, dtype=torch.float64) * self.half_height
        samples.requires_grad_(True)
        (slope,) = torch.autograd.grad(self.radius_at(samples).sum(), samples)
        self.max_radius = float(self.radius_at(samples.detach()).max())
        super().__init__(center, rotation, math.hypot(self.half_height, self.max_radius))
        self.box_local = ((-self.max_radius, -self.half_height, -self.max_radius),
                          (self.max_radius, self.half_height, self.max_radius))
        # 5% margin over the sampled slope covers the slope between samples.
        self.lipschitz = math.sqrt(1.0 + (1.05 * float(slope.abs().max())) ** 2)

    def radius_at(self, y: torch.Tensor) -> torch.Tensor:
        """Radius (metres) of the vase's cross-section at heights ``y`` (any shape, metres, local frame)."""
        s = y / self.half_height
        return (self.base + self.belly * torch.exp(-(((s - self.belly_at) / 0.5) ** 2))
                + self.lip * torch.exp(-(((s + 1.0) / 0.25) ** 2)))

    def sdf_local(self, q):
        radial = torch.stack([q[..., 0], q[..., 2]], dim=-1).norm(dim=-1)
        side = (radial - self.radius_at(q[..., 1])) / self.lipschitz
        return torch.maximum(side, q[..., 1].abs() - self.half_height)

    def parameters(self):
        return {"half_height_m": self.half_height, "base_m": self.base, "belly_m": self.belly,
                "belly_at": self.belly_at, "lip_m": self.lip}


class Cylinder(Shape):
    """Capped cylinder about the local y axis (exact SDF)."""

    name = "cylinder"
    convex = True

    def __init__(self, center, rotation, radius: float, half_height: float):
        super().__init__(center, rotation, math.hypot(radius, half_height))
        self.radius, self.half_height = float(radius), float(half_height)

    def sdf_local(self, q):
        radial = torch.stack([q[..., 0], q[..., 2]], dim=-1).norm(dim=-1) - self.radius
        axial = q[..., 1].abs() - self.half_height
        outside = torch.stack([radial.clamp_min(0.0), axial.clamp_min(0.0)], dim=-1).norm(dim=-1)
        return outside + torch.maximum(radial, axial).clamp_max(0.0)

    def parameters(self):
        return {"radius_m": self.radius, "half_height_m": self.half_height}


SHAPES: tuple[str, ...] = ("sphere", "ellipsoid", "capsule", "blob", "torus", "bowl", "relief", "vase", "cylinder")


SHAPE_DISTANCES_M = (0.2, 5.0)
"""Range of the distances (metres) at which shapes are built: the sizes and poses are made for it."""


def make_shape(name: str, seed: int = 0, distance: float = 0.5) -> Shape:
    """Build one of ``SHAPES`` about ``distance`` metres in front of the camera.

    The sphere is fixed (radius 0.07 m on the optical axis); the other shapes draw their pose and
    details (bumps, profile) from ``seed``.

    Args:
        name: one of ``SHAPES``.
        seed: non-negative integer; same seed, same shape.
        distance: metres from the camera centre to the shape's centre along z.

    Returns:
        The shape (camera frame, metres).
    """
    if name not in SHAPES:
        raise InputError(f"unknown shape {name!r}; choose from {', '.join(SHAPES)}")
    check_seed("seed", seed)
    if not SHAPE_DISTANCES_M[0] <= distance <= SHAPE_DISTANCES_M[1]:
        raise InputError(f"shape distance must be {SHAPE_DISTANCES_M[0]:g}..{SHAPE_DISTANCES_M[1]:g} m, got {distance}")
    rng = np.random.default_rng([int(seed), 11])
    center = np.array([0.0, 0.0, distance])
    if name == "sphere":
        return Sphere(center, 0.07)
    if name == "ellipsoid":
        rotation = rotation_matrix(rng.uniform(-30, 30), rng.uniform(-30, 30), rng.uniform(0, 180))
        return Ellipsoid(center, rotation, rng.uniform([0.075, 0.05, 0.045], [0.09, 0.06, 0.055]))
    if name == "capsule":
        rotation = rotation_matrix(0.0, rng.uniform(-35, 35), rng.uniform(-50, 50))
        return Capsule(center, rotation, rng.uniform(0.04, 0.055), rng.uniform(0.03, 0.038))
    if name == "blob":
        count = 7
        lobe_dirs = rng.normal(size=(count, 3))
        lobe_dirs /= np.linalg.norm(lobe_dirs, axis=1, keepdims=True)
        amplitudes = rng.uniform(0.08, 0.16, count) * rng.choice([-1.0, 1.0], count, p=[0.3, 0.7])
        return Blob(center, 0.055, lobe_dirs, amplitudes, rng.uniform(2.5, 5.0, count))
    if name == "torus":
        rotation = rotation_matrix(rng.uniform(35, 50), rng.uniform(-20, 20), 0.0)
        return Torus(center, rotation, 0.058, rng.uniform(0.02, 0.026))
    if name == "bowl":
        # Rim angle + tilt < 90 degrees keeps every inner normal facing the camera.
        rotation = rotation_matrix(rng.uniform(-15, 15), rng.uniform(-10, 10), 0.0)
        return Bowl(center - np.array([0.0, 0.0, 0.02]), rotation, 0.08, 0.006, 62.0)
    if name == "relief":
        count = 8
        bump_centers = rng.uniform([-0.075, -0.06], [0.075, 0.06], size=(count, 2))
        heights = rng.uniform(0.004, 0.014, count) * rng.choice([-1.0, 1.0], count, p=[0.25, 0.75])
        return Relief(center, 0.1, 0.08, 0.02, bump_centers, heights, rng.uniform(0.014, 0.03, count))
    if name == "vase":
        rotation = rotation_matrix(rng.uniform(15, 25), 0.0, rng.uniform(-10, 10))
        return Vase(center, rotation, 0.085, 0.024, rng.uniform(0.016, 0.024), rng.uniform(0.1, 0.4), 0.016)
    rotation = rotation_matrix(rng.uniform(20, 35), 0.0, rng.uniform(-25, 25))
    return Cylinder(center, rotation, rng.uniform(0.04, 0.05), rng.uniform(0.05, 0.065))
