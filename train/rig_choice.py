"""Which rig a command uses when no ``--rig`` is given.

Pattern and scene files record the rig they were made for (``meta["rig"]``). Without ``--rig`` a
command uses the default rig, and where an input names another one that default would be silently
wrong: frames exported at another display's resolution, captures simulated with another display's
gamma and sensor. Such a command is refused with a line that says which rig the input needs.
"""
from __future__ import annotations

from pathlib import Path

from capture_sim.array_files import read_arrays, read_meta
from capture_sim.errors import InputError
from capture_sim.rig import DEFAULT_RIG
from capture_sim.scene import scene_paths


def recorded_rig(path: str | Path, what: str) -> str | None:
    """The rig name a pattern or scene file records in its meta, or None (a plain .npy, no meta,
    no name). A file that cannot be read gives None: the command's own loading reports it."""
    try:
        contents = read_arrays(path, what, keys=("meta",))
        if not isinstance(contents, dict):
            return None
        name = read_meta(contents, Path(path), what).get("rig")
    except InputError:
        return None
    return name if isinstance(name, str) else None


def rig_for_inputs(given: str | None, pattern_files=(), scenes=(), unchosen: str = "no --rig was given") -> str:
    """The rig a command uses: ``given`` (its ``--rig``) when not None, else ``DEFAULT_RIG``.

    Args:
        given: the ``--rig`` value, None when the flag was left out.
        pattern_files: pattern file paths the command reads ('olat' and None are skipped).
        scenes: scene files or folders the command reads.
        unchosen: why the default rig is used, for the message.

    Raises:
        InputError: no rig was given and an input records a rig other than the default.
    """
    if given is not None:
        return given
    inputs = [("pattern file", path) for path in pattern_files if path not in (None, "olat")]
    inputs += [("scene", path) for path in scene_paths(scenes)]
    for what, path in inputs:
        name = recorded_rig(path, what)
        if name not in (None, DEFAULT_RIG):
            raise InputError(f"{what} {path} was made for rig {name!r}, but the command uses the default rig {DEFAULT_RIG} "
                             f"({unchosen}): pass --rig with that rig's preset name or TOML file")
    return DEFAULT_RIG
