"""Synthetic OLAT scenes: ray-cast shapes shaded with basis-BRDF materials (DESIGN sections 3, 7).

    O[k](x) = f(l_k, v) * max(0, n . l_k) * falloff(d_k) * V_k(x)

rendered by ``render_olat`` for every superpixel k of the rig, with V_k the optional cast-shadow
visibility (hard shadows by sphere tracing) and attached shadows always (the clamped cosine).

Radiometric scale: no extra factor. O is radiance per unit display intensity with the rig's falloff
in its own units (1/d^2 with d in metres for the physical falloff), so a white Lambertian patch
facing a superpixel 0.5-0.9 m away reads 1/(pi d^2) ~ 0.4-1.3; typical diffuse values are
O(0.1-1), specular highlights of glossy materials reach O(100-1000). Evaluation uses auto exposure,
so the absolute scale does not matter (DESIGN section 3).

Pixels outside the mask have zero OLAT, zero normal and zero depth.
"""
from __future__ import annotations

import numbers
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from capture_sim.atomic import refuse_overwriting, staged_files, write_json
from capture_sim.errors import MAX_SEED, DisplexWarning, InputError, is_whole_number
from capture_sim.materials import MATERIALS, make_material
from capture_sim.render import render_olat
from capture_sim.rig import Rig
from capture_sim.scene import Scene, save_scene
from capture_sim.shapes import SHAPE_DISTANCES_M, SHAPES, cast_camera_rays, make_shape, shadow_visibility

GENERATOR = "displex.synth"

_CHUNK_PIXELS = 1024
"""Pixels shaded at once: about 1024 * K * 3 float64 values per temporary, ~3.5 MB each for K = 144."""


SCENE_SIZE_DIVISOR = 4
"""Default synthetic scenes are the rig camera's resolution divided by this (128 x 153 for the
reference camera's 512 x 612): small enough to learn on a laptop CPU."""


def default_scene_size(rig: Rig) -> tuple[int, int]:
    """(height, width) of the default synthetic scenes: the rig camera's resolution divided by
    ``SCENE_SIZE_DIVISOR``, at least 2 x 2."""
    return tuple(max(2, round(side / SCENE_SIZE_DIVISOR)) for side in (rig.camera.height, rig.camera.width))


def scene_size(rig: Rig, height: int | None, width: int | None) -> tuple[int, int]:
    """(height, width) of synthetic scenes: the size given, or ``default_scene_size`` when both
    are None; ``InputError`` unless both are positive whole numbers."""
    if height is None and width is None:
        return default_scene_size(rig)
    if not (is_whole_number(height, 1) and is_whole_number(width, 1)):
        raise InputError(f"image size must be positive integers, got {height} x {width}")
    return int(height), int(width)


def check_scene_aspect(rig: Rig, height: int, width: int) -> None:
    """Warn when ``height`` x ``width`` has another aspect ratio than the rig's camera by more than
    a pixel's rounding: the camera's intrinsics are scaled to the size per axis, so its pixels
    would not be square and every object would look squashed."""
    scale_x, scale_y = width / rig.camera.width, height / rig.camera.height
    if abs(scale_x - scale_y) > max(scale_x, scale_y) / min(height, width):
        square = (height, max(2, round(height * rig.camera.width / rig.camera.height)))
        warnings.warn(f"{height} x {width} scenes have another aspect ratio than rig {rig.name}'s {rig.camera.height} x "
                      f"{rig.camera.width} camera: their pixels are not square (x scaled by {scale_x:.3g}, y by {scale_y:.3g}); "
                      f"{square[0]} x {square[1]} would keep them square", DisplexWarning, stacklevel=2)


def synthesize_scene(
    shape: str,
    material: str,
    rig: Rig,
    height: int | None = None,
    width: int | None = None,
    seed: int = 0,
    cast_shadows: bool = False,
    name: str | None = None,
    albedo=None,
) -> Scene:
    """Render the OLAT stack of one synthetic object seen by the rig's camera.

    Args:
        shape: one of ``capture_sim.shapes.SHAPES``; placed at the rig's working distance.
        material: one of ``capture_sim.materials.MATERIALS``.
        rig: the rig: its superpixel positions are the lights, its falloff is used, its camera
            intrinsics are scaled to ``height`` x ``width``.
        height, width: image size in pixels (None: ``default_scene_size``).
        seed: non-negative integer; the shape and the material draw from it (same seed, same scene).
        cast_shadows: trace shadow rays against the shape (slower); attached shadows are always on.
        name: scene name for ``meta``; default ``"{shape}-{material}-s{seed}"``.
        albedo: uniform (3,) or scalar diffuse albedo for ``material="lambertian"``.

    Returns:
        A ``Scene``: olat, diffuse, specular (K, H, W, 3) float32 with olat = diffuse + specular;
        mask (H, W); normal (H, W, 3) float32 (OpenCV frame, n_z < 0); depth (H, W) float32 metres;
        K_cam (3, 3); light_positions (R, C, 3) float32; meta (name, generator, shape, material,
        units, rig, seed).
    """
    if shape not in SHAPES:
        raise InputError(f"unknown shape {shape!r}; choose from {', '.join(SHAPES)}")
    if material not in MATERIALS:
        raise InputError(f"unknown material {material!r}; choose from {', '.join(MATERIALS)}")
    near, far = SHAPE_DISTANCES_M
    if not near <= rig.working_distance <= far:
        raise InputError(f"rig {rig.name}: synthetic objects are placed at the rig's working_distance, "
                         f"{rig.working_distance:g} m, which must be {near:g}..{far:g} m for scene synthesis")
    height, width = scene_size(rig, height, width)
    check_scene_aspect(rig, height, width)
    camera_rig = rig.with_resolution(height, width)
    K_cam = camera_rig.camera.matrix()

    surface = make_shape(shape, seed=seed, distance=rig.working_distance)
    hits = cast_camera_rays(surface, K_cam, height, width)
    if not bool(hits.mask.any()):
        # Pixel centres can all miss an object at a tiny size (or a rig whose camera looks away).
        raise InputError(
            f"the {shape} covers no pixel centre of a {height} x {width} image with rig {rig.name}'s camera; "
            "use a larger image size (the default is a quarter of the rig camera's resolution)"
        )
    brdf = make_material(material, hits.points, seed=seed, albedo=albedo)

    lights = rig.lights(dtype=torch.float64)
    num_lights = lights.shape[0]
    pixel_index = torch.nonzero(hits.mask.reshape(-1)).squeeze(-1)
    points = hits.points.reshape(-1, 3)[pixel_index]
    normals = hits.normals.reshape(-1, 3)[pixel_index]
    weights = brdf.weights.reshape(-1, brdf.num_basis)[pixel_index]

    diffuse = np.zeros((num_lights, height * width, 3), dtype=np.float32)
    specular = np.zeros((num_lights, height * width, 3), dtype=np.float32)
    for start in range(0, pixel_index.numel(), _CHUNK_PIXELS):
        chunk = slice(start, start + _CHUNK_PIXELS)
        visibility = shadow_visibility(surface, points[chunk], normals[chunk], lights) if cast_shadows else None
        diffuse_chunk, specular_chunk = render_olat(
            points[chunk], normals[chunk], lights, weights[chunk],
            brdf.diffuse_albedo, brdf.specular_albedo, brdf.roughness,
            falloff=rig.falloff, visibility=visibility,
        )
        columns = pixel_index[chunk].numpy()
        diffuse[:, columns] = diffuse_chunk.numpy()
        specular[:, columns] = specular_chunk.numpy()

    shape_of_stack = (num_lights, height, width, 3)
    diffuse, specular = diffuse.reshape(shape_of_stack), specular.reshape(shape_of_stack)
    meta = {
        "name": name or f"{shape}-{material}-s{seed}",
        "generator": GENERATOR,
        "shape": surface.describe(),
        "material": brdf.describe(),
        "seed": int(seed),
        "cast_shadows": bool(cast_shadows),
        "rig": rig.name,
        "units": {
            "olat": "radiance per unit display intensity: BRDF [1/sr] * cos * rig falloff "
                    f"({rig.falloff.kind}, distances in m); radiometric scale 1",
            "depth": "m, z in the OpenCV camera frame; 0 outside the mask",
            "light_positions": "m, OpenCV camera frame",
            "normal": "unit, OpenCV camera frame, n_z < 0; 0 outside the mask",
        },
    }
    return Scene(
        olat=diffuse + specular,
        mask=hits.mask.numpy().copy(),
        K_cam=K_cam,
        light_positions=rig.light_positions.astype(np.float32),
        normal=hits.normals.numpy().astype(np.float32),
        depth=hits.depth.numpy().astype(np.float32),
        diffuse=diffuse,
        specular=specular,
        meta=meta,
    )


def lambertian_sphere(rig: Rig, albedo=(0.6, 0.6, 0.6), height: int | None = None, width: int | None = None) -> Scene:
    """A uniform Lambertian sphere (radius 0.07 m on the optical axis at the working distance).

    Args:
        rig: the capture rig.
        albedo: (3,) or scalar diffuse albedo in [0, 1].
        height, width: image size in pixels (None: ``default_scene_size``).

    Returns:
        The scene (see ``synthesize_scene``); a convex sphere has no cast shadows.
    """
    return synthesize_scene("sphere", "lambertian", rig, height, width, seed=0, name="lambertian-sphere", albedo=albedo)


@dataclass(frozen=True)
class SceneSpec:
    """One scene of a generated set.

    Attributes:
        name: unique scene name (also the file stem).
        shape: one of ``SHAPES``.
        material: one of ``MATERIALS``.
        seed: seed of this scene's shape and material.
    """

    name: str
    shape: str
    material: str
    seed: int


# Train and test use different (shape, material) pairs. The test split holds out the bowl, capsule
# and cylinder families entirely; its blob is a new random blob (other bumps) with another material.
_DEFAULT_TRAIN = (
    ("sphere", "lambertian"), ("blob", "svbrdf"), ("torus", "glossy"),
    ("relief", "textured"), ("vase", "regions"), ("ellipsoid", "svbrdf"),
)
_DEFAULT_TEST = (("bowl", "svbrdf"), ("capsule", "glossy"), ("cylinder", "textured"), ("blob", "regions"))


def default_scene_specs(seed: int = 0) -> dict[str, list[SceneSpec]]:
    """The default train / test scene list (6 + 4 scenes) for a set seed.

    Scene i of the set gets seed ``100 * seed + i``, so different set seeds give different scenes.

    Returns:
        ``{"train": [...], "test": [...]}`` of ``SceneSpec``.
    """
    largest = (MAX_SEED - (len(_DEFAULT_TRAIN) + len(_DEFAULT_TEST) - 1)) // 100
    # One message with the bound that holds (the scenes' own seeds must stay valid seeds).
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= seed <= largest:
        raise InputError(f"scene set seed must be a whole number in [0, {largest}] (scene i gets seed 100 * seed + i <= {MAX_SEED}), got {seed!r}")
    specs: dict[str, list[SceneSpec]] = {}
    index = 0
    for split, pairs in (("train", _DEFAULT_TRAIN), ("test", _DEFAULT_TEST)):
        specs[split] = []
        for shape, material in pairs:
            name = f"{split}-{index:02d}-{shape}-{material}"
            specs[split].append(SceneSpec(name, shape, material, 100 * int(seed) + index))
            index += 1
    return specs


def default_scene_set(rig: Rig, height: int | None = None, width: int | None = None, seed: int = 0,
                      cast_shadows: bool = False, progress: bool = True) -> dict[str, list[Scene]]:
    """Synthesise the default scene set in memory (about 35 MB per scene at 128 x 153 per stack).

    Args:
        rig: the capture rig.
        height, width: image size in pixels (None: ``default_scene_size``).
        seed: set seed (see ``default_scene_specs``); same seed, identical arrays.
        cast_shadows: trace cast shadows (slower).
        progress: show a tqdm progress bar (tens of seconds at the default size).

    Returns:
        ``{"train": [6 scenes], "test": [4 scenes]}``.
    """
    height, width = scene_size(rig, height, width)
    scenes: dict[str, list[Scene]] = {split: [] for split in default_scene_specs(seed)}
    for split, _, scene in _synthesised(rig, height, width, seed, cast_shadows, "synthesising the default scenes", progress, leave=False):
        scenes[split].append(scene)
    return scenes


def _synthesised(rig: Rig, height: int, width: int, seed: int, cast_shadows: bool, description: str, progress: bool, leave: bool = True):
    """Yield (split, spec, scene) for every scene of the default set, one at a time, with a bar
    (``leave``: keep the finished bar on screen)."""
    jobs = [(split, spec) for split, specs in default_scene_specs(seed).items() for spec in specs]
    for split, spec in tqdm(jobs, desc=description, unit="scene", disable=not progress, leave=leave):
        yield split, spec, synthesize_scene(spec.shape, spec.material, rig, height, width, spec.seed, cast_shadows, spec.name)


def write_scene_set(out_dir: str | Path, rig: Rig, height: int | None = None, width: int | None = None, seed: int = 0,
                    cast_shadows: bool = False, progress: bool = True) -> Path:
    """Synthesise the default scene set and write it, one scene in memory at a time.

    Writes ``out_dir/train/NAME.npz`` and ``out_dir/test/NAME.npz`` (scene interchange format,
    ``save_scene``) and ``out_dir/index.json`` listing every scene with its split, file, shape,
    material and seed, plus the rig, size, set seed and generator. The scenes are synthesised into
    a hidden staging folder and renamed into place at the end, the index last: a failed or
    interrupted run leaves an earlier set in ``out_dir`` as it was (files of the same names are
    replaced by a finished run; other files are left alone).

    Args:
        out_dir: output folder (created if missing).
        rig: the capture rig.
        height, width: image size in pixels (None: ``default_scene_size``).
        seed: set seed (see ``default_scene_specs``).
        cast_shadows: trace cast shadows (slower).
        progress: show a tqdm progress bar.

    Returns:
        Path of the written ``index.json``.
    """
    out_dir = Path(out_dir)
    height, width = scene_size(rig, height, width)
    index = {
        "generator": GENERATOR,
        "rig": rig.name,
        "height": int(height),
        "width": int(width),
        "seed": int(seed),
        "cast_shadows": bool(cast_shadows),
        "splits": {split: [] for split in default_scene_specs(seed)},
    }
    index_path = out_dir / "index.json"
    # A folder where a file goes, or a file where a split's folder goes: one clear line before the work.
    planned = [("scene file", out_dir / split / f"{spec.name}.npz") for split, specs in default_scene_specs(seed).items() for spec in specs]
    refuse_overwriting([("index", index_path), *planned], [])
    # The long synthesis writes into a staging folder: interrupted, it leaves an earlier set in
    # ``out_dir`` as it was. The index goes last (and the earlier one first), so that no index ever
    # stands over a mixture of two sets (``displex demo`` reuses a folder whose index matches).
    with staged_files(out_dir, last=(index_path.name,)) as staging:
        for split, spec, scene in _synthesised(rig, height, width, seed, cast_shadows, "synthesising scenes", progress):
            relative = Path(split) / f"{spec.name}.npz"
            save_scene(scene, staging / relative)
            index["splits"][split].append({
                "name": spec.name, "file": relative.as_posix(), "shape": spec.shape,
                "material": spec.material, "seed": spec.seed,
            })
        write_json(staging / index_path.name, index)
    return index_path
