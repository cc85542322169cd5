"""A minimal PNG encoder and decoder for 8- and 16-bit grey or RGB images (no colour management).

Exported display frames and simulated captures need 16-bit files, which matplotlib cannot write.
The encoder writes one IDAT chunk with filter type 0 (none) on every row, which numpy builds in one
step and zlib compresses fast on flat display frames. The decoder reads what the encoder writes:
non-interlaced, filter type 0; other PNGs are refused with ``InputError``.
"""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from capture_sim.atomic import write_bytes
from capture_sim.errors import InputError, require_file

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPES = {1: 0, 3: 2}  # channels -> PNG colour type (0 grey, 2 RGB)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(image: np.ndarray, level: int = 2) -> bytes:
    """PNG bytes of an image.

    Args:
        image: (H, W) grey or (H, W, 3) RGB, uint8 or uint16 (stored as 8 or 16 bits per sample).
        level: zlib compression level 0..9 (low levels are much faster on large frames).

    Returns:
        The PNG file contents.
    """
    if not isinstance(image, np.ndarray) or image.dtype not in (np.uint8, np.uint16):
        raise InputError("PNG image must be a uint8 or uint16 numpy array")
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in _COLOUR_TYPES or image.shape[0] < 1 or image.shape[1] < 1:
        raise InputError(f"PNG image must have shape (H, W) or (H, W, 3), got {image.shape}")
    height, width, channels = image.shape
    bit_depth = 8 * image.dtype.itemsize
    samples = image.astype(">u2") if bit_depth == 16 else image
    row_bytes = samples.reshape(height, -1).view(np.uint8)
    scanlines = np.zeros((height, row_bytes.shape[1] + 1), dtype=np.uint8)  # column 0: filter type 0
    scanlines[:, 1:] = row_bytes
    header = struct.pack(">IIBBBBB", width, height, bit_depth, _COLOUR_TYPES[channels], 0, 0, 0)
    return (
        _SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(scanlines.tobytes(), level))
        + _chunk(b"IEND", b"")
    )


def decode_png(data: bytes, name: str = "PNG") -> np.ndarray:
    """Pixels of a PNG written by ``encode_png``.

    Args:
        data: PNG file contents.
        name: what the data is, for error messages (e.g. the file path).

    Returns:
        (H, W) or (H, W, 3) uint8 or uint16 array.
    """
    if not data.startswith(_SIGNATURE):
        raise InputError(f"{name}: not a PNG file")
    position = len(_SIGNATURE)
    header = None
    compressed = []
    while position + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[position : position + 8])
        body = data[position + 8 : position + 8 + length]
        crc = data[position + 8 + length : position + 12 + length]
        if len(body) != length or len(crc) != 4 or struct.unpack(">I", crc)[0] != zlib.crc32(kind + body) & 0xFFFFFFFF:
            raise InputError(f"{name}: corrupt PNG chunk {kind!r}")
        position += 12 + length
        if kind == b"IHDR":
            if length != 13:
                raise InputError(f"{name}: corrupt PNG header")
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            compressed.append(body)
        elif kind == b"IEND":
            break
    if header is None or not compressed:
        raise InputError(f"{name}: PNG has no image data")
    width, height, bit_depth, colour_type, _, _, interlace = header
    channels = {0: 1, 2: 3}.get(colour_type)
    if channels is None or bit_depth not in (8, 16) or interlace != 0:
        raise InputError(f"{name}: only non-interlaced 8/16-bit grey or RGB PNGs are supported")
    try:
        raw = zlib.decompress(b"".join(compressed))
    except zlib.error as err:
        raise InputError(f"{name}: corrupt PNG image data ({err})") from None
    row_length = 1 + width * channels * bit_depth // 8
    if len(raw) != height * row_length:
        raise InputError(f"{name}: PNG image data has the wrong size")
    scanlines = np.frombuffer(raw, dtype=np.uint8).reshape(height, row_length)
    if scanlines[:, 0].any():
        raise InputError(f"{name}: PNG uses row filters; only files written by displex (filter 0) are supported")
    samples = scanlines[:, 1:]
    if bit_depth == 16:
        samples = samples.copy().view(">u2").astype(np.uint16)
    image = samples.reshape(height, width, channels)
    return image[:, :, 0].copy() if channels == 1 else image.copy()


def png_header(path: str | Path) -> tuple[int, int, int, int] | None:
    """(height, width, bit depth, colour type) from the header of the file at ``path``, or None if
    it is not a PNG (read from its first 26 bytes only)."""
    with open(path, "rb") as file:
        start = file.read(len(_SIGNATURE) + 18)
    if len(start) < len(_SIGNATURE) + 18 or not start.startswith(_SIGNATURE) or start[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", start[16:24])
    return height, width, start[24], start[25]


def png_format(path: str | Path) -> tuple[int, int] | None:
    """(bit depth, colour type) from the header of the file at ``path``, or None if it is not a PNG."""
    header = png_header(path)
    return None if header is None else header[2:]


def write_png(path: str | Path, image: np.ndarray, level: int = 2) -> None:
    """Write ``image`` ((H, W) or (H, W, 3), uint8 or uint16) as a PNG file, atomically."""
    write_bytes(path, encode_png(image, level))


def read_png(path: str | Path) -> np.ndarray:
    """Read a PNG written by ``write_png``: (H, W) or (H, W, 3) uint8 or uint16."""
    path = require_file(path, "PNG")
    return decode_png(path.read_bytes(), str(path))
