"""Export pattern sets as display frames for the rig, with a manifest, and import them back.

A frame is the image the display shows full-screen at its native resolution ``rig.panel_pixels``
(height, width): every superpixel is a block of display pixels holding the pattern's set value P
(before the display gamma; no gamma or colour management is applied), quantised to 8 or 16 bits.
Block boundaries are integers: superpixel i of N along an axis of S pixels covers pixels
[b_i, b_{i+1}) with b_i = floor(i * S / N + 1/2), so an exact multiple (2160 / 9 = 3840 / 16 = 240)
gives equal blocks.

Frame columns are mirrored when the rig says so. The display faces the object, so a viewer at the
object sees camera +x on their left: the frame's left edge (display pixel column 0) shows the
superpixel column with the largest camera x. On every preset (light_positions x grows with the
column index c) frame block j therefore shows pattern column C - 1 - j; ``columns_mirrored`` derives
this from the rig's calibration and the manifest records it. Rows are never flipped (row 0 is the top).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from capture_sim.atomic import check_folder_place, check_replaceable, staged_files, write_bytes, write_json
from capture_sim.errors import InputError, check_array, is_whole_number
from capture_sim.png import encode_png, png_header, read_png
from capture_sim.rig import Rig, panel_size
from patterns.contact_sheet import save_contact_sheet
from patterns.io import check_patterns_match_rig, validate_patterns

MANIFEST_NAME = "manifest.json"
EXPORT_MARKER = ".displex-export-in-progress"
"""Written when an export starts and removed when its manifest is written: a folder holding it
was written by an interrupted export, so its frame files may be replaced."""
CONTACT_SHEET_NAME = "contact_sheet.png"
FORMAT = "displex-frames/1"
FRAME_GLOBS = ("pattern_*.png", "olat_*.png", "black.png", "white.png")
"""Names of the frame files an export writes (and removes from an earlier export)."""
_BIT_DEPTHS = (8, 16)


def superpixel_boundaries(count: int, pixels: int) -> np.ndarray:
    """(count + 1,) int64 pixel boundaries b_i = floor(i * pixels / count + 1/2) along one axis."""
    if count < 1 or pixels < count:
        raise InputError(f"cannot split {pixels} display pixels into {count} superpixels")
    i = np.arange(count + 1, dtype=np.int64)
    return (2 * i * pixels + count) // (2 * count)


def columns_mirrored(rig: Rig) -> bool:
    """Whether frame column blocks run opposite to the pattern's columns (see the module docstring).

    True when the rig's last superpixel column lies at larger camera x than its first: seen from the
    object, that column is on the left, where the frame starts.
    """
    x = rig.light_positions[..., 0]
    return bool(x[:, -1].mean() > x[:, 0].mean())


def render_frame(
    pattern: np.ndarray, panel_pixels: tuple[int, int], bit_depth: int = 8, mirrored: bool = True
) -> np.ndarray:
    """One display frame of a pattern.

    Args:
        pattern: (R, C, 3) display set values in [0, 1].
        panel_pixels: (height, width) of the display in pixels.
        bit_depth: 8 or 16 bits per channel.
        mirrored: frame column block j shows pattern column C - 1 - j (``columns_mirrored``).

    Returns:
        (height, width, 3) uint8 or uint16 frame: round(P * (2**bit_depth - 1)) per block.
    """
    _check_bit_depth(bit_depth, "bit depth")
    check_array("pattern", pattern, ("R", "C", 3), value_range=(0.0, 1.0))
    rows, cols, _ = pattern.shape
    height, width = panel_size(panel_pixels)
    row_sizes = np.diff(superpixel_boundaries(rows, height))
    col_sizes = np.diff(superpixel_boundaries(cols, width))
    levels = 2**bit_depth - 1
    quantised = np.round(np.asarray(pattern, dtype=np.float64) * levels).astype(np.uint8 if bit_depth == 8 else np.uint16)
    if mirrored:
        quantised = quantised[:, ::-1]
    return np.repeat(np.repeat(quantised, row_sizes, axis=0), col_sizes, axis=1)


def _exported_files(manifest_path: Path) -> set[str] | None:
    """The frame files listed by ``manifest_path`` if ``export_frames`` wrote it (its format tag),
    else None (missing, unreadable, not JSON, another format)."""
    try:
        manifest = json.loads(manifest_path.read_text())
        if manifest.get("format") != FORMAT:
            return None
        # The frames as import_frames reads them (capture_order, optional there, restates them).
        return {frame.get("file") for frame in manifest.get("frames", []) if isinstance(frame, dict)}
    except (OSError, ValueError, AttributeError, TypeError, RecursionError):  # RecursionError: absurdly nested JSON
        return None


def replaced_by_export(path: str | Path, out_dir: str | Path) -> bool:
    """Whether an export into ``out_dir`` would replace or remove the file ``path`` (a frame name,
    the manifest or the contact sheet in that folder): a command's input must not be one."""
    path = Path(path).resolve()
    names = (MANIFEST_NAME, CONTACT_SHEET_NAME, EXPORT_MARKER)
    return path.parent == Path(out_dir).resolve() and (path.name in names or any(path.match(glob) for glob in FRAME_GLOBS))


def export_frames(
    patterns,
    rig: Rig,
    out_dir: str | Path,
    bit_depth: int = 8,
    include_olat: bool = False,
    rig_name: str | None = None,
    compression_level: int = 2,
) -> dict:
    """Write display frames, a contact sheet and ``manifest.json`` for a pattern set.

    Files (in ``out_dir``): ``pattern_000.png`` ... one per pattern in capture order; with
    ``include_olat`` also ``black.png`` (all 0), ``white.png`` (all full value) and ``olat_000.png``
    ... ``olat_{K-1}.png`` (superpixel k = r * C + c at full value, the rest 0), captured after the
    patterns in that order; ``contact_sheet.png``; ``manifest.json`` last, so a folder with a
    manifest is complete.

    Args:
        patterns: (M, R, C, 3) display set values in [0, 1] on the rig's R x C grid.
        rig: the rig (grid, ``panel_pixels``, gamma, exposure).
        out_dir: output folder (created if needed).
        bit_depth: 8 (default) or 16 bits per channel.
        include_olat: also write the black, white and OLAT frames.
        rig_name: name recorded in the manifest (default ``rig.name``).
        compression_level: zlib level 0..9 for the PNG files.

    Returns:
        The manifest dict, as written: format, rig, rows, cols, num_patterns, panel_pixels,
        row_boundaries and col_boundaries (display pixels, in frame order), columns_mirrored,
        bit_depth, value_encoding, exposure (number or "auto"), gamma, capture_order (file names),
        frames (per file: file, kind, index/light/row/col, sha256), patterns (nested lists, M x R x
        C x 3), contact_sheet.
    """
    values = validate_patterns(patterns)
    check_patterns_match_rig(values, rig.rows, rig.cols, rig.name)
    _check_bit_depth(bit_depth, "bit depth")
    if not is_whole_number(compression_level, 0, 9):
        raise InputError(f"PNG compression level must be a whole number 0..9, got {compression_level!r}")
    if rig.panel_pixels is None:
        raise InputError(f"rig {rig.name} gives no display panel_pixels: export needs the panel's native resolution "
                         "([display] panel_pixels = [height, width] in the rig file)")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"export folder is a file: {out_dir}")
    height, width = rig.panel_pixels  # checked when the rig was made
    row_bounds = superpixel_boundaries(rig.rows, height)
    col_bounds = superpixel_boundaries(rig.cols, width)
    mirrored = columns_mirrored(rig)
    # Frames of an earlier export (more patterns, or OLAT frames) would be played too: they are
    # removed, but only from a folder an export wrote (its manifest, listing every frame there, or
    # the marker of an export interrupted while replacing files); other files with such names are
    # the user's.
    marker = out_dir / EXPORT_MARKER
    manifest_path = out_dir / MANIFEST_NAME
    exported = _exported_files(manifest_path)
    ours = marker.exists() or exported is not None
    if not ours and manifest_path.exists():
        raise InputError(f"{manifest_path} was not written by displex export: not an export folder; choose another folder")
    if exported is not None and not marker.exists():
        unlisted = sorted(path.name for pattern_glob in FRAME_GLOBS for path in out_dir.glob(pattern_glob) if path.name not in exported)
        if unlisted:
            raise InputError(f"{out_dir} holds frame files its {MANIFEST_NAME} does not list ({', '.join(unlisted[:3])}"
                             f"{', ...' if len(unlisted) > 3 else ''}): they are not the export's; move them or choose another folder")
    if not ours and any(any(out_dir.glob(pattern_glob)) for pattern_glob in (*FRAME_GLOBS, CONTACT_SHEET_NAME)):
        raise InputError(f"{out_dir} holds frame files (pattern_*.png, olat_*.png, contact_sheet.png, ...) but no {MANIFEST_NAME}: "
                         "not an export folder; choose another folder or remove them")

    check_folder_place(out_dir, f"cannot write into {out_dir}")
    for path in (marker, manifest_path, out_dir / CONTACT_SHEET_NAME):  # a folder there fails now, not after the frames
        check_replaceable(path)
    # Everything is written into a staging folder first and moves in at the end (the manifest
    # last): an export that fails or is interrupted leaves the earlier export as it was.
    # The earlier export's frames that this one does not replace go before its manifest lands.
    obsolete: list = []
    # The earlier manifest goes first as the new files move in: the marker says whose frames these
    # are should that moment be interrupted (written once the moves are sure to start).
    with staged_files(out_dir, last=(MANIFEST_NAME,), obsolete=obsolete,
                      before_moves=lambda: write_bytes(marker, b"export in progress\n")) as staging:
        manifest = _write_export(values, rig, staging, bit_depth, include_olat, rig_name or rig.name, compression_level,
                                 (height, width), row_bounds, col_bounds, mirrored)
        obsolete += [path for pattern_glob in FRAME_GLOBS for path in out_dir.glob(pattern_glob) if not (staging / path.name).exists()]
    marker.unlink(missing_ok=True)
    return manifest


def frame_digits(num_patterns: int, num_olat_frames: int) -> int:
    """Digits of the frame numbers (``pattern_000.png``): three, or as many as more than 1000
    frames of one kind need, so that each kind's names sort in capture order (the manifest's
    ``capture_order`` gives the whole sequence: patterns, then black, white and OLAT frames)."""
    return max(3, len(str(num_patterns - 1)), len(str(num_olat_frames - 1)))


def _write_export(values, rig: Rig, folder: Path, bit_depth: int, include_olat: bool, name: str, compression_level: int,
                  panel: tuple[int, int], row_bounds, col_bounds, mirrored: bool) -> dict:
    """Write the frames, the contact sheet and the manifest of ``export_frames`` into ``folder``."""
    frames = []

    def write_frame(file_name: str, pattern: np.ndarray, **description) -> None:
        data = encode_png(render_frame(pattern, panel, bit_depth, mirrored), compression_level)
        write_bytes(folder / file_name, data)
        frames.append({"file": file_name, **description, "sha256": hashlib.sha256(data).hexdigest()})

    digits = frame_digits(len(values), rig.num_lights if include_olat else 0)
    for m, pattern in enumerate(values):
        write_frame(f"pattern_{m:0{digits}d}.png", pattern, kind="pattern", index=m)
    if include_olat:
        grid = (rig.rows, rig.cols, 3)
        write_frame("black.png", np.zeros(grid, np.float32), kind="black")
        write_frame("white.png", np.ones(grid, np.float32), kind="white")
        for light in range(rig.num_lights):
            row, col = divmod(light, rig.cols)
            one_lit = np.zeros(grid, np.float32)
            one_lit[row, col] = 1.0
            write_frame(f"olat_{light:0{digits}d}.png", one_lit, kind="olat", light=light, row=row, col=col)

    # The sheet shows the frames as the display does, so that it can be checked against the panel.
    save_contact_sheet(folder / CONTACT_SHEET_NAME, values, f"{len(values)} patterns for rig {name} (as displayed)", mirrored=mirrored)
    manifest = {
        "format": FORMAT,
        "rig": name,
        "rows": rig.rows,
        "cols": rig.cols,
        "num_patterns": len(values),
        "panel_pixels": list(panel),
        "row_boundaries": row_bounds.tolist(),
        "col_boundaries": col_bounds.tolist(),
        "columns_mirrored": mirrored,
        "bit_depth": bit_depth,
        "value_encoding": "round(P * (2**bit_depth - 1)) per superpixel block; P is the set value before the display gamma",
        "exposure": "auto" if rig.exposure is None else rig.exposure,
        "gamma": rig.gamma,
        "capture_order": [frame["file"] for frame in frames],
        "frames": frames,
        "patterns": _float32_lists(values),
        "contact_sheet": CONTACT_SHEET_NAME,
    }
    write_json(folder / MANIFEST_NAME, manifest)
    return manifest


def import_frames(frames_dir: str | Path, rig: Rig | None = None) -> tuple[np.ndarray, dict]:
    """Recover a pattern set from exported frames.

    Reads ``manifest.json``, verifies the SHA-256, size and bit depth of every frame it lists (and
    that the folder holds no other frame files) and that the frames are listed in the export's
    play order (patterns 0..M-1, black, white, the OLAT frames light by light with light =
    row x C + col), reads the pattern frames and averages the central half of every superpixel
    block (undoing the column mirroring). The black, white and OLAT frames' contents are checked
    by their SHA-256 only.

    Args:
        frames_dir: folder written by ``export_frames``.
        rig: optional rig whose grid the patterns must match.

    Returns:
        patterns: (M, R, C, 3) float32 set values in [0, 1], within half a quantisation step
            (1/510 at 8 bits) of the exported ones.
        meta: the manifest dict.
    """
    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        raise InputError(f"{frames_dir} is not a folder of exported frames ({'a file' if frames_dir.exists() else 'not found'})")
    manifest = _read_manifest(frames_dir)
    rows, cols = manifest["rows"], manifest["cols"]
    height, width = manifest["panel_pixels"]
    bit_depth = manifest["bit_depth"]
    _check_bit_depth(bit_depth, f"{frames_dir}: manifest bit_depth")
    for frame in manifest["frames"]:
        path = frames_dir / frame["file"]
        if not path.is_file():
            raise InputError(f"{frames_dir}: frame {frame['file']} listed in the manifest is missing")
        if hashlib.sha256(path.read_bytes()).hexdigest() != frame.get("sha256"):
            raise InputError(f"{frames_dir}: frame {frame['file']} does not match its SHA-256 in the manifest")
        # Every frame the rig plays, not only the pattern frames read below (a header is 26 bytes).
        found = png_header(path)
        if found != (height, width, bit_depth, _RGB):
            shown = "not a PNG" if found is None else f"{found[0]} x {found[1]} at {found[2]} bits, colour type {found[3]}"
            raise InputError(f"{frames_dir}: frame {frame['file']} is {shown}; the manifest says {height} x {width} RGB at {bit_depth} bits")
    listed_files = {frame["file"] for frame in manifest["frames"]}
    unlisted = sorted(path.name for glob in FRAME_GLOBS for path in frames_dir.glob(glob) if path.name not in listed_files)
    if unlisted:  # a rig that plays the folder's frames would show them too
        raise InputError(f"{frames_dir}: frame files not listed in the manifest: {', '.join(unlisted[:5])}"
                         f"{f' and {len(unlisted) - 5} more' if len(unlisted) > 5 else ''}; remove them or export again")
    pattern_frames = [f for f in manifest["frames"] if f["kind"] == "pattern"]  # in index order (_read_manifest)
    # The count first: a forged num_patterns of 10^12 must not build a list of that length.
    if len(pattern_frames) != manifest["num_patterns"]:
        raise InputError(f"{frames_dir}: manifest lists {len(pattern_frames)} pattern frames, but num_patterns is {manifest['num_patterns']}")
    # The listed values first: their shape must restate the grid before a frame is averaged over it.
    try:
        listed = np.asarray(manifest["patterns"])
    except ValueError:  # lists of uneven lengths
        listed = None
    if listed is None or listed.dtype.kind not in "iuf" or listed.shape != (len(pattern_frames), rows, cols, 3) or not np.isfinite(listed).all():
        raise InputError(f"{frames_dir}: manifest patterns are not a finite {len(pattern_frames)} x {rows} x {cols} x 3 array of numbers")
    row_bounds = superpixel_boundaries(rows, height)
    col_bounds = superpixel_boundaries(cols, width)
    levels = 2**bit_depth - 1
    recovered = []
    for frame in pattern_frames:
        image = read_png(frames_dir / frame["file"])
        if image.shape != (height, width, 3) or image.dtype.itemsize * 8 != bit_depth:
            raise InputError(
                f"{frames_dir}: frame {frame['file']} is {image.shape} at {image.dtype.itemsize * 8} bits, "
                f"manifest says ({height}, {width}, 3) at {bit_depth} bits"
            )
        recovered.append(_block_means(image, row_bounds, col_bounds) / levels)  # the grid is checked against a real frame first
    recovered = np.stack(recovered)
    if manifest["columns_mirrored"]:
        recovered = recovered[:, :, ::-1]
    patterns = validate_patterns(recovered, f"{frames_dir}: recovered patterns")
    if np.abs(listed - patterns).max() > 0.5 / levels + 1e-6:
        raise InputError(f"{frames_dir}: the frames do not show the pattern values listed in the manifest")
    if rig is not None:
        check_patterns_match_rig(patterns, rig.rows, rig.cols, rig.name)
    return patterns, manifest


FRAME_KINDS = {"pattern": ("index",), "black": (), "white": (), "olat": ("light", "row", "col")}
"""The manifest's frame kinds, in play order, and the whole-number fields each frame of a kind has."""

_RGB = 2
"""PNG colour type of the frames (truecolour, no alpha)."""


def _check_bit_depth(bit_depth, what: str) -> None:
    if not is_whole_number(bit_depth) or bit_depth not in _BIT_DEPTHS:
        raise InputError(f"{what} must be 8 or 16, got {bit_depth!r}")


def _read_manifest(frames_dir: Path) -> dict:
    path = frames_dir / MANIFEST_NAME
    if not path.is_file():
        raise InputError(f"no {MANIFEST_NAME} in {frames_dir} (not an exported frame folder, or an interrupted export)")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:  # RecursionError: absurdly nested JSON
        raise InputError(f"{path}: not a readable manifest ({err})") from None
    required = ("format", "rows", "cols", "num_patterns", "panel_pixels", "bit_depth", "columns_mirrored", "frames", "patterns")
    missing = [key for key in required if not isinstance(manifest, dict) or key not in manifest]
    if missing:
        raise InputError(f"{path}: manifest is missing {', '.join(missing)}")
    if manifest["format"] != FORMAT:
        raise InputError(f"{path}: unknown manifest format {manifest['format']!r} (expected {FORMAT})")
    sizes = [manifest["rows"], manifest["cols"], manifest["num_patterns"]]
    whole = all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in sizes)
    if not whole or not isinstance(manifest["frames"], list) or not isinstance(manifest["columns_mirrored"], bool):
        raise InputError(f"{path}: manifest rows, cols, num_patterns, columns_mirrored or frames are malformed")
    panel = panel_size(manifest["panel_pixels"], f"{path}: manifest panel_pixels")
    if manifest["rows"] > panel[0] or manifest["cols"] > panel[1]:
        raise InputError(f"{path}: manifest grid {manifest['rows']} x {manifest['cols']} has more superpixels than the panel's {panel[0]} x {panel[1]} pixels")
    for frame in manifest["frames"]:
        if not isinstance(frame, dict) or not isinstance(frame.get("file"), str) or Path(frame["file"]).name != frame["file"]:
            raise InputError(f"{path}: every manifest frame needs a plain file name, got {frame!r}")
        if frame.get("kind") not in FRAME_KINDS:
            raise InputError(f"{path}: frame {frame['file']} has kind {frame.get('kind')!r}, not one of {', '.join(FRAME_KINDS)}")
        for key in FRAME_KINDS[frame["kind"]]:
            if not is_whole_number(frame.get(key)):
                raise InputError(f"{path}: {frame['kind']} frame {frame['file']} has no whole-number {key}")
    # Fields that restate one another must agree: an edited manifest is not silently half-applied.
    files = [frame["file"] for frame in manifest["frames"]]
    if len(set(files)) != len(files):
        raise InputError(f"{path}: the manifest lists a frame file twice")
    if "capture_order" in manifest and manifest["capture_order"] != files:
        raise InputError(f"{path}: capture_order does not list the frames in their manifest order")
    # The frames in play order restate the export's sequence: patterns 0..M-1, then at most one
    # black and one white frame, then the OLAT frames light by light (light = row * C + col).
    # A hand-edited order or numbering would pair captures with the wrong lighting.
    rows, cols = manifest["rows"], manifest["cols"]
    kinds = [frame["kind"] for frame in manifest["frames"]]
    indices = [frame["index"] for frame in manifest["frames"] if frame["kind"] == "pattern"]
    if indices != list(range(len(indices))):
        raise InputError(f"{path}: manifest lists pattern frames {indices[:12]}{' ...' if len(indices) > 12 else ''} in play order, expected 0, 1, 2, ...")
    if kinds != sorted(kinds, key=list(FRAME_KINDS).index) or kinds.count("black") > 1 or kinds.count("white") > 1:
        raise InputError(f"{path}: frames are not in the export's play order (patterns, then one black, one white, then OLAT frames)")
    olat = [(frame["light"], frame["row"], frame["col"]) for frame in manifest["frames"] if frame["kind"] == "olat"]
    # Compared light by light, never by building the grid's list: a forged grid may be huge.
    if olat and (len(olat) != rows * cols or any(entry != (light, *divmod(light, cols)) for light, entry in enumerate(olat))):
        raise InputError(f"{path}: the OLAT frames do not list the {rows} x {cols} grid's lights 0..{rows * cols - 1} in order (light = row x {cols} + col)")
    for key, count, pixels in (("row_boundaries", manifest["rows"], panel[0]), ("col_boundaries", manifest["cols"], panel[1])):
        if key in manifest and manifest[key] != superpixel_boundaries(count, pixels).tolist():
            raise InputError(f"{path}: {key} do not split {pixels} display pixels into {count} superpixels as the export does")
    return manifest


def _block_means(image: np.ndarray, row_bounds: np.ndarray, col_bounds: np.ndarray) -> np.ndarray:
    """(R, C, 3) mean of the central half of every block, away from edges a display might blur."""
    rows, cols = len(row_bounds) - 1, len(col_bounds) - 1
    means = np.empty((rows, cols, 3), dtype=np.float64)
    row_ranges = [_central(row_bounds[i], row_bounds[i + 1]) for i in range(rows)]
    col_ranges = [_central(col_bounds[j], col_bounds[j + 1]) for j in range(cols)]
    for i, (top, bottom) in enumerate(row_ranges):
        for j, (left, right) in enumerate(col_ranges):
            means[i, j] = image[top:bottom, left:right].reshape(-1, 3).mean(axis=0)
    return means


def _central(start: int, stop: int) -> tuple[int, int]:
    margin = (stop - start) // 4
    return int(start + margin), int(stop - margin)


def _float32_lists(values: np.ndarray) -> list:
    """Nested lists of the shortest decimals that read back as the same float32 values."""
    flat = [float(str(v)) for v in values.astype(np.float32).ravel()]
    return np.asarray(flat, dtype=np.float64).reshape(values.shape).tolist()
