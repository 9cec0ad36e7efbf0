"""Small device-array operations the surface stages need beyond ``engine.backend.Backend``'s primitives, written
once on top of them: an array's element type, a clone, an index range, a deterministic float64 sum, and the
backend a Warp device or a device spec means."""

from __future__ import annotations

from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, Backend, DType
from engine.backend.select import backend_of, get_backend

SUM_RUNS = 1024  # runs of a float64 sum (each summed in order by one thread; the host adds the runs in order)

__all__ = ["backend_of", "clone", "dtype_of", "get_backend", "sum_f64"]


def dtype_of(arr: Any) -> DType:
    """The element type of a device array, as the backend interface names it (a numpy dtype, VEC3F or VEC3I)."""
    if getattr(arr, "backend", None) is not None:  # an OpenCL array
        return arr.dtype
    import warp as wp

    if arr.dtype == wp.vec3:
        return VEC3F
    if arr.dtype == wp.vec3i:
        return VEC3I
    return np.dtype(wp.dtype_to_numpy(arr.dtype))


def clone(bk: Backend, arr: Any) -> Any:
    """A copy of a device array on its backend."""
    out = bk.empty(tuple(arr.shape), dtype_of(arr))
    if len(arr):
        bk.copy(out, arr)
    return out


def sum_f64(bk: Backend, values: Any, n: int, runs: Any = None) -> float:
    """The sum of the first ``n`` float64 ``values``, the same bits on every backend and run: runs summed in order
    on the device (``measures.run_sums``), their sums added in order on the host (a sync point). ``runs``: a
    float64 scratch array of at least ``SUM_RUNS`` elements to reuse."""
    from engine.surface import kernel_specs as k

    if n <= 0:
        return 0.0
    count = min(SUM_RUNS, n)
    run = -(-n // count)
    count = -(-n // run)
    runs = runs if runs is not None else bk.empty(count, np.float64)
    bk.launch(k.RUN_SUMS, count, [values, n, run, runs])
    total = 0.0
    for x in bk.to_host(runs, count).tolist():
        total += x
    return total
