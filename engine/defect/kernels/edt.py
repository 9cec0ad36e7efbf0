"""Warp kernels of the exact Euclidean distance transform (Felzenszwalb and Huttenlocher's lower envelope of
parabolas, one thread per grid line, one pass per axis, anisotropic spacing). Volumes are flat float32 arrays in
(z, y, x) order; ``BIG`` stands for "no feature on this line". OpenCL C twins: ``edt.cl`` (the same arithmetic)."""

from __future__ import annotations

import warp as wp

BIG = 1.0e30


@wp.func
def _line(line: int, nz: int, ny: int, nx: int, axis: int) -> wp.vec3i:
    """(first flat index, stride, length) of grid line ``line`` along ``axis``."""
    if axis == 2:
        return wp.vec3i(line * nx, 1, nx)
    if axis == 1:
        z = line // nx
        x = line - z * nx
        return wp.vec3i(z * ny * nx + x, nx, ny)
    return wp.vec3i(line, ny * nx, nz)


@wp.func
def lower_envelope(
    f: wp.array(dtype=wp.float32),
    base: int,
    stride: int,
    n: int,
    spacing: float,
    v: wp.array(dtype=wp.int32),
    zb: wp.array(dtype=wp.float32),
    so: int,
) -> int:
    """The lower envelope of one grid line's parabolas (x - x_p)^2 + f[p] (``base``, ``stride``, ``n``: ``_line``):
    the positions of its parabolas in ``v`` and their breakpoints in ``zb``, from ``so``; the index of its last
    parabola, -1 where the line has no feature."""
    k = int(-1)
    for q in range(n):
        fq = f[base + q * stride]
        if fq < BIG * 0.5:
            xq = float(q) * spacing
            if k < 0:
                k = 0
                v[so] = q
                zb[so] = -BIG
                zb[so + 1] = BIG
            else:
                vk = int(v[so + k])
                xv = float(vk) * spacing
                s = ((fq + xq * xq) - (f[base + vk * stride] + xv * xv)) / (2.0 * (xq - xv))
                while s <= zb[so + k]:
                    k -= 1
                    vk = int(v[so + k])
                    xv = float(vk) * spacing
                    s = ((fq + xq * xq) - (f[base + vk * stride] + xv * xv)) / (2.0 * (xq - xv))
                k += 1
                v[so + k] = q
                zb[so + k] = s
                zb[so + k + 1] = BIG
    return k


@wp.kernel
def features_kernel(mask: wp.array(dtype=wp.uint8), inside: int, f: wp.array(dtype=wp.float32)):
    """f = 0 at the features (mask set, or mask clear with ``inside``), BIG elsewhere."""
    i = wp.tid()
    m = int(mask[i])
    if inside != 0:
        m = 1 - m
    if m != 0:
        f[i] = 0.0
    else:
        f[i] = BIG


@wp.kernel
def edt_pass_kernel(
    f: wp.array(dtype=wp.float32),
    g: wp.array(dtype=wp.float32),
    nz: int,
    ny: int,
    nx: int,
    axis: int,
    spacing: float,
    v: wp.array(dtype=wp.int32),
    zb: wp.array(dtype=wp.float32),
):
    """One axis of the squared distance: g[q] = min_p (x_q - x_p)^2 + f[p] along each line (lower envelope)."""
    line = wp.tid()
    geo = _line(line, nz, ny, nx, axis)
    base = geo[0]
    stride = geo[1]
    n = geo[2]
    so = line * (n + 1)
    k = lower_envelope(f, base, stride, n, spacing, v, zb, so)
    if k < 0:
        for q in range(n):
            g[base + q * stride] = BIG
    else:
        j = int(0)
        for q in range(n):
            xq = float(q) * spacing
            while zb[so + j + 1] < xq:
                j += 1
            vj = int(v[so + j])
            d = xq - float(vj) * spacing
            g[base + q * stride] = d * d + f[base + vj * stride]


@wp.kernel
def sqrt_kernel(g: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    """out = sqrt(g), BIG where no feature was found."""
    i = wp.tid()
    x = g[i]
    if x >= BIG * 0.5:
        out[i] = BIG
    else:
        out[i] = wp.sqrt(x)
