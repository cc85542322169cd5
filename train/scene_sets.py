"""Where commands get their scenes: files and folders given by the user, or the default synthetic set."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from capture_sim.errors import InputError, is_whole_number
from capture_sim.rig import Rig, load_rig
from capture_sim.scene import Scene, load_scene, scene_paths
from capture_sim.synth import default_scene_set, default_scene_size, scene_size


def configured_scene_size(size, rig: str) -> tuple[int, int]:
    """A config's ``scene_size``: two whole numbers of at least 2 (height, width), or None for the
    default synthetic scenes' size on ``rig`` (``capture_sim.synth.default_scene_size``), resolved
    here so that every record of a run names the size its scenes have.

    Raises:
        InputError: any other value, or a rig that cannot be loaded (when ``size`` is None).
    """
    if size is None:
        if not isinstance(rig, (str, Path)):
            raise InputError(f"rig must be a preset name or a TOML file path, got {rig!r}")
        return default_scene_size(load_rig(rig))
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(is_whole_number(side, 2) for side in size)):
        raise InputError(f"scene_size must be two whole numbers of at least 2 (height, width), got {size!r}")
    return tuple(int(side) for side in size)


_CACHE_SIZE = 4
_cache: dict = {}


def _rig_key(rig: Rig) -> tuple:
    """What the synthetic scenes depend on: rigs loaded twice from one file share their scenes."""
    return (rig.name, rig.light_positions.tobytes(), rig.backlight.tobytes(), rig.camera, rig.falloff, rig.gamma, rig.scale,
            rig.working_distance)


def _default_set(rig: Rig, height: int, width: int, seed: int) -> dict:
    height, width = scene_size(rig, height, width)
    key = (_rig_key(rig), height, width, seed)
    if key not in _cache:
        if len(_cache) >= _CACHE_SIZE:
            _cache.pop(next(iter(_cache)))  # the oldest set: a few hundred MB each
        _cache[key] = default_scene_set(rig, height=height, width=width, seed=seed)
    return _cache[key]


def default_split(split: str, rig: Rig, size: tuple[int, int] | None = None, seed: int = 0) -> list[Scene]:
    """The ``"train"`` or ``"test"`` split of the default synthetic set (made once per process) at
    ``size`` (height, width; None: ``capture_sim.synth.default_scene_size``, a quarter of the rig camera's)."""
    height, width = (None, None) if size is None else size
    return list(_default_set(rig, height, width, seed)[split])


def resolve_scenes(paths, split: str, rig: Rig, size: tuple[int, int] | None = None, seed: int = 0,
                   separated: bool = True) -> list[Scene]:
    """Scenes from files/folders in ``paths``, or the default set's ``split`` when ``paths`` is
    empty; without ``separated``, without their diffuse and specular stacks (``load_scene``)."""
    if paths:
        return [load_scene(path, separated) for path in scene_paths(paths)]
    scenes = default_split(split, rig, size, seed)
    return scenes if separated else [dataclasses.replace(scene, diffuse=None, specular=None) for scene in scenes]
