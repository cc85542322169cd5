"""Loaders for the public DIR dataset of the reference rig (DESIGN section 7) into ``Scene``.

Two published layouts per object folder:

    DIR-basic: main/diffuseNspecular/000.png .. 143.png, main/diffuseNspecular/black.png (and
               white.png, unused), mask.png, point_cloud.npy (H x W x 3, depth in the last channel),
               GT_geometry/normal.npy
    DIR-pms (DiLiGenT style): 000.png .. 143.png, filenames.txt, light_directions.txt,
               light_intensities.txt, mask.png, Normal_gt.mat

Foreign conventions are mapped here, once:

- Light order. The published code mirrors the pattern's column axis before weighting the OLAT
  files, so OLAT file i = r * C + c was lit by superpixel (r, C - 1 - c): file i goes to our light
  k = (i // C) * C + (C - 1 - i % C) (``dir_file_to_light``).
- Radiometry. The PNGs are linear 8-bit captures (the published loader only divides by 255), so
  O_k = max(0, image / 255 - black / 255) / ((1 + B_k)^gamma - B_k^gamma): ``black.png`` is the
  capture with every superpixel at 0 (the backlight only); subtracting it removes the backlight,
  and the division by the display's emission step from set value 0 to 1 of superpixel k (backlight
  B_k, DESIGN section 3) leaves the OLAT per unit display intensity (DESIGN section 2). The DIR-pms
  layout ships no black capture, so nothing is subtracted or divided there; its
  light_directions.txt / light_intensities.txt are checked but not applied (the rig's positions
  and falloff describe the lights). 16-bit PNGs divide by 65535; 16-bit colour PNGs are read by
  ``capture_sim.png`` (Pillow would keep only their high bytes), which supports unfiltered files
  such as displex writes and refuses others with an error.
- Normals. Their frame is not documented. Rule: if most valid normals inside the mask have
  n_z > 0, they are in an OpenGL-style frame (x right, y up, z towards the camera) and we negate
  y and z to reach the OpenCV frame (n_z < 0 visible); otherwise they are used as they are.
- Mask. Pixels inside mask.png whose ground truth is missing (non-finite or zero normal, or
  non-positive depth) leave the mask; how many is recorded in ``meta["mask_dropped_pixels"]``.
  OLAT values outside the mask are kept as captured (unlike synthetic scenes, where they are 0).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from capture_sim.array_files import read_arrays
from capture_sim.errors import InputError, check_array, warn_once
from capture_sim.png import decode_png, png_format
from capture_sim.rig import Rig
from capture_sim.scene import MAX_DEPTH_M, UNIT_TOLERANCE, Scene

GENERATOR = "displex.dir_dataset"


def dir_file_to_light(file_index, rows: int, cols: int):
    """Light index k = r * C + c of our grid for DIR OLAT file number ``file_index``.

    File i was lit by superpixel (i // C, C - 1 - i % C): the published rendering code mirrors the
    pattern's columns, so its file column c is our column C - 1 - c.

    Args:
        file_index: int or integer array of file numbers in [0, R * C).
        rows, cols: the display grid R x C.

    Returns:
        Light index (same type and shape as ``file_index``).
    """
    file_index = np.asarray(file_index)
    if np.any(file_index < 0) or np.any(file_index >= rows * cols):
        raise InputError(f"DIR file index must lie in [0, {rows * cols}), got {file_index}")
    light = (file_index // cols) * cols + (cols - 1 - file_index % cols)
    return int(light) if light.ndim == 0 else light


def detect_dir_layout(folder: str | Path) -> str:
    """``"basic"`` if ``folder/main/diffuseNspecular`` exists, ``"pms"`` if ``folder/filenames.txt`` does."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"DIR object folder not found: {folder}")
    if (folder / "main" / "diffuseNspecular").is_dir():
        return "basic"
    if (folder / "filenames.txt").is_file():
        return "pms"
    raise InputError(
        f"{folder}: not a DIR object folder: expected main/diffuseNspecular/ (DIR-basic) or "
        "filenames.txt (DIR-pms, DiLiGenT style)"
    )


def load_dir_object(folder: str | Path, rig: Rig, downsample: int = 1) -> Scene:
    """Load one DIR object (either layout) as a scene in our conventions.

    Args:
        folder: the object's folder (e.g. ``DIR/A``).
        rig: the rig it was captured with (its R x C must match the 144 files, its camera's aspect
            ratio the images'); gives light_positions and the intrinsics, scaled to the image size.
        downsample: integer box-filter factor f (image sides must be divisible by it): OLAT and
            depth are averaged over f x f blocks, normals averaged and renormalised, and a block is
            in the mask only if all its pixels are. DIR's 512 x 612 with f = 4 gives 128 x 153.

    Returns:
        A ``Scene``: olat (K, H/f, W/f, 3) float32 (see the module docstring for the light order and
        black-level rule), mask, normal (OpenCV frame) and depth (metres) when available, K_cam,
        light_positions (R, C, 3) float32, meta (name, generator, layout, the conventions applied).
    """
    folder = Path(folder)
    layout = detect_dir_layout(folder)
    if not isinstance(downsample, (int, np.integer)) or downsample < 1:
        raise InputError(f"downsample must be a positive integer, got {downsample!r}")
    num_lights = rig.num_lights
    light_of_file = dir_file_to_light(np.arange(num_lights), rig.rows, rig.cols)
    notes: dict = {}

    if layout == "basic":
        image_dir = folder / "main" / "diffuseNspecular"
        image_paths = [image_dir / f"{i:03d}.png" for i in range(num_lights)]
        _require_files(image_paths + [image_dir / "black.png", folder / "mask.png"], folder)
        numbered = [path for path in image_dir.glob("*.png") if path.stem.isdigit()]
        if len(numbered) != num_lights:  # e.g. a rig of another grid: its first K files would pass
            raise InputError(f"{image_dir}: {len(numbered)} numbered OLAT images, but rig {rig.name} has {rig.rows} x {rig.cols} = "
                             f"{num_lights} superpixels")
        black = _read_image(image_dir / "black.png")
        notes["olat"] = (
            "PNG / full scale minus black.png (backlight-only capture), clamped at 0, divided per light by "
            "(1 + B_k)^gamma - B_k^gamma (the display's emission step from set value 0 to 1 with backlight B_k)"
        )
    else:
        image_paths = _pms_image_paths(folder, num_lights)
        _require_files(image_paths + [folder / "mask.png"], folder)
        for text_file in ("light_directions.txt", "light_intensities.txt"):
            _check_light_table(folder / text_file, num_lights)
        black = None
        notes["olat"] = "PNG / full scale (no black capture in this layout; nothing subtracted)"
        notes["light_tables"] = "light_directions.txt and light_intensities.txt checked, not applied"

    mask_full = _read_mask(folder / "mask.png")
    height, width = mask_full.shape
    _check_camera(rig, height, width, folder)
    if height % downsample or width % downsample:
        raise InputError(f"{folder}: image size {height} x {width} is not divisible by downsample {downsample}")
    if black is not None and black.shape[:2] != (height, width):
        raise InputError(f"{folder}: black.png is {black.shape[1]} x {black.shape[0]}, mask.png is {width} x {height}")

    out_h, out_w = height // downsample, width // downsample
    backlight = rig.backlight.reshape(-1)
    emission_step = (1.0 + backlight) ** rig.gamma - backlight**rig.gamma
    olat = np.zeros((num_lights, out_h, out_w, 3), dtype=np.float32)
    for file_index, path in enumerate(image_paths):
        image = _read_image(path)
        if image.shape[:2] != (height, width):
            raise InputError(f"{path}: image is {image.shape[1]} x {image.shape[0]}, mask.png is {width} x {height}")
        light = light_of_file[file_index]
        if black is not None:
            # image - black = s ((1 + B_k)^gamma - B_k^gamma) O_k under the display model (DESIGN section
            # 3): divide by the per-light step so that O_k is radiance per unit display intensity (the
            # global s only scales every capture, which auto exposure absorbs).
            image = np.clip(image - black, 0.0, None) / emission_step[light]
        olat[light] = _block_mean(image, downsample)

    normal_full, depth_full = _read_geometry(folder, layout, (height, width), notes)
    valid = mask_full.copy()
    if normal_full is not None:
        length = np.linalg.norm(np.nan_to_num(normal_full), axis=-1)
        normal_ok = np.isfinite(normal_full).all(-1) & (length > 1e-6)
        stored = valid & normal_ok
        off = stored & (np.abs(length - 1.0) > UNIT_TOLERANCE)
        if 2 * off.sum() > stored.sum():
            # A colour-encoded map ((n + 1) / 2, or 0..255) renormalised would be tens of degrees off.
            raise InputError(f"{folder}: most ground-truth normals inside the mask are not unit vectors (lengths "
                             f"{float(length[stored].min()):.3g} to {float(length[stored].max()):.3g}); decode a colour-encoded "
                             "normal map (e.g. n = 2 c - 1) before loading")
        normal_ok &= ~off  # a few odd pixels (e.g. interpolated at an edge) leave the mask like missing ones
        notes["non_unit_normals_dropped"] = int(off.sum())
        valid &= normal_ok
        unit = np.nan_to_num(normal_full) / np.maximum(length, 1e-12)[..., None]
        normal_full = np.where(normal_ok[..., None], unit, 0.0)
        normal_full = _to_opencv_normals(normal_full, valid, notes)
    if depth_full is not None:
        depth_ok = np.isfinite(depth_full) & (depth_full > 0)
        valid &= depth_ok
        depth_full = np.where(depth_ok, depth_full, 0.0)
        depth_full = _to_metres(depth_full, valid, notes)
    notes["mask_dropped_pixels"] = int(mask_full.sum() - valid.sum())
    if mask_full.any() and not valid.any():
        raise InputError(f"{folder}: none of the {int(mask_full.sum())} pixels of mask.png has usable ground truth "
                         "(finite unit normals, positive depth)")
    if depth_full is not None and valid.any():
        median = float(np.median(depth_full[valid]))
        low, high = rig.working_distance / 4, rig.working_distance * 4
        if not low <= median <= high:
            warn_once(f"{folder}: the object's median depth is {median:.4g} m after unit conversion ({notes['depth_units']}), outside "
                      f"{low:g}..{high:g} m around rig {rig.name}'s working distance {rig.working_distance:g} m: are the depths in another unit?")

    mask = _block_all(valid, downsample)
    if valid.any() and not mask.any():
        raise InputError(f"{folder}: no {downsample} x {downsample} block of mask.png has usable ground truth at all its pixels "
                         f"({notes['mask_dropped_pixels']} mask pixels lack it); load with a smaller downsample")
    normal = depth = None
    if normal_full is not None:
        normal = _block_mean(normal_full, downsample)
        normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
        normal[~mask] = 0.0
        normal = normal.astype(np.float32)
    if depth_full is not None:
        depth = np.where(mask, _block_mean(depth_full, downsample), 0.0).astype(np.float32)

    meta = {
        "name": folder.name,
        "generator": GENERATOR,
        "source": str(folder),
        "layout": f"DIR-{layout}",
        "rig": rig.name,
        "downsample": int(downsample),
        "light_mapping": "file i -> light (i // C) * C + (C - 1 - i % C): DIR mirrors pattern columns",
        **notes,
        "units": {"olat": "linear, 1 = sensor full scale", "depth": "m", "light_positions": "m, OpenCV camera frame"},
    }
    return Scene(
        olat=olat,
        mask=mask,
        K_cam=rig.with_resolution(out_h, out_w).camera.matrix(),
        light_positions=rig.light_positions.astype(np.float32),
        normal=normal,
        depth=depth,
        meta=meta,
    )


def dir_object_folders(root: str | Path) -> list[Path]:
    """Sorted sub-folders of ``root`` that hold a DIR object in either layout."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"DIR dataset folder not found: {root}")
    found = [p for p in sorted(root.iterdir()) if p.is_dir()
             and ((p / "main" / "diffuseNspecular").is_dir() or (p / "filenames.txt").is_file())]
    if not found:
        raise InputError(f"{root}: no DIR object folders (main/diffuseNspecular/ or filenames.txt) inside")
    return found


def load_dir_dataset(root: str | Path, rig: Rig, downsample: int = 1) -> list[Scene]:
    """Load every DIR object folder under ``root`` (see ``load_dir_object``), sorted by name."""
    return [load_dir_object(folder, rig, downsample) for folder in dir_object_folders(root)]


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def _require_files(paths: list[Path], folder: Path) -> None:
    missing = [p for p in paths if not p.is_file()]
    if missing:
        shown = ", ".join(str(p.relative_to(folder)) for p in missing[:3])
        more = f" and {len(missing) - 3} more" if len(missing) > 3 else ""
        raise InputError(f"{folder}: missing DIR file(s) {shown}{more}")


def _pms_image_paths(folder: Path, num_lights: int) -> list[Path]:
    path = folder / "filenames.txt"
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: not a readable list of image names ({err})") from None
    names = [line.strip() for line in text.splitlines() if line.strip()]
    if len(names) != num_lights:
        raise InputError(f"{folder / 'filenames.txt'}: lists {len(names)} images, the rig has {num_lights} lights")
    return [folder / name for name in names]


def _check_light_table(path: Path, num_lights: int) -> None:
    if not path.is_file():
        raise InputError(f"{path.parent}: missing DIR file(s) {path.name}")
    try:
        table = np.loadtxt(path, ndmin=2)
    except ValueError as err:
        raise InputError(f"{path}: not a table of numbers ({err})") from None
    if table.shape != (num_lights, 3) or not np.isfinite(table).all():
        raise InputError(f"{path}: expected {num_lights} finite rows of 3 numbers, got shape {table.shape}")


def _read_image(path: Path) -> np.ndarray:
    """(H, W, 3) float64 image in [0, 1] from an 8-bit or 16-bit PNG (grey is copied to RGB)."""
    try:
        header = png_format(path)
    except OSError as err:
        raise InputError(f"{path}: not a readable image ({err.strerror})") from None
    if header is not None and header[0] == 16 and header[1] in (2, 6):
        # Pillow reads 16-bit colour PNGs as 8-bit RGB (high bytes only): decode them here.
        if header[1] == 6:
            raise InputError(f"{path}: 16-bit RGBA PNGs are not supported (save the OLAT images as 16-bit RGB or grey, or 8-bit)")
        try:
            return decode_png(path.read_bytes(), str(path)).astype(np.float64) / 65535.0
        except InputError as err:
            raise InputError(f"{err} (16-bit colour PNGs must be unfiltered, as displex writes them; 8-bit and 16-bit grey PNGs "
                             "may be filtered)") from None
    try:
        with Image.open(path) as image:
            mode = image.mode
            if mode in ("I;16", "I;16B", "I;16L"):
                values = np.asarray(image, dtype=np.float64) / 65535.0
            elif mode in ("RGB", "RGBA", "L", "P", "LA", "1"):
                values = np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0
            else:
                values = None
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: not a readable image ({err})") from None
    if values is None:
        raise InputError(f"{path}: unsupported image mode {mode} (expected 8-bit RGB/grey or 16-bit grey PNG)")
    if values.ndim == 2:
        values = np.repeat(values[..., None], 3, axis=-1)
    return values


def _read_mask(path: Path) -> np.ndarray:
    """(H, W) bool: any non-zero channel is object."""
    return _read_image(path).max(axis=-1) > 0


def _check_camera(rig: Rig, height: int, width: int, folder: Path) -> None:
    """Scaling the rig's intrinsics to the images is only right if the aspect ratios agree."""
    scale_y, scale_x = height / rig.camera.height, width / rig.camera.width
    if abs(scale_x - scale_y) > 0.01 * max(scale_x, scale_y):
        raise InputError(
            f"{folder}: mask.png (the size every image must have) is {height} x {width} but rig {rig.name}'s camera is "
            f"{rig.camera.height} x {rig.camera.width}; the intrinsics cannot be scaled to a different aspect ratio"
        )


def _read_geometry(folder: Path, layout: str, size: tuple[int, int], notes: dict):
    """Ground-truth normals (H, W, 3) and depth (H, W) as stored, or None when the file is absent."""
    normal = depth = None
    if layout == "basic":
        normal_path, cloud_path = folder / "GT_geometry" / "normal.npy", folder / "point_cloud.npy"
        if normal_path.is_file():
            normal = _load_npy(normal_path)
        if cloud_path.is_file():
            cloud = _load_npy(cloud_path)
            if cloud.ndim != 3 or cloud.shape[-1] != 3:
                raise InputError(f"{cloud_path}: expected shape (H, W, 3), got {cloud.shape}")
            depth = cloud[..., 2]
        absent = [str(p.relative_to(folder)) for p in (normal_path, cloud_path) if not p.is_file()]
    else:
        normal_path = folder / "Normal_gt.mat"
        if normal_path.is_file():
            normal = _load_mat_normals(normal_path)
        absent = [] if normal_path.is_file() else [normal_path.name]
    if absent:
        notes["absent_optional_files"] = absent
    if normal is not None and normal.shape != (*size, 3):
        raise InputError(f"{normal_path}: expected shape {(*size, 3)}, got {normal.shape}")
    if depth is not None and depth.shape != size:
        raise InputError(f"{folder / 'point_cloud.npy'}: expected {size} pixels, got {depth.shape}")
    return normal, depth


def _load_npy(path: Path) -> np.ndarray:
    array = read_arrays(path, ".npy array")
    if not isinstance(array, np.ndarray):
        raise InputError(f"{path}: an .npz archive, expected a plain .npy array")
    check_array(str(path), array, finite=False)  # numbers; NaN is allowed outside the mask
    return array.astype(np.float64)


def _load_mat_normals(path: Path) -> np.ndarray:
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    try:
        contents = loadmat(path)
    except (OSError, ValueError, NotImplementedError, MatReadError) as err:
        raise InputError(f"{path}: not a readable .mat file ({err})") from None
    if "Normal_gt" in contents:
        return np.asarray(contents["Normal_gt"], dtype=np.float64)
    arrays = [v for k, v in contents.items() if not k.startswith("__") and np.ndim(v) == 3]
    if len(arrays) != 1:
        raise InputError(f"{path}: expected a variable 'Normal_gt' of shape (H, W, 3)")
    return np.asarray(arrays[0], dtype=np.float64)


def _to_opencv_normals(normal: np.ndarray, valid: np.ndarray, notes: dict) -> np.ndarray:
    """Apply the sign rule of the module docstring; records which convention was found."""
    if valid.any() and np.mean(normal[valid][:, 2] > 0) > 0.5:
        notes["normal_convention"] = "OpenGL-style (most n_z > 0) -> OpenCV: y and z negated"
        return normal * np.array([1.0, -1.0, -1.0])
    notes["normal_convention"] = "OpenCV (most n_z < 0): unchanged"
    return normal


def _to_metres(depth: np.ndarray, valid: np.ndarray, notes: dict) -> np.ndarray:
    """Depth in metres: objects sit ~0.5 m away, so a median above 20 can only be millimetres."""
    if valid.any() and float(np.median(depth[valid])) > MAX_DEPTH_M:
        notes["depth_units"] = "millimetres in point_cloud.npy, converted to metres"
        return depth / 1000.0
    notes["depth_units"] = "metres in point_cloud.npy"
    return depth


def _block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean over factor x factor blocks of the first two axes."""
    if factor == 1:
        return image.copy()
    height, width = image.shape[0] // factor, image.shape[1] // factor
    return image.reshape(height, factor, width, factor, *image.shape[2:]).mean(axis=(1, 3))


def _block_all(mask: np.ndarray, factor: int) -> np.ndarray:
    """A block is True only if all of its factor x factor pixels are."""
    if factor == 1:
        return mask.copy()
    height, width = mask.shape[0] // factor, mask.shape[1] // factor
    return mask.reshape(height, factor, width, factor).all(axis=(1, 3))
