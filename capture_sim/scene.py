"""Scenes: an OLAT stack with its mask, geometry and calibration (DESIGN section 7).

A scene is read from and written to the interchange ``.npz``; ``load_scene`` validates it so that
every command fails with one clear message on a bad file.
"""
from __future__ import annotations

import dataclasses
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from capture_sim.array_files import archive_names, read_arrays, read_meta
from capture_sim.atomic import save_npz, strict_json
from capture_sim.errors import DisplexWarning, InputError, check_array, one_line, warn_once
from capture_sim.geometry import points_from_depth
from capture_sim.rig import Camera, Rig, check_light_positions

MIN_DEPTH_M = 1e-3
"""Metres: a point this close to the camera is no object in front of a display (and within the
solvers' default ``min_distance``, so every pixel would be flagged bad geometry)."""
MAX_DEPTH_M = 20.0
"""Metres: objects sit about half a metre from the camera, so a median depth above this can only be
another unit (millimetres), refused in scene files and converted by the DIR loader; no pixel inside
the mask may lie farther either."""


@dataclass(frozen=True, eq=False)
class Scene:
    """An OLAT capture of one object.

    Attributes:
        olat: (K, H, W, 3) float16/float32 linear radiance per unit display intensity, backlight removed.
        mask: (H, W) bool object mask.
        K_cam: (3, 3) float64 intrinsics for H x W.
        light_positions: (R, C, 3) float32 superpixel centres, metres, camera frame.
        normal: optional (H, W, 3) float32 unit ground-truth normals (n_z < 0 where visible).
        depth: optional (H, W) float32 z-depth in metres.
        diffuse, specular: optional (K, H, W, 3) polarisation-separated stacks.
        meta: free-form description (name, generator, material, units).
    """

    olat: np.ndarray
    mask: np.ndarray
    K_cam: np.ndarray
    light_positions: np.ndarray
    normal: np.ndarray | None = None
    depth: np.ndarray | None = None
    diffuse: np.ndarray | None = None
    specular: np.ndarray | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        validate_scene(self)

    @property
    def name(self) -> str:
        return one_line(self.meta.get("name", "scene"))

    @property
    def label(self) -> str:
        """'scene NAME (FILE)' for messages: two files may carry one meta name."""
        named = f"scene {self.name}" if "name" in self.meta else "scene"
        return named + (f" ({one_line(self.meta['file'])})" if "file" in self.meta else "")

    @property
    def height(self) -> int:
        return self.olat.shape[1]

    @property
    def width(self) -> int:
        return self.olat.shape[2]

    @property
    def num_lights(self) -> int:
        return self.olat.shape[0]

    def without_specular(self) -> "Scene":
        """The same object as if it reflected diffusely only: ``olat`` replaced by the ``diffuse``
        stack (K, H, W, 3), no specular stack; geometry, mask and meta unchanged.

        The diffuse stack takes the OLAT stack's dtype.

        Raises:
            InputError: the scene has no separate diffuse stack, or it is zero inside the mask
                (a purely specular object: every pixel would be dark).
        """
        if self.diffuse is None:
            raise InputError(f"{self.label} has no separate diffuse stack")
        diffuse = np.asarray(self.diffuse, dtype=self.olat.dtype)
        if not float(diffuse[:, self.mask].max(initial=0.0)) > 0:
            raise InputError(f"{self.label}: its diffuse stack is zero inside the mask (a purely specular object)")
        return dataclasses.replace(self, olat=diffuse, specular=None)

    def points(self, working_distance: float, dtype=torch.float32) -> torch.Tensor:
        """(H, W, 3) surface points in metres: from the depth map, else a plane at ``working_distance``."""
        if self.depth is not None:
            depth = torch.as_tensor(self.depth, dtype=torch.float64)
        else:
            depth = torch.full((self.height, self.width), float(working_distance), dtype=torch.float64)
        return points_from_depth(depth, self.K_cam).to(dtype)


UNIT_TOLERANCE = 1e-2
"""Largest |length - 1| of a ground-truth normal inside a scene's mask."""


def validate_scene(scene: Scene) -> None:
    """Raise ``InputError`` with one readable line if the scene breaks DESIGN section 7."""
    name = scene.label
    for key in _ARRAY_KEYS:
        value = getattr(scene, key)
        if value is not None and not isinstance(value, np.ndarray):
            raise InputError(f"{name}: {key} must be a numpy array (scenes hold arrays, not {type(value).__name__}; "
                             "convert a tensor with .numpy())")
    check_array(f"{name}: olat", scene.olat, ("K", "H", "W", 3))
    num_lights, height, width, _ = scene.olat.shape
    _check_radiance(name, "olat", scene.olat)
    if not float(scene.olat.max(initial=0.0)) > 0:
        # Every result from such a scene (learned patterns, errors, exposures) would be meaningless.
        raise InputError(f"{name}: every OLAT value is 0: no superpixel lights the scene")
    check_array(f"{name}: mask", scene.mask, (height, width))
    if scene.mask.dtype != np.bool_:
        raise InputError(f"{name}: mask must be bool, got {scene.mask.dtype}")
    if not scene.mask.any():
        raise InputError(f"{name}: mask selects no pixels")
    for key in ("K_cam", "light_positions", "normal", "depth", "diffuse", "specular"):
        # A bool or integer array where metres or radiance go is a mistake (a mask saved as depth,
        # depth in millimetres), not something to convert silently; intrinsics may be integers.
        value = getattr(scene, key)
        if value is None:
            continue
        dtype = np.asarray(value).dtype
        if dtype.kind not in ("iuf" if key == "K_cam" else "f"):
            raise InputError(f"{name}: {key} must hold {'numbers' if key == 'K_cam' else 'floating-point values'}, got dtype {dtype}")
    check_array(f"{name}: K_cam", scene.K_cam, (3, 3))
    intrinsics = np.asarray(scene.K_cam, dtype=np.float64)
    # Upper triangular with a positive diagonal, so invertible; K[1, 0] would otherwise be ignored.
    if not (intrinsics[0, 0] > 0 and intrinsics[1, 1] > 0 and intrinsics[1, 0] == 0 and np.array_equal(intrinsics[2], [0.0, 0.0, 1.0])):
        raise InputError(f"{name}: K_cam must be upper triangular with fx, fy > 0 and last row (0, 0, 1), got {intrinsics.tolist()}")
    centre_x, centre_y = float(intrinsics[0, 2]), float(intrinsics[1, 2])
    if not (0 <= centre_x <= width and 0 <= centre_y <= height):
        warnings.warn(f"{name}: K_cam's principal point ({centre_x:g}, {centre_y:g}) lies outside the {height} x {width} image "
                      "(intrinsics of another image size?)", DisplexWarning, stacklevel=3)
    check_light_positions(f"{name}: light_positions", scene.light_positions)
    rows, cols = scene.light_positions.shape[:2]
    if rows * cols != num_lights:
        raise InputError(
            f"{name}: olat has {num_lights} images but light_positions is a {rows} x {cols} grid ({rows * cols} lights)"
        )
    for key, shape in (("normal", (height, width, 3)), ("depth", (height, width))):
        value = getattr(scene, key)
        if value is not None:
            check_array(f"{name}: {key}", value, shape, finite=False)
            bad = ~np.isfinite(value)
            if bad.any():
                inside = bad[scene.mask].any(axis=-1) if value.ndim == 3 else bad[scene.mask]
                where = f"at {int(inside.sum())} pixels inside the mask" if inside.any() else "outside the mask (set them to 0; load_scene does)"
                raise InputError(f"{name}: {key} has NaN or infinite values {where}")
    if scene.normal is not None:
        inside = np.asarray(scene.normal, dtype=np.float64)[scene.mask]
        # A component beyond 2 is no unit vector, and 1e300 would overflow the norm.
        if inside.size and (float(np.abs(inside).max()) > 2 or float(np.abs(np.linalg.norm(inside, axis=-1) - 1).max()) > UNIT_TOLERANCE):
            raise InputError(f"{name}: normals inside the mask must be unit vectors")
        # Grazing normals may lean slightly past n_z = 0; a majority facing away is a flipped convention.
        if inside.size and float((inside[:, 2] > 0).mean()) > 0.5:
            raise InputError(f"{name}: most normals face away from the camera (n_z > 0); visible normals have n_z < 0 (README: Conventions)")
    if scene.depth is not None:
        nearest = float(scene.depth[scene.mask].min())
        if nearest <= MIN_DEPTH_M:
            raise InputError(f"{name}: depth must exceed {MIN_DEPTH_M * 1000:g} mm inside the mask, got {nearest:g} m "
                             "(depth is in metres: another unit, or an unset background inside the mask?)")
        median = float(np.median(scene.depth[scene.mask]))
        if median > MAX_DEPTH_M:
            raise InputError(f"{name}: depth must be in metres, but its median inside the mask is {median:g} (millimetres?)")
        # One far outlier (an unset or background value inside the mask) would otherwise reach the
        # light field as a distance the falloff cannot serve, or quietly as a wrong light direction.
        farthest = float(scene.depth[scene.mask].max())
        if farthest > MAX_DEPTH_M:
            count = int((scene.depth[scene.mask] > MAX_DEPTH_M).sum())
            raise InputError(f"{name}: depth must be at most {MAX_DEPTH_M:g} m inside the mask, but {count} pixel{'s' if count > 1 else ''} "
                             f"reach{'' if count > 1 else 'es'} {farthest:g} m (an unset or background value inside the mask?)")
    for key in ("diffuse", "specular"):
        stack = getattr(scene, key)
        if stack is not None:
            check_array(f"{name}: {key}", stack, (num_lights, height, width, 3))
            _check_radiance(name, key, stack)


def _check_radiance(name: str, key: str, stack: np.ndarray) -> None:
    """An OLAT-like stack must be float16 or float32 (any byte order) and non-negative."""
    if stack.dtype.kind != "f" or stack.dtype.itemsize not in (2, 4):
        raise InputError(f"{name}: {key} must be float16 or float32, got {stack.dtype}")
    if float(stack.min(initial=0.0)) < 0:
        raise InputError(f"{name}: {key} has negative radiance (min {float(stack.min()):g})")


_ARRAY_KEYS = ("olat", "mask", "K_cam", "light_positions", "normal", "depth", "diffuse", "specular")


SEPARATED_STACKS = ("diffuse", "specular")


def load_scene(path: str | Path, separated: bool = True) -> Scene:
    """Read and validate a scene interchange ``.npz`` (DESIGN section 7). With ``separated``
    False the polarisation-separated ``diffuse`` and ``specular`` stacks are not read (for work
    on the OLAT stack alone: each is as large as it, 1 GB at full resolution in float32)."""
    path = Path(path)
    keys = _ARRAY_KEYS if separated else tuple(key for key in _ARRAY_KEYS if key not in SEPARATED_STACKS)
    arrays = read_arrays(path, "scene", keys=(*keys, "meta"))
    if isinstance(arrays, np.ndarray):
        raise InputError(f"{path}: a plain .npy array, but a scene is an .npz of named arrays (README: Scene files)")
    meta = read_meta(arrays, path, "scene")
    arrays.pop("meta", None)
    for required in ("olat", "mask", "K_cam", "light_positions"):
        if required not in arrays:
            raise InputError(f"{path}: scene is missing required array '{required}'")
    unknown = sorted(set(archive_names(path)) - {*_ARRAY_KEYS, "meta"})
    if unknown:  # a misspelt optional array ('Depth', 'normals') would silently fall back to its default
        warn_once(f"{path}: unknown arrays {', '.join(map(repr, unknown))} are ignored (a scene file holds {', '.join(_ARRAY_KEYS)} and meta)")
    # Native byte order (files written on big-endian machines or by other tools), same values.
    arrays = {key: value if value.dtype.isnative else value.astype(value.dtype.newbyteorder("=")) for key, value in arrays.items()}
    arrays.update(_zero_background(arrays))
    meta.setdefault("name", path.stem)
    meta["file"] = str(path)  # in memory only: outputs are named after the file the user gave
    return Scene(meta=meta, **arrays)


def _zero_background(arrays: dict) -> dict:
    """``normal`` and ``depth`` with non-finite values outside the mask set to 0: ground truth
    often holds NaN in the background, which no computation reads. Arrays whose shapes do not
    fit the mask are left for ``validate_scene`` to refuse."""
    mask = arrays["mask"]
    cleaned = {}
    for key in ("normal", "depth"):
        value = arrays.get(key)
        if value is None or value.dtype.kind != "f" or mask.dtype != np.bool_ or value.shape[:2] != mask.shape:
            continue
        outside = ~np.isfinite(value) & ~(mask if value.ndim == 2 else mask[..., None])
        if outside.any():
            cleaned[key] = np.where(outside, 0, value).astype(value.dtype)
    return cleaned


def save_scene(scene: Scene, path: str | Path, compressed: bool = True) -> None:
    """Write a scene as interchange ``.npz`` atomically."""
    arrays = {key: getattr(scene, key) for key in _ARRAY_KEYS if getattr(scene, key) is not None}
    save_npz(path, compressed=compressed, meta=np.array(strict_json(scene.meta)), **arrays)


def scene_files(folder: Path) -> list[Path]:
    """The scene files of a folder: every ``*.npz`` in it, sorted, hidden ones left out (the
    temporary files of an interrupted atomic write, ``capture_sim.atomic``, or a system's side
    files, macOS ``._name.npz``)."""
    return sorted(path for path in Path(folder).glob("*.npz") if not path.name.startswith("."))


def scene_paths(paths) -> list[Path]:
    """Expand files and folders (their ``scene_files``) into a list of scene files."""
    found: list[Path] = []
    for entry in paths:
        entry = Path(entry)
        if entry.is_dir():
            files = scene_files(entry)
            if not files:
                splits = [split for split in ("train", "test") if scene_files(entry / split)]
                hint = f"; a synthesised scene set: pass {' or '.join(str(entry / split) for split in splits)}" if splits else ""
                raise InputError(f"no scene .npz files in folder {entry}{hint}")
            found.extend(files)
        elif entry.is_file():
            found.append(entry)
        elif entry.is_symlink() and not entry.exists():
            raise InputError(f"scene path {entry} is a link to {os.readlink(entry)}, which is not found")
        elif os.path.lexists(entry):  # a device or FIFO: there, but not a scene file
            raise InputError(f"scene path {entry} is not a file or folder")
        else:
            raise InputError(f"scene path not found: {entry}")
    return found


def file_fingerprints(paths) -> list[list]:
    """[absolute path, size in bytes, modification time in ns] of each file: what a run records of
    the files it was made from, so that a file rewritten or replaced since is noticed
    (``InputError`` for a file that is not there, such as a broken link)."""
    fingerprints = []
    for path in paths:
        try:
            status = Path(path).stat()
        except FileNotFoundError:  # e.g. a broken link listed in a scene folder
            raise InputError(f"file not found: {path}") from None
        fingerprints.append([str(Path(path).resolve()), status.st_size, status.st_mtime_ns])
    return fingerprints


LIGHT_MISMATCH_M = 0.01
"""Metres: scene and rig light positions further apart than this are reported (a scene from
another rig, or a stale calibration); closer ones are calibration rounding."""
MILLIMETRE_MATCH_M = 0.2
"""Metres: scene lights that, divided by 1000, lie within this of the rig's are the rig's display
calibrated in millimetres (two calibrations of one display differ by ~0.1 m)."""


def rig_for_scene(rig: Rig, scene: Scene) -> Rig:
    """The rig's display and sensor models with the scene's own lights and intrinsics.

    A scene carries the calibration it was captured with; the rig supplies what the scene does not
    (backlight, gamma, scale, noise, bit depth, falloff). Their light grids must agree.
    """
    rows, cols = scene.light_positions.shape[:2]
    if (rows, cols) != (rig.rows, rig.cols):
        raise InputError(f"{scene.label} has a {rows} x {cols} light grid but rig {rig.name} is {rig.rows} x {rig.cols}; "
                         "a scene made for another rig needs that rig (--rig, or `rig` in a config)")
    camera = Camera(K_cam=tuple(tuple(float(v) for v in row) for row in scene.K_cam), height=scene.height, width=scene.width,
                    exposure_ms=rig.camera.exposure_ms)
    lights = scene.light_positions.astype(np.float64)
    # A distant display is a valid scene (far-field tests), so the unit cannot be told from the
    # distances alone; a grid near the rig's in millimetres (raw DIR calibration, or another
    # calibration of the same display) can, when it fits the rig's better than the metres do (a
    # small display near the camera lies within the tolerance of anything divided by 1000). A
    # far-field scene built as exactly "rig x 1000" is refused too.
    shift = float(np.linalg.norm(lights - rig.light_positions, axis=-1).max())
    millimetre_shift = float(np.linalg.norm(lights / 1000.0 - rig.light_positions, axis=-1).max())
    if millimetre_shift <= MILLIMETRE_MATCH_M and millimetre_shift < shift:
        raise InputError(f"{scene.label}: its light positions are rig {rig.name}'s in millimetres; scene files use metres (divide by 1000)")
    recorded = scene.meta.get("rig")
    if isinstance(recorded, str) and recorded != rig.name:
        warn_once(f"scenes made for rig {recorded!r} are used with rig {rig.name!r}: their own light positions and "
                  "intrinsics, its display and sensor", stacklevel=2)  # one line for all the scenes of that rig
    elif shift > LIGHT_MISMATCH_M:
        warn_once(f"{scene.label}: its light positions differ from rig {rig.name}'s by up to {shift:.3f} m; "
                  "the scene's own light positions are used, with the rig's display and sensor", stacklevel=2)
    return rig.replace(light_positions=lights, camera=camera)

