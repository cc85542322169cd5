"""Scenes prepared for simulation and reconstruction: the masked pixels of one or many scenes.

Learning samples pixels across scenes; evaluation runs whole scenes. Both need, per pixel, the light
transport column, the 3D point, the true normal and which scene it belongs to.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from capture_sim.errors import DisplexWarning, InputError
from capture_sim.rig import Rig
from capture_sim.scene import Scene, rig_for_scene
from capture_sim.simulator import LightTransport, light_transport
from reconstruct.unrolled_ps import light_reach


@dataclass(frozen=True, eq=False)
class ScenePixels:
    """The masked pixels of one scene, ready for the simulator and the solvers.

    Attributes:
        name: scene name.
        rig: the rig with this scene's lights and intrinsics.
        transport: (3, K, N) light transport of the masked pixels.
        points: (N, 3) surface points, metres, camera frame (depth map, else the rig's plane).
        normal: (N, 3) true unit normals, or None when the scene has none.
        mask: (H, W) bool mask the pixels come from.
    """

    name: str
    rig: Rig
    transport: LightTransport
    points: torch.Tensor
    normal: torch.Tensor | None
    mask: np.ndarray

    @property
    def num_pixels(self) -> int:
        return self.transport.num_pixels

    def lights(self) -> torch.Tensor:
        """(K, 3) light positions of the scene, metres, camera frame."""
        return self.rig.lights()


def warn_if_black_inside_mask(scene: Scene) -> None:
    """Warn (``DisplexWarning``) if the scene's OLAT stack is zero on every masked pixel: usable but
    probably not meant (a wrong mask, a failed capture, a purely specular scene stripped of its
    specular stack), as its captures hold nothing but noise. Stops at the first lit light."""
    if not any(np.any(image[scene.mask]) for image in scene.olat):
        warnings.warn(f"{scene.label} is black inside its mask (its OLAT stack is zero there): its captures hold "
                      "nothing but noise, so its errors say nothing about the patterns", DisplexWarning, stacklevel=3)


def require_ground_truth(scene: Scene) -> None:
    """``InputError`` naming the scene and its file if it has no ground-truth normals."""
    if scene.normal is None:
        raise InputError(f"{scene.label} has no ground-truth normals, which this command needs")


def scene_pixels(scene: Scene, rig: Rig, require_normals: bool = False) -> ScenePixels:
    """Prepare one scene; ``require_normals`` raises ``InputError`` for scenes without ground truth.

    A scene black inside its mask is reported (``warn_if_black_inside_mask``).
    """
    if require_normals:
        require_ground_truth(scene)
    if not scene.mask.any():
        raise InputError(f"{scene.label} has an empty mask")
    scene_rig = rig_for_scene(rig, scene)
    warn_if_black_inside_mask(scene)
    transport = light_transport(scene.olat, scene.mask)
    flat_mask = torch.as_tensor(scene.mask.reshape(-1))
    points = scene.points(scene_rig.working_distance).reshape(-1, 3)[flat_mask]
    normal = None if scene.normal is None else torch.as_tensor(scene.normal, dtype=torch.float32).reshape(-1, 3)[flat_mask]
    try:
        scene_rig.falloff.check(torch.cdist(points, scene_rig.lights()))
    except InputError as err:
        raise InputError(f"{scene.label}: {err}") from None
    return ScenePixels(scene.name, scene_rig, transport, points, normal, np.asarray(scene.mask))


@dataclass(frozen=True, eq=False)
class ShuffledPixels:
    """A scene's pixels in one seeded random order, for sampling windows without a gather.

    The first ``window - 1`` pixels of the order are repeated at the end, so every cyclic window
    of ``window`` consecutive positions is a plain slice (a view) of the tensors below; a window
    starting at a uniformly random position holds every pixel with the same probability as a fresh
    random subset would.

    Attributes:
        scene: the scene with transport, points and normals in shuffled, wrapped order
            (num_pixels + window - 1 columns; the source scene is not kept).
        reach: (K, num_pixels + window - 1) ``light_reach`` of the shuffled points (geometry only,
            computed once instead of every step).
        window: pixels per draw, min(requested, number of pixels).
        num_pixels: N, the scene's distinct pixels (the first N columns of ``scene``).
    """

    scene: ScenePixels
    reach: torch.Tensor
    window: int
    num_pixels: int

    def every_pixel(self, limit: int | None = None) -> ScenePixels:
        """The scene's N pixels once each, in shuffled order, as views; with ``limit``, only the
        first min(N, limit) of them: a fixed uniform random sample of the scene's pixels."""
        part, scene = slice(0, self.num_pixels if limit is None else min(self.num_pixels, limit)), self.scene
        normal = None if scene.normal is None else scene.normal[part]
        return ScenePixels(scene.name, scene.rig, scene.transport.subset(part), scene.points[part], normal, scene.mask)

    def draw(self, generator: torch.Generator) -> slice:
        """A random window of ``window`` pixels, as a slice into ``scene`` and ``reach``."""
        start = int(torch.randint(self.num_pixels, (1,), generator=generator))
        return slice(start, start + self.window)


def shuffle_pixels(pixels: ScenePixels, window: int, generator: torch.Generator) -> ShuffledPixels:
    """Shuffle a scene's pixels once (order drawn from ``generator``) for windowed sampling.

    Args:
        pixels: the prepared scene; needs true normals.
        window: pixels per draw (clamped to the scene's pixel count), >= 1.
        generator: seeds the order, so the same seed gives the same windows.
    """
    if window < 1:
        raise InputError(f"window must be >= 1, got {window}")
    window = min(window, pixels.num_pixels)
    order = torch.randperm(pixels.num_pixels, generator=generator)
    order = torch.cat([order, order[: window - 1]])
    transport = pixels.transport.subset(order)
    points = pixels.points[order]
    normal = None if pixels.normal is None else pixels.normal[order]
    scene = ScenePixels(pixels.name, pixels.rig, transport, points, normal, pixels.mask)
    reach = light_reach(points, pixels.lights(), pixels.rig.falloff)
    return ShuffledPixels(scene, reach, window, pixels.num_pixels)


def fixed_pixel_subsets(scenes: list[ScenePixels], pixels_per_scene: int, seed: int, offset: int = 0) -> list:
    """Per scene: sorted (P,) indices of a fixed random subset of ``pixels_per_scene`` masked pixels
    (generator seeded by ``seed * 1000 + scene index + offset``), or None to use every pixel
    (``pixels_per_scene`` 0, or a scene no larger than it)."""
    columns = []
    for index, pixels in enumerate(scenes):
        if pixels_per_scene and pixels.num_pixels > pixels_per_scene:
            chooser = torch.Generator().manual_seed(seed * 1000 + index + offset)
            columns.append(torch.randperm(pixels.num_pixels, generator=chooser)[:pixels_per_scene].sort().values)
        else:
            columns.append(None)
    return columns
