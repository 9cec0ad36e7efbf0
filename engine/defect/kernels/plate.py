"""Warp kernel of the core test's allowance for the grid's staircase (``engine.defect.region.PLATE_SHELLS``), on the
device where the voxel rules' arrays already are: a voxel of the mirrored skull outside the bone, whose sample is
absent bone and that is no core, becomes one when no bone of the scan lies within the healthy shell's thickness
less the voxel's width along the mirrored shell's normal (the mirrored field's unit gradient, Sobel 3x3x3 in mm,
as the growth's; the width capped at the largest voxel side), nor within two such widths, and along that normal,
within ``shells`` shells either way (steps of half the smallest voxel side, samples trilinear), no bone of the scan
and, once the column has left the mirrored shell's run it starts in, no mirrored bone. OpenCL C twin:
``plate.cl`` (the same arithmetic, each sum left to right)."""

from __future__ import annotations

import warp as wp

from engine.defect.kernels.mirror import Box, _at, _gradient, _sample


@wp.kernel
def plate_kernel(
    data: wp.array(dtype=wp.float32),
    mirrored: wp.array(dtype=wp.float32),
    code: wp.array(dtype=wp.uint8),
    thick: wp.array(dtype=wp.float32),
    to_bone: wp.array(dtype=wp.float32),
    core: wp.array(dtype=wp.uint8),
    box: Box,
    level: float,
    shells: float,
    marked: wp.array(dtype=wp.uint8),
    cores: wp.array(dtype=wp.uint8),
):
    """``marked``: ``core`` with 3 where the allowance adds a core; ``cores``: 1 at the cores, strict or added."""
    z, y, x = wp.tid()
    i = _at(z, y, x, box.ny, box.nx)
    c = int(code[i])
    k0 = int(core[i])
    t = thick[i]
    big = wp.max(box.sz, wp.max(box.sy, box.sx))
    added = int(0)
    if (c & 4) != 0 and (c & 1) == 0 and (c & 8) != 0 and k0 == 0 and t > 0.0 and to_bone[i] > t - big:
        grad = _gradient(mirrored, box, z, y, x)
        gz = grad[0]
        gy = grad[1]
        gx = grad[2]
        n = wp.sqrt(gz * gz + gy * gy + gx * gx)
        if n > 0.0:
            nz_ = gz / n
            ny_ = gy / n
            nx_ = gx / n
            width = wp.min(wp.abs(nz_) * box.sz + wp.abs(ny_) * box.sy + wp.abs(nx_) * box.sx, big)
            if to_bone[i] > wp.max(t - width, 2.0 * width):
                added = int(1)
                step = 0.5 * wp.min(box.sz, wp.min(box.sy, box.sx))
                run0 = int(1)  # the column (this way, then the other) is still in the mirrored shell it starts in
                run1 = int(1)
                k = int(1)
                while float(k) * step <= shells * t + step and added == 1:
                    for s in range(2):
                        d = float(k) * step * (1.0 - 2.0 * float(s))
                        fz = float(z) + d * nz_ / box.sz
                        fy = float(y) + d * ny_ / box.sy
                        fx = float(x) + d * nx_ / box.sx
                        scan = _sample(data, box.nz, box.ny, box.nx, fz, fy, fx, -1.0e30) >= level
                        mir = _sample(mirrored, box.nz, box.ny, box.nx, fz, fy, fx, -1.0e30) >= level
                        run = run0
                        if s == 1:
                            run = run1
                        if run == 1 and not mir:
                            run = 0
                        if scan or (run == 0 and mir):
                            added = 0
                        if s == 0:
                            run0 = run
                        else:
                            run1 = run
                    k += 1
    m = k0
    if added == 1:
        m = 3
    marked[i] = wp.uint8(m)
    one = int(0)
    if k0 == 1 or added == 1:
        one = 1
    cores[i] = wp.uint8(one)
