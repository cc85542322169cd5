"""Pattern files (DESIGN section 7): ``.npz`` with ``patterns`` and a JSON ``meta``, or a plain ``.npy``.

A pattern set is P with shape (M, R, C, 3): display set values in [0, 1] before the display gamma,
row 0 at the top of the panel. Files are recognised by their contents, not their suffix.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from capture_sim.array_files import read_arrays, read_meta
from capture_sim.atomic import strict_json, write_bytes
from capture_sim.errors import InputError, check_array


def validate_patterns(patterns, name: str = "patterns") -> np.ndarray:
    """Check a pattern set and return it as a float32 numpy array.

    Args:
        patterns: (M, R, C, 3) numpy array or torch tensor of display set values in [0, 1].
        name: what the patterns are, for error messages (e.g. the file path).

    Returns:
        (M, R, C, 3) float32 numpy array (a copy for tensors, possibly shared for float32 arrays).
    """
    if isinstance(patterns, torch.Tensor):
        patterns = patterns.detach().cpu()
        patterns = (patterns.float() if patterns.dtype == torch.bfloat16 else patterns).numpy()  # numpy has no bfloat16
    if not isinstance(patterns, np.ndarray):
        raise InputError(f"{name}: expected an array of shape (M, R, C, 3), got {type(patterns).__name__}")
    if patterns.dtype.kind not in "fiub":
        raise InputError(f"{name}: expected real numbers, got dtype {patterns.dtype}")
    check_array(name, patterns, ("M", "R", "C", 3), value_range=(0.0, 1.0))
    if 0 in patterns.shape:
        raise InputError(f"{name}: expected at least one pattern of at least 1 x 1 superpixels, got shape {patterns.shape}")
    return np.ascontiguousarray(patterns, dtype=np.float32)


def check_pattern_output(path: str | Path) -> None:
    """Refuse a pattern output not named .npz: a pattern file is an .npz archive (values and
    provenance), which numpy would misread under a .npy name and image tools under a .png one."""
    if Path(path).suffix.lower() != ".npz":
        raise InputError(f"pattern files are written as .npz archives (values and provenance): name the output *.npz, got {path}")


def save_patterns(path: str | Path, patterns, meta: dict | None = None) -> None:
    """Write a pattern file (.npz) atomically.

    Args:
        path: output file, named .npz (``check_pattern_output``).
        patterns: (M, R, C, 3) display set values in [0, 1] (numpy array or torch tensor).
        meta: JSON-serialisable dict describing family, parameters, rig, how the patterns were
            made (non-finite numbers are written as null).
    """
    check_pattern_output(path)
    values = validate_patterns(patterns)
    if meta is not None and not isinstance(meta, dict):  # load_patterns would refuse the file
        raise InputError(f"pattern meta must be a dict, got {type(meta).__name__}")
    try:
        meta_json = strict_json(meta or {})
    except (TypeError, ValueError) as err:
        raise InputError(f"pattern meta must be JSON-serialisable ({err})") from None
    buffer = io.BytesIO()
    # Meta as ASCII bytes (json escapes the rest), compressed: a unicode array would take 4 bytes
    # per character, and the meta of a random family lists every value as a named parameter.
    np.savez_compressed(buffer, patterns=values, meta=np.array(meta_json.encode("ascii")))
    write_bytes(path, buffer.getvalue())


def load_patterns(path: str | Path) -> tuple[np.ndarray, dict]:
    """Read and validate a pattern file.

    Args:
        path: a .npz written by ``save_patterns`` (``patterns`` and optional ``meta``), or a plain
            .npy holding the (M, R, C, 3) array.

    Returns:
        patterns: (M, R, C, 3) float32 display set values in [0, 1].
        meta: the file's meta dict ({} for a plain .npy).
    """
    path = Path(path)
    contents = read_arrays(path, "pattern", keys=("patterns", "meta"))
    if isinstance(contents, np.ndarray):
        return validate_patterns(contents, str(path)), {}
    if "patterns" not in contents:
        raise InputError(f"{path}: pattern .npz has no 'patterns' array")
    return validate_patterns(contents["patterns"], str(path)), read_meta(contents, path, "pattern")


def names_pattern_file(text) -> bool:
    """Whether a setting such as ``TrainConfig.init`` names a pattern file (.npz or .npy) rather
    than 'auto' or a family."""
    return isinstance(text, str) and Path(text).suffix.lower() in (".npz", ".npy")  # as check_pattern_output accepts them


def check_patterns_match_rig(patterns, rows: int, cols: int, rig_name: str | None = None, source: str | Path | None = None) -> None:
    """Raise ``InputError`` unless ``patterns`` (M, R, C, 3) is on the rig's ``rows`` x ``cols``
    grid; ``rig_name`` names the rig in the message, ``source`` (e.g. the pattern file) the patterns."""
    shape = tuple(np.shape(patterns))
    if len(shape) != 4 or shape[1:3] != (rows, cols):
        rig = "the rig" if rig_name is None else f"rig {rig_name}"
        hint = "; patterns made for another rig need that rig" if len(shape) == 4 else ""
        what = "patterns" if source is None else f"patterns of {source}"
        raise InputError(f"{what} have shape {shape} but {rig}'s display grid is {rows} x {cols} (expected (M, {rows}, {cols}, 3)){hint}")
