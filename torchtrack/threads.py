"""The number of torch intra-op threads, set for the length of a block, and chosen per workload.

The workloads differ: the detector's convolutions are large and split well over threads, while the trackers
and filters (Kalman, IMM, particle, GM-PHD, GLMB, PMB) step tensors of tens to thousands of elements, where
each op split over threads costs an OpenMP fork and join and threads that wait on each other — more than the
op itself. So the trackers run on :data:`TRACKER_THREADS` by default whatever the detector is given: the
pipeline (``torchtrack track``, ``demo``) switches to them around each tracker step
(``PipelineConfig.tracker_threads``) and the trackers' and filters' benches default to them.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from torchtrack.errors import TorchtrackError

TRACKER_THREADS = 1
"""Intra-op threads of the small-tensor workloads (the trackers and the filters' benches) by default."""


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
    if n is not None and n != previous:  # set only to change it: setting also clears oneDNN's primitive cache
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if torch.get_num_threads() != previous:
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
