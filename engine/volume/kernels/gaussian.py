"""Warp kernels on volumes: separable 3-tap Gaussian smoothing (replicated borders); ``gaussian.cl`` is the OpenCL C
version, the same arithmetic."""

from __future__ import annotations

from typing import Any

import warp as wp


@wp.kernel
def gauss3_axis_kernel(
    src: wp.array3d(dtype=Any),
    dst: wp.array3d(dtype=wp.float32),
    axis: int,
    w_side: float,
    w_centre: float,
    nz: int,
    ny: int,
    nx: int,
):
    """dst = w_side * (src[i-1] + src[i+1]) + w_centre * src[i] along ``axis``, borders replicated; ``nz, ny, nx``
    is the shape (as the OpenCL kernel of ``gaussian.cl`` takes it)."""
    z, y, x = wp.tid()
    c = float(src[z, y, x])
    lo = c
    hi = c
    if axis == 0:
        lo = float(src[wp.max(z - 1, 0), y, x])
        hi = float(src[wp.min(z + 1, nz - 1), y, x])
    elif axis == 1:
        lo = float(src[z, wp.max(y - 1, 0), x])
        hi = float(src[z, wp.min(y + 1, ny - 1), x])
    else:
        lo = float(src[z, y, wp.max(x - 1, 0)])
        hi = float(src[z, y, wp.min(x + 1, nx - 1)])
    dst[z, y, x] = w_side * (lo + hi) + w_centre * c
