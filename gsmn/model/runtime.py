"""Process-level CPU settings for training and benchmarks (docs/model.md, "Speed"). Never called by the model.

glibc serves allocations above 32 MB (the ResNet's activations for a batch of 128 frames are 38-150 MB each)
with fresh mmap'ed pages and unmaps them on free, so every training step page-faults through gigabytes of
zeroed memory (the "sys" time of a training process). Keeping freed memory in the heap removes that: +35 % training
frames/s here, at the price of a process that holds its peak memory.

Several processes sharing a few cores (the test suite's workers, a dashboard beside a training run) each running
torch with a thread per core spin against each other: two tiny training runs side by side on two cores took
22-27 s each with 2 threads and 10-11 s with 1. $GSMN_MAX_THREADS caps the torch threads every gsmn process
asks for (`set_torch_threads`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4


def keep_freed_memory(trim_threshold: int = 1 << 30) -> bool:
    """Make glibc malloc never mmap and keep up to `trim_threshold` bytes of freed heap. Process-wide; call once
    at the start of a training or benchmark process. Returns False (and does nothing) off glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold))


def set_torch_threads(threads: int) -> int:
    """torch's CPU threads in this process: `threads`, at most $GSMN_MAX_THREADS where that is set (a positive
    integer; anything else is refused, naming it). Returns the count set."""
    cap = os.environ.get("GSMN_MAX_THREADS", "").strip()
    if cap:
        if not cap.isdigit() or int(cap) < 1:
            raise ValueError(f"GSMN_MAX_THREADS must be a positive integer, not {cap!r}")
        threads = min(threads, int(cap))
    import torch

    torch.set_num_threads(threads)
    return threads
