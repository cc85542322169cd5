"""Run a block of work on a set number of torch intra-op threads, restoring the number afterwards."""
from __future__ import annotations

from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(count: int):
    """Run the block on ``count`` torch threads (0: leave the current number), then restore the
    previous number, also when the block raises: commands run in-process (tests, ``compare``) must
    not change the caller's setting."""
    previous = torch.get_num_threads()
    torch.set_num_threads(count or previous)
    try:
        yield torch.get_num_threads()
    finally:
        torch.set_num_threads(previous)
