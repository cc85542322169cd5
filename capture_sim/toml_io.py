"""Read TOML (tomllib from Python 3.11, tomli before) with a clear error for missing or bad files."""
from __future__ import annotations

import sys
from pathlib import Path

from capture_sim.errors import InputError, require_file

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


def load_toml(path: str | Path) -> dict:
    """Parse a TOML file into a dict; a missing or malformed file raises ``InputError``."""
    path = require_file(path, "TOML")
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{path}: invalid TOML: {err}") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a TOML file (not UTF-8 text)") from None
    except OSError as err:
        raise InputError(f"cannot read {path}: {err.strerror or err}") from None
