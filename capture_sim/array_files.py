"""Reading .npy and .npz array files, with one clear error for anything unreadable."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from capture_sim.errors import InputError, require_file

_NPY_MAGIC = b"\x93NUMPY"
_ZIP_MAGIC = b"PK"


def read_arrays(path: str | Path, what: str, keys=None) -> np.ndarray | dict[str, np.ndarray]:
    """Read a .npy file (one array) or a .npz file (named arrays), eagerly and without pickles.

    Args:
        path: the file; the format is told by its first bytes, not its name.
        what: what the file should be, for messages (e.g. ``"scene"``).
        keys: for a .npz, the names to read (absent ones are skipped); None reads all.

    Returns:
        The array of a .npy file, or a dict of the arrays of a .npz file.

    Raises:
        InputError: the file is missing, neither format, damaged (truncated, bad compression) or
            holds object arrays (pickles are never loaded).
    """
    path = require_file(path, what)
    try:
        with path.open("rb") as handle:
            magic = handle.read(len(_NPY_MAGIC))
        if magic.startswith(_NPY_MAGIC):
            return np.load(path, allow_pickle=False)
        if magic.startswith(_ZIP_MAGIC):
            with np.load(path, allow_pickle=False) as data:
                names = data.files if keys is None else [key for key in keys if key in data.files]
                return {name: data[name] for name in names}
    except Exception as err:
        # A damaged file fails in many ways: a truncated member (EOFError, ValueError), a broken
        # archive (BadZipFile), bad compressed data (zlib.error), a garbled array header
        # (SyntaxError, tokenize.TokenError), a header claiming a huge shape (MemoryError).
        raise InputError(f"{path}: not a readable {what} file ({type(err).__name__}: {err})") from None
    raise InputError(f"{path}: not a {what} file (its contents are neither a .npz archive nor a .npy array)")


def archive_names(path: str | Path) -> list[str]:
    """Names of the arrays in a .npz archive that ``read_arrays`` has read (without loading them)."""
    with np.load(path, allow_pickle=False) as data:
        return list(data.files)


def read_meta(arrays: dict, path: str | Path, what: str) -> dict:
    """The JSON object stored as the ``meta`` string of a .npz read by ``read_arrays`` ({} if none).

    Raises:
        InputError: ``meta`` is not JSON, or not a JSON object.
    """
    if "meta" not in arrays:
        return {}
    stored = np.asarray(arrays["meta"])
    try:
        # JSON text as a numpy unicode string, or as ASCII bytes (pattern files: a quarter the size).
        meta = json.loads(stored.item().decode("ascii") if stored.dtype.kind == "S" and stored.ndim == 0 else str(stored))
    except ValueError as err:  # UnicodeDecodeError included
        raise InputError(f"{path}: {what} meta is not JSON ({err})") from None
    except RecursionError:
        raise InputError(f"{path}: {what} meta is JSON nested too deeply to read") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path}: {what} meta must be a JSON object, got {type(meta).__name__}")
    return meta
