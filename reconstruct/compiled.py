"""What the solvers' compiled (numba) kernels share: how they are compiled, and which to run.

Threads: numba's OpenMP layer shares the CPU with torch's. A process forked after parallel kernels
ran may not start OpenMP threads again (GNU OpenMP aborts it: compare's evaluation workers are
forked), so forked processes must run serial kernels (``forked``). Parallel kernels run on
torch's thread count (``--threads``), set by ``match_torch_threads``.

Caching: compiled code is cached on disk beside the source (or in ``NUMBA_CACHE_DIR``), a few
seconds on first use per dtype. Numba's cache tells kernels apart by function, not by options:
a function compiled both ways is cached in one of them only (``compile_kernel``'s ``cache``).
Where no cache folder is writable every kernel is compiled in each process that uses it.
"""
from __future__ import annotations

import os

import numba
import torch


def compile_kernel(function, parallel: bool, cache: bool | None = None):
    """``function`` compiled lazily (on its first call) by ``numba.njit`` with IEEE division
    (``error_model="numpy"``: Python's model tests every divisor in order to raise); cached on
    disk if ``cache`` (default: ``parallel``) and a cache folder is writable."""
    options = dict(parallel=parallel, error_model="numpy")
    if parallel if cache is None else cache:
        try:
            return numba.njit(cache=True, **options)(function)
        except RuntimeError as error:  # no writable cache folder (beside the source or the user's)
            if "cannot cache" not in str(error):
                raise
    return numba.njit(**options)(function)


_FORKED = False


def _mark_forked() -> None:
    global _FORKED
    _FORKED = True


os.register_at_fork(after_in_child=_mark_forked)


def forked() -> bool:
    """True in a process forked from another (run serial kernels there: module docstring)."""
    return _FORKED


def match_torch_threads() -> None:
    """Run numba's parallel loops on torch's thread count (at most numba's own limit)."""
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))
