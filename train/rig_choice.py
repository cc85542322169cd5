"""Which rig a command uses, against the rigs its input files were made for.

Pattern and scene files record the rig they were made for (``meta["rig"]``). Without ``--rig`` a
command uses the default rig, and where an input names another one that default would be silently
wrong (frames exported at another display's resolution, captures simulated with another display's
gamma and sensor): such a command is refused with a line that says which rig the input needs. A
rig that is chosen but differs from an input's is used as chosen, with a warning.
"""
from __future__ import annotations

import warnings
from collections import defaultdict
from pathlib import Path

from capture_sim.array_files import read_arrays, read_meta
from capture_sim.errors import DisplexWarning, InputError
from capture_sim.rig import DEFAULT_RIG, load_rig
from capture_sim.scene import scene_paths


def recorded_rig(path: str | Path, what: str) -> str | None:
    """The rig name a pattern or scene file records in its meta, or None (a plain .npy, no meta,
    no name). A file that cannot be read gives None: the command's own loading reports it."""
    return _record(path, what)[0]


def _record(path: str | Path, what: str, keys: tuple[str, ...] = ()) -> tuple[str | None, dict]:
    """(``recorded_rig``, the arrays ``keys`` of the file), read in one pass; (None, {}) for a
    file that cannot be read."""
    try:
        contents = read_arrays(path, what, keys=("meta", *keys))
        if not isinstance(contents, dict):
            return None, {}
        name = read_meta(contents, Path(path), what).get("rig")
    except InputError:
        return None, {}
    return (name if isinstance(name, str) else None), contents


def rig_for_inputs(given: str | None, pattern_files=(), scenes=(), unchosen: str = "no --rig was given",
                   remedy: str = "pass --rig with that rig's preset name or TOML file") -> str:
    """The rig a command uses: ``given`` when not None, else ``DEFAULT_RIG``.

    Args:
        given: the rig the user chose (``--rig``, or a config's ``rig``), None when none was.
        pattern_files: pattern file paths the command reads ('olat' and None are skipped).
        scenes: scene files or folders the command reads.
        unchosen: why the default rig is used, and ``remedy`` what to do, for the message.

    Raises:
        InputError: no rig was chosen and an input records a rig other than the default.

    Warns:
        DisplexWarning: a chosen rig differs from the one a pattern file on its grid records (one
        line per recorded rig; scenes warn when they are prepared, ``rig_for_scene``).
    """
    patterns = [path for path in pattern_files if path not in (None, "olat")]
    if given is None:
        for what, path in [("pattern file", path) for path in patterns] + [("scene", path) for path in scene_paths(scenes)]:
            name = recorded_rig(path, what)
            if name not in (None, DEFAULT_RIG):
                raise InputError(f"{what} {path} was made for rig {name!r}, but the command uses the default rig {DEFAULT_RIG} "
                                 f"({unchosen}): {remedy}")
        return DEFAULT_RIG
    warn_other_rigs(load_rig(given), patterns)
    return given


def warn_other_rigs(rig, pattern_files, what: str = "pattern file") -> None:
    """Warn once per recorded rig when pattern files on ``rig``'s grid were made for another rig:
    they are shown on this rig's display, which may not be meant. Files on another grid are left
    to the command, which refuses or skips them."""
    others: dict = defaultdict(list)
    for path in pattern_files:
        name, contents = _record(path, what, ("patterns",))
        shape = getattr(contents.get("patterns"), "shape", ())
        # A file on another grid is left to the command, which refuses or skips it.
        if name is not None and name != rig.name and len(shape) == 4 and tuple(shape[1:3]) == (rig.rows, rig.cols):
            others[name].append(Path(path).name)
    for name, files in others.items():
        listed = ", ".join(files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
        plural = len(files) > 1
        warnings.warn(f"{what}{'s' if plural else ''} {listed} {'were' if plural else 'was'} made for rig {name!r}; shown on the "
                      f"display of rig {rig.name!r}, as chosen", DisplexWarning, stacklevel=3)

