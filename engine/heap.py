"""The C heap under a host memory bound (issue 46).

numpy's and Warp's host arrays come from the C library's ``malloc``. glibc maps a block above its threshold on its
own and unmaps it when freed, but after such a block is freed it raises the threshold to that block's size (up to
32 MiB): later blocks below it come from the heap, and the heap keeps what is freed resident until the top of it is
free. A job's stages allocate and free arrays of every size, so its resident set kept 40-100 MiB of freed memory
between stages (``benchmarks/host_memory.py``: a 384 MiB scan under a 96 MiB bound). Under a host bound, blocks of
``LARGE_BLOCK`` and more are mapped on their own (``mallopt``: a fixed threshold, which also stops the raising), and
what the heap holds free is given back between stages (``malloc_trim``). Elsewhere than glibc, nothing is done.
"""

from __future__ import annotations

import ctypes
import functools
import sys
from typing import Any

M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
LARGE_BLOCK = 1 << 20  # blocks this large and larger are mapped on their own under a host bound


@functools.cache
def _glibc() -> Any:
    """glibc's ``mallopt`` and ``malloc_trim``, or None (another C library or platform)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt.argtypes, libc.malloc_trim.argtypes = [ctypes.c_int, ctypes.c_int], [ctypes.c_size_t]
    except (OSError, AttributeError):
        return None
    return libc


def bound_heap() -> bool:
    """Map blocks of ``LARGE_BLOCK`` and more on their own, for the rest of the process (a worker with a host bound
    runs every job under it): whether it was set."""
    libc = _glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(M_MMAP_THRESHOLD, LARGE_BLOCK)) and bool(libc.mallopt(M_TRIM_THRESHOLD, LARGE_BLOCK))


def give_back() -> None:
    """Return the heap's free memory to the system (between the stages of a job under a host bound)."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)
