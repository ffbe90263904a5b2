"""The number of torch intra-op threads, set for the length of a block."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from torchtrack.errors import TorchtrackError


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (``None``: unchanged); restore the count after. More
    threads than the machine's cores are clamped to the cores with a note on stderr: each thread costs a stack
    and the OpenMP runtime fails (or crashes) when asked for thousands."""
    if n is not None and n < 1:
        raise TorchtrackError(f"threads must be >= 1; got {n}")
    if n is not None:
        n = clamp_threads(n)
    previous = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def clamp_threads(n: int) -> int:
    """``n`` threads, or the cores this process may run on where ``n`` is more (with a note on stderr)."""
    cores = available_cores()
    if n > cores:
        print(f"note: {n} threads asked for, {cores} used (the cores this process may run on)", file=sys.stderr)
        return cores
    return n


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity where the system reports one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)
