"""Atomic file writes: write to a temporary file in the target folder, then rename over the target."""
from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from capture_sim.errors import InputError, warn_once


def refuse_overwriting(outputs, inputs, folders=()) -> None:
    """Raise ``InputError`` if an output file would replace an input file or another output, if
    an output path holds something other than a regular file (``check_replaceable``), if it is
    one of the command's output folders or would have to hold one, or if no file can be created
    in its folder: commands call this before their work, so that such an output fails at once,
    not after it.

    Args:
        outputs: (what, path or None) pairs of files a command will write.
        inputs: (what, path or None) pairs of files it reads (folders are ignored).
        folders: (what, path or None) pairs of folders it writes into, created if missing (e.g.
            ``--out`` of evaluate, ``--logdir``); files inside them are fine.
    """
    seen: dict = {}
    for what, path in inputs:
        if path is not None and Path(path).is_file():
            seen.setdefault(Path(path).resolve(), what)
    for what, folder in folders:
        if folder is not None:
            check_folder_place(Path(folder), f"cannot write {what} {folder}")
    refuse_folder_clashes(outputs, folders)
    probed: set = set()
    for what, path in outputs:
        if path is None:
            continue
        check_replaceable(path)
        resolved = Path(path).resolve()
        if resolved in seen:
            raise InputError(f"{what} {path} is also the {seen[resolved]}: writing it would destroy that file")
        seen[resolved] = what
        _check_writable(Path(path), probed)


def refuse_folder_clashes(outputs, folders) -> None:
    """Raise ``InputError`` if an output file (``outputs``: (what, path or None) pairs) is one of
    the output folders (``folders``: the same pairs) or would have to hold one."""
    places = [(what, folder, Path(folder).resolve()) for what, folder in folders if folder is not None]
    for what, path in outputs:
        if path is None:
            continue
        resolved = Path(path).resolve()
        for folder_what, folder, place in places:
            if place == resolved:
                raise InputError(f"{what} {path} is also the {folder_what} folder: give them different names")
            if resolved in place.parents:
                raise InputError(f"{what} {path} would have to be a folder to hold the {folder_what} folder {folder}: give them different names")


def _check_writable(path: Path, probed: set) -> None:
    """Raise ``InputError`` unless a file can be created in the nearest existing folder of
    ``path`` (a read-only or pseudo file system such as /proc would otherwise fail only when the
    output is written, after the work). ``probed`` collects the folders already tried."""
    folder = _nearest_existing(path.parent)
    if folder is None or folder in probed:
        return
    probed.add(folder)
    try:
        handle, name = tempfile.mkstemp(prefix=".displex-probe.", dir=folder)
    except OSError as err:
        raise InputError(f"cannot write {path}: {err.strerror or err}") from None
    os.close(handle)
    os.unlink(name)


def separate_json(json_path: str | Path | None, out: str | Path | None, name: str) -> Path | None:
    """``json_path`` as a Path, or None when it is the file ``name`` that the output folder ``out``
    receives anyway: the same document, not a second output to check or write."""
    if json_path is None or (out is not None and Path(json_path).resolve() == (Path(out) / name).resolve()):
        return None
    return Path(json_path)


def check_replaceable(path: str | Path) -> None:
    """Raise ``InputError`` if ``path`` names a folder ('.', '/', 'x/..') or exists and is not a
    regular file (a rename would silently replace a device, FIFO or socket, e.g. /dev/null run as
    root, and a folder would fail with the temporary file's name), or if a file stands where one of
    its folders would be created."""
    path = Path(path)
    if path.name in ("", ".."):  # '.', '/', 'x/..': a folder whatever exists (and no name to stage a file under)
        raise InputError(f"cannot write {path}: it names a folder, not a file")
    if path.exists() and not path.is_file():
        raise InputError(f"cannot write {path}: it exists and is not a regular file")
    check_folder_place(path.parent, f"cannot write {path}")


def check_folder_place(folder: Path, failure: str) -> None:
    """Raise ``InputError`` (``failure``, then why) if ``folder``, or the nearest of its parents
    that exists, is not a folder: a file, or a broken symbolic link, where creating the missing
    folders would fail with a misleading 'File exists'."""
    found = _nearest_existing(folder)
    if found is None or found.is_dir():
        return
    if found.is_symlink() and not found.exists():
        raise InputError(f"{failure}: {found} is a broken symbolic link (to {os.readlink(found)})")
    raise InputError(f"{failure}: {found} is a file, not a folder")


def _nearest_existing(path: Path) -> Path | None:
    """``path`` or its nearest parent that exists; a broken symbolic link counts (it stands there)."""
    path = Path(path).absolute()
    return next((place for place in (path, *path.parents) if os.path.lexists(place)), None)


def check_output_folder(path: str | Path, command: str) -> None:
    """Raise ``InputError`` if a command's output folder ``path`` exists as a file (before any work:
    the first write into it would fail with a misleading 'not a directory')."""
    if Path(path).exists() and not Path(path).is_dir():
        raise InputError(f"--out {path} is a file; {command} writes a folder")


@contextmanager
def atomic_path(path: str | Path, suffix: str = "", sync: bool = False):
    """Yield a temporary path next to ``path``; on success it replaces ``path`` in one rename.

    ``suffix`` keeps the file ending that some writers need (e.g. ``.png`` for matplotlib).
    ``sync`` flushes the file to disk before the rename, so that after a crash ``path`` holds the
    old or the new content, never a truncated file (used for checkpoints that runs resume from;
    it costs a disk flush per file).
    """
    requested = Path(path)
    check_replaceable(requested)
    # In the physical parent folder: 'a/b/../../p.npz' needs no folder a/b (creating the parents
    # as written left a/ and a/b/ behind). The last component stays as given (a symlink there is
    # replaced, not its target).
    path = Path(os.path.realpath(requested.parent)) / requested.name
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or ".tmp", dir=path.parent)
    except OSError as err:
        # Name the path the caller asked for, not the temporary file.
        raise InputError(f"cannot write {requested}: {err.strerror or err}") from None
    os.close(handle)
    # mkstemp makes the file owner-only; give it the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield Path(tmp)
        if sync:
            with open(tmp, "rb") as written:
                os.fsync(written.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@contextmanager
def signals_held():
    """Hold SIGINT and SIGTERM back for the block (a few renames and a clean-up), then raise them
    again, SIGTERM first: an interrupt arrives after the block, never in its middle. Python
    handlers run in the main thread only, so elsewhere the block runs as is, and a signal whose
    handler was not set from Python is left alone. (Blocking the signals with ``pthread_sigmask``
    is not enough: the kernel hands a process's signal to any thread that does not block it,
    torch's included, and Python's handler then interrupts the main thread all the same.)"""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # SIGINT last: it is restored, and raised, after SIGTERM, so its KeyboardInterrupt can cut
    # neither the restoring nor the other signal short.
    numbers = [number for number in (signal.SIGTERM, signal.SIGINT) if signal.getsignal(number) is not None]
    pending: set[int] = set()
    previous = {number: signal.signal(number, lambda received, _frame: pending.add(received)) for number in numbers}
    try:
        yield
    finally:
        # Inline, not a loop or a call: a handler restored first may raise when its signal comes
        # (sys.exit on SIGTERM), and Python runs handlers between any two instructions, a
        # function's entry included; the second restore must still happen.
        restore = [(number, previous[number]) for number in numbers]
        try:
            if restore:
                signal.signal(*restore[0])
        finally:
            if len(restore) > 1:
                signal.signal(*restore[1])
        for number in numbers:
            if number in pending:
                signal.raise_signal(number)


STAGING_PREFIX = ".staging."
"""Name prefix of the temporary folders of ``staged_files``."""


@contextmanager
def staged_files(folder: str | Path, last: tuple[str, ...] = (), obsolete: list | None = None, before_moves=None):
    """Yield a temporary folder inside ``folder`` (created if needed) for the files of one command.

    When the block ends normally, every file written into it (in subfolders too) replaces its
    namesake at the same place in ``folder``, one rename each. The top-level names in ``last``
    (e.g. a manifest or an index whose presence says the folder is complete) are removed first and
    moved in after all the others, so that none ever stands over a mixture of two runs. The paths
    in ``obsolete`` (an earlier run's files this one does not replace; the block may still add to
    the list) are removed after the others move in and before the ``last`` ones: until then the
    earlier run is whole, and once ``last`` stands the folder holds this run alone. When the
    block raises, the files are discarded, and so are the folders it created (``folder`` and any
    missing parents) if they are empty. A command that writes many files during long work thus
    leaves all of them or none: never new files of some scenes beside an earlier run's results.
    Callers check the final paths first (``refuse_overwriting``) where they know them before the
    work; a folder standing where a file goes is refused here anyway, before anything moves.
    ``before_moves`` (no arguments) is called once those checks pass, right before the first move
    (e.g. to mark the folder as being replaced).
    """
    folder = Path(folder)
    check_folder_place(folder, f"cannot write into {folder}")
    created = _missing_folders(folder)
    # A killed command (SIGKILL, power loss) cannot clean up; one still running may be writing.
    leftovers = sorted(path.name for path in folder.glob(f"{STAGING_PREFIX}*") if path.is_dir()) if folder.is_dir() else []
    if leftovers:
        warn_once(f"{folder} holds {len(leftovers)} staging folder(s) of an interrupted command ({', '.join(leftovers[:3])}"
                  f"{', ...' if len(leftovers) > 3 else ''}): delete them unless a displex command is writing into {folder} now")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=folder))
    except OSError as err:
        raise InputError(f"cannot write into {folder}: {err.strerror or err}") from None
    try:
        yield staging
        files = sorted(path.relative_to(staging) for path in staging.rglob("*") if not path.is_dir())
        # A folder (or device) where a file goes would stop the moves half-way: refused before any.
        for path in [folder / relative for relative in files] + list(obsolete or ()):
            if not Path(path).is_symlink():  # a rename replaces a link itself, whatever it points to
                check_replaceable(path)
        if before_moves is not None:
            before_moves()

        def move(relatives) -> None:
            for relative in relatives:
                (folder / relative).parent.mkdir(parents=True, exist_ok=True)
                os.replace(staging / relative, folder / relative)

        with signals_held():  # Ctrl-C in the middle would leave a mixture of two runs (or a staging folder)
            for name in last:
                (folder / name).unlink(missing_ok=True)
            move(relative for relative in files if relative.parts[0] not in last)
            for path in obsolete or ():
                Path(path).unlink(missing_ok=True)
            move(relative for relative in files if relative.parts[0] in last)
            shutil.rmtree(staging, ignore_errors=True)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        _remove_empty(created)
        raise


def _missing_folders(folder: Path) -> list[Path]:
    """``folder`` and those of its parents that do not exist, deepest first."""
    return [path for path in (folder, *folder.parents) if not os.path.lexists(path)]


def _remove_empty(folders: list[Path]) -> None:
    """Remove the folders (deepest first) that are still empty: a refused or failed command
    leaves no empty folders that it created."""
    for path in folders:
        with contextlib.suppress(OSError):
            path.rmdir()  # only if nothing else was put there meanwhile


@contextmanager
def exclusive_output(path: str | Path, command: str):
    """Hold an exclusive lock on the output ``path`` for the block: a second run writing the same
    output at the same time (whose checkpoint or files would silently replace this one's) fails at
    once with ``InputError``. The lock is the hidden file ``.<stem>.lock`` beside ``path``, locked
    with ``flock`` (released by the system if the process dies, so never stale) and removed at the
    end: named by the stem, as the side files of a command's output are (``a.ckpt.pt`` and
    ``a.config.json`` of ``a.npz``), so that ``a.npz`` and ``a.NPZ`` share it. Where ``fcntl``
    does not exist (Windows) the block runs unlocked."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    path = Path(path)
    lock_path = path.with_name(f".{path.stem}.lock")
    check_replaceable(lock_path)
    created = _missing_folders(lock_path.parent)
    while True:
        try:
            lock_path.parent.mkdir(parents=True, exist_ok=True)
            handle = open(lock_path, "a")
        except OSError as err:
            _remove_empty(created)
            raise InputError(f"cannot write {lock_path}: {err.strerror or err}") from None
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            raise InputError(f"another {command} is writing {path} right now; wait for it or choose another output") from None
        if locks_current_file(handle, lock_path):
            break
        # The run that held it removed the file between our open and our lock: the lock is on a
        # file nobody else will open, so a third run could lock a new one. Lock that one instead.
        handle.close()
    with handle:
        try:
            yield
        except BaseException:
            lock_path.unlink(missing_ok=True)
            _remove_empty(created)  # e.g. a run refused after the lock: no empty output folder
            raise
        lock_path.unlink(missing_ok=True)


def locks_current_file(handle, lock_path: Path) -> bool:
    """Whether the open file ``handle`` is still the file at ``lock_path`` (not removed since)."""
    try:
        return os.stat(lock_path).st_ino == os.fstat(handle.fileno()).st_ino
    except FileNotFoundError:
        return False


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    write_bytes(path, text.encode("utf-8"))


def strict_json(obj, **options) -> str:
    """``json.dumps(obj, **options)`` with every NaN or infinite float (in nested dicts, lists and
    tuples) written as null: JSON has no token for them, and Python's NaN and Infinity make the
    file unreadable to other parsers (jq, JavaScript)."""
    return json.dumps(_finite_or_null(obj), allow_nan=False, **options)


def _finite_or_null(value):
    if isinstance(value, np.generic) or (isinstance(value, np.ndarray) and value.ndim == 0):
        value = value.item()  # numpy numbers (np.float32, np.int64, np.bool_, 0-d arrays) as Python's
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key.item() if isinstance(key, np.generic) else key: _finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(item) for item in value]
    return value


def write_json(path: str | Path, obj) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically (``strict_json``: NaN and infinities
    as null)."""
    write_text(path, strict_json(obj, indent=2) + "\n")


def save_npy(path: str | Path, array: np.ndarray) -> None:
    """Save one array as .npy atomically."""
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, array)


def save_npz(path: str | Path, compressed: bool = False, **arrays) -> None:
    """Save arrays as .npz atomically (written straight to the temporary file: no in-memory copy)."""
    with atomic_path(path, suffix=".npz") as tmp:
        (np.savez_compressed if compressed else np.savez)(tmp, **arrays)
