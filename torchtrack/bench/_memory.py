"""The peak memory of a block of a benchmark: CUDA's allocator peak, or the growth of the resident set."""

from __future__ import annotations

import resource
from pathlib import Path

import torch


class PeakMemory:
    """The peak memory of a block: CUDA's allocator peak on a CUDA device; on the CPU the growth of the peak
    resident set (``VmHWM``, reset through ``/proc/self/clear_refs`` where Linux allows, else ``ru_maxrss``,
    which only counts a peak above the process's earlier ones).

    After the block, ``mb`` is the growth over what the process held on entering, ``peak_mb`` the peak
    itself (CUDA: allocated tensors; CPU: the whole process's resident set, interpreter and libraries
    included), both in MiB."""

    def __init__(self, device: torch.device):
        self.device = device

    def __enter__(self) -> PeakMemory:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
        else:
            try:
                Path("/proc/self/clear_refs").write_text("5")
            except OSError:
                pass
            self.base = resident_kb("VmRSS")
        return self

    def __exit__(self, *exc) -> None:
        if self.device.type == "cuda":
            peak = torch.cuda.max_memory_allocated(self.device)
            self.mb, self.peak_mb = (peak - self.base) / 2**20, peak / 2**20
        else:
            peak = resident_kb("VmHWM")
            self.mb, self.peak_mb = max(peak - self.base, 0) / 1024, peak / 1024


def resident_kb(key: str) -> float:
    """``key`` (``VmRSS`` or ``VmHWM``) of ``/proc/self/status`` in kB (``ru_maxrss`` where there is none)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    except OSError:
        pass
    return float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
