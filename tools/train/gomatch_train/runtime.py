"""Process setup for CPU training: thread count and the C allocator.

glibc returns large freed blocks to the OS (mmap/trim), so every step pays page faults again for its multi-MB
activation buffers; keeping them in the heap makes a training step ~15% faster on CPU (measured with
gomatch_train.bench). Does nothing where glibc's mallopt is unavailable.
"""

import ctypes
import ctypes.util

import torch

M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Ask glibc malloc to keep freed memory (no mmap for large blocks, no trimming). True when applied."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    ok = mallopt(M_MMAP_THRESHOLD, 1 << 30) == 1
    ok &= mallopt(M_TRIM_THRESHOLD, 1 << 30) == 1
    ok &= mallopt(M_TOP_PAD, 64 << 20) == 1
    return bool(ok)


def configure_cpu(threads: int) -> None:
    """Use `threads` intra-op threads (and one inter-op thread) and tune the allocator."""
    torch.set_num_threads(threads)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:
        pass  # already set, or parallel work has started; the intra-op count is what matters
    keep_freed_memory()
