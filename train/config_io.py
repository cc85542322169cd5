"""Frozen-dataclass configs from TOML: unknown keys are errors, values are type-checked lightly."""
from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from pathlib import Path

from capture_sim.errors import InputError
from capture_sim.rig import rig_file
from capture_sim.toml_io import load_toml
from patterns.io import names_pattern_file


def config_from_dict(cls, values: dict, source: str = "config"):
    """Build the frozen dataclass ``cls`` from ``values``; unknown keys raise ``InputError``."""
    fields = {field.name: field for field in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise InputError(f"{source}: unknown key(s) {', '.join(unknown)}; known: {', '.join(fields)}")
    required = [name for name, field in fields.items()
                if field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING]
    missing = [name for name in required if name not in values]
    if missing:
        raise InputError(f"{source}: missing key(s) {', '.join(missing)}")
    hints = typing.get_type_hints(cls)
    converted = {}
    for key, value in values.items():
        converted[key] = _checked_value(key, value, hints[key], source)
    try:
        return cls(**converted)
    except (TypeError, ValueError) as err:
        raise InputError(f"{source}: {err}") from None


_SCALARS = {int: (int,), float: (int, float), str: (str,), bool: (bool,)}


def _checked_value(key: str, value, hint, source: str):
    """``value`` converted to the field's type hint (lists become tuples), or ``InputError``.
    An optional hint (``X | None``) takes None as is and checks other values against X."""
    options = typing.get_args(hint) if isinstance(hint, types.UnionType) else ()
    if len(options) == 2 and type(None) in options:
        if value is None:
            return None
        hint = next(option for option in options if option is not type(None))
    if typing.get_origin(hint) is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"{source}: {key} must be a list, got {value!r}")
        items = typing.get_args(hint)  # (X, ...): any length; (X, Y): exactly these
        if items and items[-1] is Ellipsis:
            items = (items[0],) * len(value)
        elif items and len(value) != len(items):
            raise InputError(f"{source}: {key} must be a list of {len(items)} values, got {value!r}")
        if not items:
            return tuple(value)
        return tuple(_checked_value(f"{key}[{index}]", item, item_hint, source) for index, (item, item_hint) in enumerate(zip(value, items)))
    expected = _SCALARS.get(hint)
    # bool is an int subclass: accept it only where a bool is expected.
    if expected is not None and (not isinstance(value, expected) or (isinstance(value, bool) and hint is not bool)):
        raise InputError(f"{source}: {key} must be of type {hint.__name__}, got {value!r}")
    return value


def repository_root(config_path: Path) -> Path:
    """The folder holding the ``configs/`` folder a config file sits in (else the file's folder):
    what relative paths inside the file are relative to."""
    config_path = Path(config_path).resolve()
    for parent in config_path.parents:
        if parent.name == "configs":
            return parent.parent
    return config_path.parent


def resolve_path(path: str, root: Path) -> str:
    """``path`` made relative to ``root`` unless it is absolute (``~`` expanded)."""
    candidate = Path(path).expanduser()
    return str(candidate if candidate.is_absolute() else root / candidate)


SCENE_LIST_KEYS = ("scenes", "val_scenes", "train_scenes", "test_scenes")


def resolve_file_fields(values: dict, root: Path) -> dict:
    """``values`` of a config file (train, search, compare or its ``[learned]`` tables) with their
    file paths resolved against ``root``: the scene lists, ``init`` when it names a pattern file,
    ``rig`` when it names a TOML file (a preset name stays a name) and a non-blank ``out``. Values
    of the wrong type are left for the config's own checks to refuse."""
    values = dict(values)
    for key in SCENE_LIST_KEYS:
        if isinstance(values.get(key), list) and all(isinstance(path, str) for path in values[key]):
            values[key] = [resolve_path(path, root) for path in values[key]]
    if names_pattern_file(values.get("init")):
        values["init"] = resolve_path(values["init"], root)
    if isinstance(values.get("rig"), str) and rig_file(values["rig"]):
        values["rig"] = resolve_path(values["rig"], root)
    if isinstance(values.get("out"), str) and values["out"].strip():  # a blank one is refused as such
        values["out"] = resolve_path(values["out"], root)
    return values


def load_config(cls, path: str | Path | None, overrides: dict | None = None, flags: dict | None = None):
    """Defaults of ``cls``, updated by the TOML file at ``path`` (if any), then by non-None overrides.

    File paths inside the file are relative to the folder holding its ``configs/`` folder
    (``resolve_file_fields``), as in compare configs; those of overrides (command-line flags) to
    the working directory. ``flags`` maps override keys to the command-line flags that set them:
    an error about a value a flag set names the flag (``--steps``), not only the field."""
    values = {} if path is None else resolve_file_fields(load_toml(path), repository_root(Path(path)))
    given = {key: value for key, value in (overrides or {}).items() if value is not None}
    values.update(given)
    try:
        return config_from_dict(cls, values, source=str(path or cls.__name__))
    except InputError as err:
        # The list of known keys after an unknown-key error names every field: not a culprit.
        subject = str(err).split("; known:")[0]
        named = [flag for key, flag in (flags or {}).items() if key in given and re.search(rf"\b{key}\b", subject)]
        if not named:
            raise
        raise InputError(f"{err} (set by {', '.join(named)})") from None


def json_value(value):
    """``value`` as strict JSON can hold it: JSON has no infinity or NaN (``angle_cap_deg = inf``,
    ``restart_condition = inf``), so non-finite floats become the strings "inf", "-inf", "nan"."""
    return str(value) if isinstance(value, float) and not math.isfinite(value) else value


def config_to_dict(config) -> dict:
    """A JSON/TOML-friendly dict of a config dataclass (paths and tuples become str and lists,
    non-finite floats strings, see ``json_value``)."""
    out = {}
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if isinstance(value, Path):
            value = str(value)
        elif isinstance(value, tuple):
            value = [str(v) if isinstance(v, Path) else json_value(v) for v in value]
        out[field.name] = json_value(value)
    return out


def changed_keys(recorded, wanted: dict) -> list[str]:
    """The keys, sorted, whose values differ between a recorded config dict (``config_to_dict``
    of an earlier run; anything else counts as no record: []) and ``wanted``."""
    if not isinstance(recorded, dict):
        return []
    return sorted(key for key in set(recorded) | set(wanted) if recorded.get(key) != wanted.get(key))
