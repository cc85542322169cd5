"""DIR dataset loaders (capture_sim.dir_dataset) on tiny hand-built folders of both layouts."""
from __future__ import annotations

import json
import struct
import warnings
import zlib

import numpy as np
import pytest
from PIL import Image
from scipy.io import savemat

from capture_sim.dir_dataset import (
    detect_dir_layout, dir_file_to_light, dir_object_folders, load_dir_dataset, load_dir_object,
)
from capture_sim.errors import DisplexWarning, InputError
from capture_sim.png import write_png
from capture_sim.rig import load_rig

HEIGHT, WIDTH = 6, 8
NUM_FILES = 144
BLACK_LEVEL = 3  # 8-bit value of black.png in every channel


@pytest.fixture(scope="module")
def rig():
    return load_rig().with_resolution(HEIGHT, WIDTH)


def _object_mask():
    mask = np.ones((HEIGHT, WIDTH), dtype=bool)
    mask[0, :] = False
    mask[:, 0] = False
    return mask


def _opencv_normals():
    """(H, W, 3) unit normals in the OpenCV frame (n_z < 0), varying over the image."""
    v, u = np.meshgrid(np.linspace(-0.4, 0.4, HEIGHT), np.linspace(-0.5, 0.5, WIDTH), indexing="ij")
    normals = np.stack([u, v, -np.ones_like(u)], axis=-1)
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def _olat_png(file_index):
    """8-bit RGB content of OLAT file i: red encodes the file, green the pixel, blue is constant."""
    v, u = np.meshgrid(np.arange(HEIGHT), np.arange(WIDTH), indexing="ij")
    red = np.full((HEIGHT, WIDTH), BLACK_LEVEL + file_index + 1)
    green = BLACK_LEVEL + 10 + v * WIDTH + u
    blue = np.full((HEIGHT, WIDTH), BLACK_LEVEL + 200)
    return np.stack([red, green, blue], axis=-1).astype(np.uint8)


def _save_png(path, array):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)


def _make_basic(folder, normals=None, depth=None):
    image_dir = folder / "main" / "diffuseNspecular"
    for i in range(NUM_FILES):
        _save_png(image_dir / f"{i:03d}.png", _olat_png(i))
    _save_png(image_dir / "black.png", np.full((HEIGHT, WIDTH, 3), BLACK_LEVEL, dtype=np.uint8))
    _save_png(image_dir / "white.png", np.full((HEIGHT, WIDTH, 3), 250, dtype=np.uint8))
    _save_png(folder / "mask.png", (_object_mask() * 255).astype(np.uint8))
    cloud = np.zeros((HEIGHT, WIDTH, 3))
    cloud[..., 2] = 0.5 + 0.01 * np.arange(WIDTH) if depth is None else depth
    np.save(folder / "point_cloud.npy", cloud)
    (folder / "GT_geometry").mkdir(parents=True, exist_ok=True)
    np.save(folder / "GT_geometry" / "normal.npy", _opencv_normals() if normals is None else normals)
    return folder


def _make_pms(folder, normals=None):
    folder.mkdir(parents=True, exist_ok=True)
    names = [f"{i:03d}.png" for i in range(NUM_FILES)]
    for i, name in enumerate(names):
        _save_png(folder / name, _olat_png(i))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", np.tile([0.0, 0.0, 1.0], (NUM_FILES, 1)))
    np.savetxt(folder / "light_intensities.txt", np.ones((NUM_FILES, 3)))
    _save_png(folder / "mask.png", (_object_mask() * 255).astype(np.uint8))
    opengl = _opencv_normals() * np.array([1.0, -1.0, -1.0])  # DiLiGenT frame: y up, z towards the camera
    savemat(folder / "Normal_gt.mat", {"Normal_gt": opengl if normals is None else normals})
    return folder


@pytest.fixture(scope="module")
def basic_folder(tmp_path_factory):
    return _make_basic(tmp_path_factory.mktemp("dir") / "A")


@pytest.fixture(scope="module")
def pms_folder(tmp_path_factory):
    return _make_pms(tmp_path_factory.mktemp("dir_pms") / "APNG")


def test_file_to_light_mirrors_columns():
    rows, cols = 9, 16
    assert dir_file_to_light(0, rows, cols) == 15
    assert dir_file_to_light(15, rows, cols) == 0
    assert dir_file_to_light(16, rows, cols) == 31
    assert dir_file_to_light(143, rows, cols) == 128
    lights = dir_file_to_light(np.arange(rows * cols), rows, cols)
    assert sorted(lights.tolist()) == list(range(rows * cols))
    assert np.array_equal(dir_file_to_light(lights, rows, cols), np.arange(rows * cols))  # a mirror twice is identity
    with pytest.raises(InputError):
        dir_file_to_light(144, rows, cols)


def test_layout_detection(basic_folder, pms_folder, tmp_path):
    assert detect_dir_layout(basic_folder) == "basic"
    assert detect_dir_layout(pms_folder) == "pms"
    with pytest.raises(InputError, match="not a DIR object folder"):
        detect_dir_layout(tmp_path)
    with pytest.raises(InputError, match="not found"):
        detect_dir_layout(tmp_path / "missing")


def test_basic_layout_olat_order_black_level_and_geometry(basic_folder, rig):
    scene = load_dir_object(basic_folder, rig)
    assert scene.olat.shape == (NUM_FILES, HEIGHT, WIDTH, 3) and scene.olat.dtype == np.float32
    # Each light's image minus black is divided by its emission step (1 + B)^gamma - B^gamma.
    backlight = rig.backlight.reshape(-1)
    step = (1 + backlight) ** rig.gamma - backlight**rig.gamma
    for file_index in range(NUM_FILES):
        row, col = divmod(file_index, 16)
        light = row * 16 + (15 - col)
        expected_red = (file_index + 1) / 255.0 / step[light]  # black level subtracted
        assert np.allclose(scene.olat[light, ..., 0], expected_red, atol=1e-7), file_index
    v, u = np.meshgrid(np.arange(HEIGHT), np.arange(WIDTH), indexing="ij")
    assert np.allclose(scene.olat[5, ..., 1], (10 + v * WIDTH + u) / 255.0 / step[5], atol=1e-7)
    assert np.allclose(scene.olat[..., 2], 200 / 255.0 / step[:, None, None], atol=1e-7)
    assert np.array_equal(scene.mask, _object_mask())
    assert np.allclose(scene.normal[scene.mask], _opencv_normals()[scene.mask], atol=1e-6)
    assert not scene.normal[~scene.mask].any()
    assert np.allclose(scene.depth[scene.mask], (0.5 + 0.01 * u)[scene.mask], atol=1e-6)
    assert np.allclose(scene.K_cam, rig.camera.matrix())
    assert np.array_equal(scene.light_positions, rig.light_positions.astype(np.float32))
    assert scene.meta["layout"] == "DIR-basic" and scene.meta["name"] == "A"
    assert "unchanged" in scene.meta["normal_convention"]
    json.dumps(scene.meta)


def test_opengl_normals_are_converted(tmp_path, rig):
    opengl = _opencv_normals() * np.array([1.0, -1.0, -1.0])
    scene = load_dir_object(_make_basic(tmp_path / "B", normals=opengl), rig)
    assert np.allclose(scene.normal[scene.mask], _opencv_normals()[scene.mask], atol=1e-6)
    assert bool((scene.normal[scene.mask][:, 2] < 0).all())
    assert "y and z negated" in scene.meta["normal_convention"]


def test_pms_layout(pms_folder, rig):
    scene = load_dir_object(pms_folder, rig)
    assert scene.meta["layout"] == "DIR-pms"
    for file_index in (0, 7, 16, 143):
        row, col = divmod(file_index, 16)
        # No black capture in this layout: nothing is subtracted.
        expected_red = (BLACK_LEVEL + file_index + 1) / 255.0
        assert np.allclose(scene.olat[row * 16 + 15 - col, ..., 0], expected_red, atol=1e-7)
    assert np.allclose(scene.normal[scene.mask], _opencv_normals()[scene.mask], atol=1e-6)
    assert scene.depth is None
    assert np.array_equal(scene.mask, _object_mask())


def test_downsampling_averages_blocks(basic_folder, rig):
    full = load_dir_object(basic_folder, rig)
    small_rig = load_rig().with_resolution(HEIGHT, WIDTH)
    half = load_dir_object(basic_folder, small_rig, downsample=2)
    assert half.olat.shape == (NUM_FILES, HEIGHT // 2, WIDTH // 2, 3)
    block = full.olat[:, 2:4, 4:6].mean(axis=(1, 2))
    assert np.allclose(half.olat[:, 1, 2], block, atol=1e-6)
    # A block touching the masked-out first row / column leaves the mask.
    assert not half.mask[0, :].any() and not half.mask[:, 0].any() and half.mask[1:, 1:].all()
    assert np.allclose(np.linalg.norm(half.normal[half.mask], axis=-1), 1.0, atol=1e-6)
    assert np.allclose(half.K_cam, small_rig.with_resolution(HEIGHT // 2, WIDTH // 2).camera.matrix())
    with pytest.raises(InputError, match="divisible"):
        load_dir_object(basic_folder, rig, downsample=4)


def test_missing_ground_truth_pixels_leave_the_mask(tmp_path, rig):
    normals = _opencv_normals()
    normals[3, 3] = np.nan
    depth = np.full((HEIGHT, WIDTH), 500.0)  # millimetres
    depth[2, 5] = 0.0
    scene = load_dir_object(_make_basic(tmp_path / "C", normals=normals, depth=depth), rig)
    assert not scene.mask[3, 3] and not scene.mask[2, 5]
    assert scene.meta["mask_dropped_pixels"] == 2
    assert np.allclose(scene.depth[scene.mask], 0.5)
    assert "millimetres" in scene.meta["depth_units"]
    assert np.isfinite(scene.normal).all()


def test_ground_truth_that_cannot_be_right_is_refused_or_warned(tmp_path, rig):
    """A colour-encoded normal map was renormalised into normals ~36 deg off; ground truth missing at
    every mask pixel was reported as an empty mask; depths in centimetres became 5 cm away."""
    with pytest.raises(InputError, match="most ground-truth normals .* not unit vectors .* decode a colour-encoded normal map"):
        load_dir_object(_make_basic(tmp_path / "colour", normals=(_opencv_normals() + 1) / 2), rig)
    odd = _opencv_normals()
    odd[3, 3] *= 0.5  # one pixel off (e.g. interpolated at an edge): it leaves the mask, the object loads
    scene = load_dir_object(_make_basic(tmp_path / "odd", normals=odd), rig)
    assert not scene.mask[3, 3] and scene.meta["non_unit_normals_dropped"] == 1
    scattered = _opencv_normals()
    scattered[1::2, 1::2] = 0.0  # every 2 x 2 block loses a pixel: nothing left at downsample 2
    with pytest.raises(InputError, match="no 2 x 2 block of mask.png has usable ground truth"):
        load_dir_object(_make_basic(tmp_path / "scattered", normals=scattered), rig, downsample=2)
    empty = _make_basic(tmp_path / "empty")
    _save_png(empty / "mask.png", np.zeros((HEIGHT, WIDTH), dtype=np.uint8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no NaN median warning before the one error
        with pytest.raises(InputError, match="mask selects no pixels"):
            load_dir_object(empty, rig)
    with pytest.raises(InputError, match="none of the .* pixels of mask.png has usable ground truth"):
        load_dir_object(_make_basic(tmp_path / "zeros", normals=np.zeros((HEIGHT, WIDTH, 3))), rig)
    with pytest.warns(DisplexWarning, match=r"median depth is 0.05 m .* outside 0.125..2 m .* another unit"):
        load_dir_object(_make_basic(tmp_path / "cm", depth=np.full((HEIGHT, WIDTH), 50.0)), rig)


def test_missing_files_raise_clear_errors(tmp_path, rig):
    folder = _make_basic(tmp_path / "D")
    (folder / "main" / "diffuseNspecular" / "077.png").unlink()
    with pytest.raises(InputError, match="077.png"):
        load_dir_object(folder, rig)
    folder = _make_basic(tmp_path / "E")
    (folder / "main" / "diffuseNspecular" / "black.png").unlink()
    with pytest.raises(InputError, match="black.png"):
        load_dir_object(folder, rig)
    folder = _make_basic(tmp_path / "F")
    (folder / "mask.png").unlink()
    with pytest.raises(InputError, match="mask.png"):
        load_dir_object(folder, rig)
    folder = _make_pms(tmp_path / "G")
    (folder / "light_intensities.txt").unlink()
    with pytest.raises(InputError, match="light_intensities.txt"):
        load_dir_object(folder, rig)


def test_bad_content_raises(tmp_path, rig):
    folder = _make_basic(tmp_path / "H")
    _save_png(folder / "main" / "diffuseNspecular" / "010.png", np.zeros((HEIGHT + 1, WIDTH, 3), dtype=np.uint8))
    with pytest.raises(InputError, match="010.png"):
        load_dir_object(folder, rig)
    folder = _make_pms(tmp_path / "I")
    (folder / "filenames.txt").write_text("000.png\n001.png\n")
    with pytest.raises(InputError, match="filenames.txt"):
        load_dir_object(folder, rig)
    folder = _make_basic(tmp_path / "J")
    (folder / "main" / "diffuseNspecular" / "003.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="003.png"):
        load_dir_object(folder, rig)
    # Text in another encoding, and a truncated .mat file, raised their libraries' own errors.
    folder = _make_pms(tmp_path / "K")
    (folder / "filenames.txt").write_bytes("\n".join(f"{i:03d}é.png" for i in range(144)).encode("latin-1"))
    with pytest.raises(InputError, match="filenames.txt: not a readable list of image names"):
        load_dir_object(folder, rig)
    folder = _make_pms(tmp_path / "L")
    (folder / "Normal_gt.mat").write_bytes((folder / "Normal_gt.mat").read_bytes()[:300])
    with pytest.raises(InputError, match="Normal_gt.mat: not a readable .mat file"):
        load_dir_object(folder, rig)


def test_olat_count_must_match_the_rig(basic_folder):
    """A folder of 144 OLAT images is not read as the first 32 of a 4 x 8 rig."""
    small = load_rig("panel-55in-4x8").with_resolution(HEIGHT, WIDTH)
    with pytest.raises(InputError, match="144 numbered OLAT images, but rig panel-55in-4x8 has 4 x 8 = 32"):
        load_dir_object(basic_folder, small)


def test_sixteen_bit_colour_pngs_keep_their_low_bytes(tmp_path, rig):
    """Pillow reads 16-bit RGB PNGs as 8 bits; the loader decodes them itself (as displex writes
    them) and refuses filtered ones instead of truncating them."""
    folder = _make_basic(tmp_path / "K")
    image_dir = folder / "main" / "diffuseNspecular"
    sixteen = np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint16)
    sixteen[...] = [200, 300, 40000]
    write_png(image_dir / "000.png", sixteen)
    write_png(image_dir / "black.png", np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint16))
    scene = load_dir_object(folder, rig)
    light = dir_file_to_light(0, rig.rows, rig.cols)
    backlight = rig.backlight.reshape(-1)[light]
    step = (1 + backlight) ** rig.gamma - backlight**rig.gamma
    inside = _object_mask()
    assert np.allclose(scene.olat[light][inside], np.array([200, 300, 40000]) / 65535 / step, rtol=1e-6)
    # The same pixels with the PNG 'Sub' filter on every row (as most other writers produce).
    raw = np.concatenate([np.ones((HEIGHT, 1), np.uint8), np.zeros((HEIGHT, WIDTH * 6), np.uint8)], axis=1)
    header = struct.pack(">IIBBBBB", WIDTH, HEIGHT, 16, 2, 0, 0, 0)
    chunks = [(b"IHDR", header), (b"IDAT", zlib.compress(raw.tobytes())), (b"IEND", b"")]
    (image_dir / "000.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"".join(
        struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body)) for kind, body in chunks))
    with pytest.raises(InputError, match="000.png: PNG uses row filters.*16-bit colour PNGs must be unfiltered"):
        load_dir_object(folder, rig)


def test_camera_aspect_mismatch_raises(basic_folder):
    with pytest.raises(InputError, match="mask.png .* is 6 x 8 .* aspect ratio"):
        load_dir_object(basic_folder, load_rig())  # 512 x 612 camera, 6 x 8 images


def test_load_dataset_lists_object_folders(basic_folder, rig):
    root = basic_folder.parent
    assert dir_object_folders(root) == [basic_folder]
    scenes = load_dir_dataset(root, rig)
    assert [s.name for s in scenes] == ["A"]
    with pytest.raises(InputError, match="no DIR object folders"):
        dir_object_folders(basic_folder / "GT_geometry")
