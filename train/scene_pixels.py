"""Scenes prepared for simulation and reconstruction: the masked pixels of one or many scenes.

Learning samples pixels across scenes; evaluation runs whole scenes. Both need, per pixel, the light
transport column, the 3D point, the true normal and which scene it belongs to.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from capture_sim.errors import InputError
from capture_sim.rig import Rig
from capture_sim.scene import Scene, rig_for_scene
from capture_sim.simulator import LightTransport, light_transport


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


def scene_pixels(scene: Scene, rig: Rig, require_normals: bool = False) -> ScenePixels:
    """Prepare one scene; ``require_normals`` raises ``InputError`` for scenes without ground truth."""
    if require_normals and scene.normal is None:
        raise InputError(f"scene {scene.name} has no ground-truth normals, which this command needs")
    if not scene.mask.any():
        raise InputError(f"scene {scene.name} has an empty mask")
    scene_rig = rig_for_scene(rig, scene)
    transport = light_transport(scene.olat, scene.mask)
    flat_mask = torch.as_tensor(scene.mask.reshape(-1))
    points = scene.points(scene_rig.working_distance).reshape(-1, 3)[flat_mask]
    normal = None if scene.normal is None else torch.as_tensor(scene.normal, dtype=torch.float32).reshape(-1, 3)[flat_mask]
    scene_rig.falloff.check(torch.cdist(points, scene_rig.lights()))
    return ScenePixels(scene.name, scene_rig, transport, points, normal, np.asarray(scene.mask))
