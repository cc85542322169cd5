"""One error type for bad user input, and the one helper that checks tensors at public entry points.

The command line turns an ``InputError`` into a single line on stderr and exit status 2; anything
else is a bug and keeps its traceback.
"""
from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import torch


class InputError(ValueError):
    """Bad input from a user: wrong shape, non-finite data, out-of-range values, missing file."""


class DisplexWarning(UserWarning):
    """Input that is usable but probably not what the user meant; the command line prints it as
    one ``displex: warning:`` line."""


_WARNED: set = set()


def warn_once(message: str, stacklevel: int = 1) -> None:
    """Issue ``message`` as a ``DisplexWarning`` unless it was issued already since the last
    ``forget_warnings`` (each command starts afresh; a Python session until it calls that): one
    cause met again (a rig loaded twice, every scene of one set) says so once. Python's own
    once-per-place registry is not enough: any change of the warning filters, as importing scipy
    or matplotlib makes, clears it. ``stacklevel`` as ``warnings.warn``'s, counted from the caller
    of this function. A warning that a filter turns into an error is not counted as said."""
    if message not in _WARNED:
        warnings.warn(message, DisplexWarning, stacklevel=stacklevel + 1)
        _WARNED.add(message)


def forget_warnings() -> None:
    """Let ``warn_once`` issue every message again (at the start of a command)."""
    _WARNED.clear()


def one_line(text) -> str:
    """``str(text)`` with control characters escaped (a newline in a scene's meta name or a file
    name would otherwise split a one-line message or a table row): a newline becomes the two
    characters backslash and n."""
    text = str(text)
    if text.isprintable():
        return text
    return "".join(char if char.isprintable() else char.encode("unicode_escape").decode("ascii") for char in text)


MAX_SEED = 2**32 - 1
"""Largest seed accepted. Seeds derived from it (seed * 1000 + scene index and the like) stay
well inside the 64-bit range of torch's and numpy's generators."""


def require_file(path, what: str) -> Path:
    """``path`` as a Path if it names an existing regular file, else one ``InputError`` line that
    says what is wrong: missing, a folder (a common slip: a scene folder where one file goes), or
    something else (a device, a socket)."""
    path = Path(path)
    if path.is_file():
        return path
    if path.is_dir():
        raise InputError(f"{path} is a folder, not a {what} file")
    if path.exists():
        raise InputError(f"{path} is not a regular file (expected a {what} file)")
    raise InputError(f"{what} file not found: {path}")


def is_whole_number(value, low: int = 0, high: float = float("inf")) -> bool:
    """Whether ``value`` is a Python or numpy integer (not a bool) in [low, high]."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and low <= value <= high


def is_real_number(value) -> bool:
    """Whether ``value`` is a Python or numpy int or float (not a bool, a string or a tensor)
    that is not NaN."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) and not math.isnan(value)


def check_field_types(config) -> None:
    """Refuse fields of a settings dataclass whose values do not match their annotation: an
    ``int`` field must hold a whole number, a ``float`` field a real number that is not NaN (an
    int is accepted; bools never are). For configs built in code; TOML loading checks types first."""
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        annotation = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", "")
        if annotation == "int" and not is_whole_number(value, -(2**63), 2**63 - 1):
            raise InputError(f"{type(config).__name__}: {field.name} must be a whole number, got {value!r}")
        if annotation == "float" and not is_real_number(value):
            raise InputError(f"{type(config).__name__}: {field.name} must be a number, got {value!r}")


def check_seed(name: str, seed) -> int:
    """``seed`` as an int if it is a whole number in [0, MAX_SEED], else ``InputError``."""
    if not is_whole_number(seed, 0, MAX_SEED):
        raise InputError(f"{name} must be a whole number in [0, {MAX_SEED}], got {seed!r}")
    return int(seed)


MAX_THREADS = 1024
"""Largest torch thread count accepted (torch crashes on absurd thread counts instead of refusing them)."""


def check_thread_count(count) -> int:
    """``count`` as an int if it is 0 (torch's default) or 1..MAX_THREADS, else ``InputError``.

    The one range check of every thread setting: ``displex --threads`` (also accepted after
    ``invrender``; the CLI's argparse type calls it) and ``InvRenderConfig.threads`` from Python.
    """
    if not is_whole_number(count, 0, MAX_THREADS):
        raise InputError(f"thread count must be 0 (torch's default) or 1..{MAX_THREADS}, got {count!r}")
    return int(count)


def check_array(
    name: str,
    value,
    shape: Sequence[int | str | None] | None = None,
    *,
    finite: bool = True,
    value_range: tuple[float, float] | None = None,
) -> None:
    """Check a numpy array or torch tensor and raise one readable ``InputError`` if it is wrong.

    Args:
        name: what the value is, used in the message (e.g. ``"patterns"``).
        value: numpy array or torch tensor.
        shape: expected shape; an int must match exactly, a str or None matches any size
            (a str names the dimension in the message, e.g. ``("M", 9, 16, 3)``). A leading
            ``"..."`` allows any number of leading dimensions.
        finite: require every value to be finite.
        value_range: inclusive (low, high) bounds every value must respect.
    """
    if not isinstance(value, (np.ndarray, torch.Tensor)):
        raise InputError(f"{name}: expected an array, got {type(value).__name__}")
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        raise InputError(f"{name}: expected numbers, got an array of dtype {value.dtype}")
    if isinstance(value, torch.Tensor) and value.is_complex():
        raise InputError(f"{name}: expected real numbers, got a tensor of dtype {value.dtype}")
    actual = tuple(value.shape)
    if shape is not None:
        expected = tuple(shape)
        if expected and expected[0] == "...":
            expected = expected[1:]
            ok = len(actual) >= len(expected) and _dims_match(actual[len(actual) - len(expected):], expected)
        else:
            ok = len(actual) == len(expected) and _dims_match(actual, expected)
        if not ok:
            wanted = "(" + ", ".join("..." if d == "..." else str(d) for d in shape) + ")"
            raise InputError(f"{name}: expected shape {wanted}, got {actual}")
    is_tensor = isinstance(value, torch.Tensor)
    if is_tensor:
        value = value.detach()
    if value.dtype in (torch.bool, np.bool_) or (value.numel() if is_tensor else value.size) == 0:
        return
    # A tensor's minimum and maximum in one pass serve both checks (NaN and infinities reach them).
    bounds = tuple(float(bound) for bound in torch.aminmax(value)) if is_tensor and (finite or value_range is not None) else None
    if finite and not (all(map(math.isfinite, bounds)) if is_tensor else bool(np.isfinite(value).all())):
        raise InputError(f"{name}: contains NaN or infinite values")
    if value_range is not None:
        low, high = value_range
        vmin, vmax = bounds if is_tensor else (float(value.min()), float(value.max()))
        if vmin < low or vmax > high:
            # repr: the shortest text that reads back as the same float, so a value a rounding step
            # outside a bound (float32 or float64) never prints as the bound itself.
            raise InputError(f"{name}: values must lie in [{low:g}, {high:g}], found [{vmin!r}, {vmax!r}]")


def all_finite(values: torch.Tensor) -> bool:
    """Whether every value of a tensor (any shape; empty: True) is finite, from its minimum and
    maximum, which NaN and infinities reach: one pass with no temporaries, where
    ``torch.isfinite(values).all()`` costs ~5 ns a value (6.7 ms on a training step's 1.2 M
    captures, 1.2 s on a full-resolution OLAT capture, one thread) and a bool tensor of its size."""
    if values.is_complex():  # no order: test the parts
        return all_finite(torch.view_as_real(values.detach().resolve_conj()))
    if not values.is_floating_point() or values.numel() == 0:
        return True
    low, high = torch.aminmax(values.detach())
    return math.isfinite(float(low)) and math.isfinite(float(high))


def _dims_match(actual: tuple[int, ...], expected: tuple) -> bool:
    return all(not isinstance(e, int) or a == e for a, e in zip(actual, expected))
