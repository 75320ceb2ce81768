"""Keep freed tensor memory for reuse on the CPU (glibc's allocator).

glibc serves every allocation above its mmap threshold (which it adapts, but never past 32 MB)
with fresh pages from the kernel and unmaps them when freed. A training step whose activations are
larger page-faults them in again on every step: about 30% of a discovery step's CPU time at the
default sizes (measured on one thread, see docs/RESULTS.md). Raising the threshold keeps those
blocks on the heap, where the next step reuses them.
"""

import ctypes
import platform

import torch

M_TRIM_THRESHOLD = -1  # mallopt parameters, from glibc's malloc.h
M_MMAP_THRESHOLD = -3
KEEP_BYTES = 1 << 30


def reuse_freed_memory(device: torch.device) -> bool:
    """For training on `device`: serve allocations up to 1 GiB from the heap and keep up to 1 GiB
    of freed memory there.

    Process-wide; returns False, changing nothing, for an accelerator (its tensors do not come from
    the C heap) or where the C library is not glibc.
    """
    if device.type != "cpu" or platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    mallopt = ctypes.CDLL(None).mallopt
    return bool(mallopt(M_MMAP_THRESHOLD, KEEP_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, KEEP_BYTES))
