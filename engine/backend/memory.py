"""The device memory a job used: its peak, measured (``PeakMemory``), beside the budget it planned with
(``engine.budget``).

The peak is measured from the device's memory pool (CUDA: the pool's used-memory high-water mark, reset at the
start of a job) or, on the CPU, by Warp's allocation tracker, and reported beside the budget.
"""

from __future__ import annotations

import ctypes
import re
from typing import Any

__all__ = ["PeakMemory"]


class PeakMemory:
    """The most device memory a job had in use between ``start()`` and ``peak()``, beyond what was in use before.

    CUDA: the memory pool's used-memory high-water mark (reset through the driver at ``start``; where the reset is
    not available, the process's mark, labelled ``since process start``) minus the memory in use at ``start``
    (``baseline``: e.g. a finished job's mesh still held). CPU: Warp's allocation tracker (new allocations only).
    """

    def __init__(self, device: Any) -> None:
        self.device = device
        self.how = "none"
        self.baseline = 0  # device memory already in use at ``start`` (not the job's): subtracted from the peak
        self._tracker: Any = None

    def start(self) -> PeakMemory:
        import warp as wp

        if self.device.is_cuda and self.device.is_mempool_enabled:
            wp.synchronize_device(self.device)
            self.baseline = int(wp.get_mempool_used_mem_current(self.device))
            self.how = "cuda memory pool high-water mark" if _reset_pool_high(self.device) else "since process start"
        elif not self.device.is_cuda:
            self._tracker = wp.ScopedMemoryTracker("bonemesh", print=False)
            self._tracker.__enter__()
            self._tracker.clear()
            self.how = "warp allocation tracker"
        return self

    def peak(self) -> int | None:
        import warp as wp

        if self.device.is_cuda and self.device.is_mempool_enabled:
            wp.synchronize_device(self.device)
            return int(wp.get_mempool_used_mem_high(self.device)) - self.baseline
        if self._tracker is not None:
            text: list[str] = []
            self._tracker.report_func = text.append
            self._tracker.report(max_items=0)
            m = re.search(r"Peak usage:\s*\n\s*cpu\s+([0-9.]+)\s*(\w+)", "".join(text))
            if m:  # the tracker's "MB" and "GB" are binary
                scale = {"b": 1, "bytes": 1, "kb": 1 << 10, "mb": 1 << 20, "gb": 1 << 30, "tb": 1 << 40}
                return int(float(m.group(1)) * scale.get(m.group(2).lower(), 1))
        return None

    def stop(self) -> None:
        if self._tracker is not None:
            self._tracker.__exit__(None, None, None)
            self._tracker = None


def _reset_pool_high(device: Any) -> bool:
    """Reset the device's default memory pool's used-memory high-water mark (CUDA driver API)."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
        dev = ctypes.c_int()
        pool = ctypes.c_void_p()
        if cuda.cuDeviceGet(ctypes.byref(dev), int(device.ordinal)) != 0:
            return False
        if cuda.cuDeviceGetDefaultMemPool(ctypes.byref(pool), dev) != 0:
            return False
        zero = ctypes.c_uint64(0)
        used_mem_high = 8  # CU_MEMPOOL_ATTR_USED_MEM_HIGH
        return bool(cuda.cuMemPoolSetAttribute(pool, used_mem_high, ctypes.byref(zero)) == 0)
    except (OSError, AttributeError):
        return False
