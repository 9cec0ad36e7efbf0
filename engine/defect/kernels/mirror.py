"""Warp kernels of the defect's voxel rules: the mirrored scan (trilinear) with each voxel's class and shell
thickness, then the core tests and the grown region. Volumes are flat (z, y, x) arrays (their shape passed as
``nz, ny, nx``) of a crop whose first voxel is ``lo`` in the whole grid; points are grid (x, y, z) mm. The mirror
map is twelve floats (``a``: 3 x 3 row-major, then ``b``), the spacing three (z, y, x). OpenCL C twins:
``mirror.cl`` (the same arithmetic, each sum left to right, so both give the same bits)."""

from __future__ import annotations

import warp as wp

# voxel classes (bits of ``code``)
BONE = 1  # the sample is at or above the level
SKULL = 2  # in the skull (the largest bone piece)
MIRROR = 4  # the mirrored skull is at or above the level here
ABSENT = 8  # the sample is nearer the tissue around the bone than the level: no bone here, not even thin bone
MIRROR_ABSENT = 16  # the same for the mirrored sample


@wp.func
def _at(z: int, y: int, x: int, ny: int, nx: int) -> int:
    return (z * ny + y) * nx + x


@wp.func
def _sample(
    data: wp.array(dtype=wp.float32), nz: int, ny: int, nx: int, fz_: float, fy_: float, fx_: float, outside: float
) -> float:
    """Trilinear sample at fractional index (z, y, x); ``outside`` beyond the array."""
    z0 = int(wp.floor(fz_))
    y0 = int(wp.floor(fy_))
    x0 = int(wp.floor(fx_))
    fz = fz_ - float(z0)
    fy = fy_ - float(y0)
    fx = fx_ - float(x0)
    acc = float(0.0)
    for c in range(8):
        dz = c // 4
        dy = (c // 2) % 2
        dx = c % 2
        z = z0 + dz
        y = y0 + dy
        x = x0 + dx
        wz = 1.0 - fz
        if dz == 1:
            wz = fz
        wy = 1.0 - fy
        if dy == 1:
            wy = fy
        wx = 1.0 - fx
        if dx == 1:
            wx = fx
        w = wz * wy * wx
        v = outside
        if z >= 0 and z < nz and y >= 0 and y < ny and x >= 0 and x < nx:
            v = data[_at(z, y, x, ny, nx)]
        acc += w * v
    return acc


@wp.func
def _any_corner(mask: wp.array(dtype=wp.uint8), nz: int, ny: int, nx: int, fz: float, fy: float, fx: float) -> int:
    """1 when any of the 8 trilinear corners around fractional index (z, y, x) is set."""
    z0 = int(wp.floor(fz))
    y0 = int(wp.floor(fy))
    x0 = int(wp.floor(fx))
    hit = int(0)
    for c in range(8):
        z = z0 + c // 4
        y = y0 + (c // 2) % 2
        x = x0 + c % 2
        if z >= 0 and z < nz and y >= 0 and y < ny and x >= 0 and x < nx:
            if mask[_at(z, y, x, ny, nx)] != wp.uint8(0):
                hit = 1
    return hit


@wp.func
def _local_thickness(
    half: wp.array(dtype=wp.float32),
    nz: int,
    ny: int,
    nx: int,
    cz: int,
    cy: int,
    cx: int,
    rz: int,
    ry: int,
    rx: int,
    sz: float,
    sy: float,
    sx: float,
    reach: float,
    slack: float,
) -> float:
    """The shell's local thickness around voxel (cz, cy, cx): the diameter of the largest ball inside the shell
    centred within ``reach`` mm of it (``half``: each voxel's distance to outside the shell, the ball's radius;
    ``r*``: the reach in voxels; ``slack``: half a voxel). A voxel anywhere across a shell up to twice the reach
    thick sees the shell's middle, so the thickness is the shell's, not the voxel's depth in it."""
    best = float(0.0)
    for z in range(wp.max(cz - rz, 0), wp.min(cz + rz + 1, nz)):
        dz = float(z - cz) * sz
        for y in range(wp.max(cy - ry, 0), wp.min(cy + ry + 1, ny)):
            dy = float(y - cy) * sy
            for x in range(wp.max(cx - rx, 0), wp.min(cx + rx + 1, nx)):
                h = half[_at(z, y, x, ny, nx)]
                if 2.0 * h > best:
                    dx = float(x - cx) * sx
                    if wp.sqrt(dz * dz + dy * dy + dx * dx) <= reach + slack:
                        best = 2.0 * h
    return best


@wp.struct
class Mirror:
    """The mirror map ``q = a @ p + b`` on grid (x, y, z) mm: ``a`` row-major, then ``b`` (4-byte floats, the same
    layout as ``mirror.cl``'s ``mirror_t``)."""

    a00: wp.float32
    a01: wp.float32
    a02: wp.float32
    a10: wp.float32
    a11: wp.float32
    a12: wp.float32
    a20: wp.float32
    a21: wp.float32
    a22: wp.float32
    b0: wp.float32
    b1: wp.float32
    b2: wp.float32


@wp.struct
class Box:
    """A crop: its shape, its first voxel in the whole grid (z, y, x), and the grid's spacing (z, y, x mm)."""

    nz: wp.int32
    ny: wp.int32
    nx: wp.int32
    lz: wp.int32
    ly: wp.int32
    lx: wp.int32
    sz: wp.float32
    sy: wp.float32
    sx: wp.float32


@wp.kernel
def mirror_kernel(
    data: wp.array(dtype=wp.float32),
    skull: wp.array(dtype=wp.uint8),
    box: Box,
    source: wp.array(dtype=wp.float32),
    source_skull: wp.array(dtype=wp.uint8),
    half: wp.array(dtype=wp.float32),
    src: Box,
    m: Mirror,
    level: float,
    mid: float,
    outside: float,
    rz: int,
    ry: int,
    rx: int,
    reach: float,
    mirrored: wp.array(dtype=wp.float32),
    code: wp.array(dtype=wp.uint8),
    thick: wp.array(dtype=wp.float32),
):
    """Per voxel of a box (``data``, ``skull``: the scan and the skull there, its first voxel ``box.l*`` in the
    whole grid): the mirrored sample (trilinear in ``source``, a larger crop holding the mirror images, ``src``, at
    the mirror image ``a @ p + b`` of the voxel's grid point p), the voxel's classes, and the shell's local thickness
    where the mirror and the scan disagree (``half``: the source's distances to outside the skull): at the mirror
    image for a voxel of the mirrored skull not in the bone (the healthy side's thickness), at the voxel itself for
    a skull voxel whose mirror image is not bone; 0 elsewhere."""
    z, y, x = wp.tid()
    i = _at(z, y, x, box.ny, box.nx)
    px = float(x + box.lx) * box.sx
    py = float(y + box.ly) * box.sy
    pz = float(z + box.lz) * box.sz
    qx = m.a00 * px + m.a01 * py + m.a02 * pz + m.b0
    qy = m.a10 * px + m.a11 * py + m.a12 * pz + m.b1
    qz = m.a20 * px + m.a21 * py + m.a22 * pz + m.b2
    fz = qz / box.sz - float(src.lz)
    fy = qy / box.sy - float(src.ly)
    fx = qx / box.sx - float(src.lx)
    mv = _sample(source, src.nz, src.ny, src.nx, fz, fy, fx, outside)
    mirrored[i] = mv
    v = data[i]
    c = int(0)
    if v >= level:
        c = c | 1
    if skull[i] != wp.uint8(0):
        c = c | 2
    if mv >= level:
        if _any_corner(source_skull, src.nz, src.ny, src.nx, fz, fy, fx) != 0:
            c = c | 4
    if v < mid:
        c = c | 8
    if mv < mid:
        c = c | 16
    code[i] = wp.uint8(c)
    t = float(0.0)
    slack = 0.5 * wp.max(box.sz, wp.max(box.sy, box.sx))
    if (c & 4) != 0 and (c & 1) == 0:
        t = _local_thickness(half, src.nz, src.ny, src.nx, int(wp.round(fz)), int(wp.round(fy)), int(wp.round(fx)),
                             rz, ry, rx, box.sz, box.sy, box.sx, reach, slack)  # fmt: skip
    elif (c & 2) != 0 and (c & 4) == 0:
        t = _local_thickness(half, src.nz, src.ny, src.nx, z + box.lz - src.lz, y + box.ly - src.ly,
                             x + box.lx - src.lx, rz, ry, rx, box.sz, box.sy, box.sx, reach, slack)  # fmt: skip
    thick[i] = t


@wp.kernel
def core_kernel(
    code: wp.array(dtype=wp.uint8),
    thick: wp.array(dtype=wp.float32),
    to_bone: wp.array(dtype=wp.float32),
    to_mirror: wp.array(dtype=wp.float32),
    core: wp.array(dtype=wp.uint8),
):
    """The cores: 1 where the mirrored shell has no bone of the scan within its thickness and the scan holds
    tissue there (missing bone); 2 where the scan's shell has no mirrored bone within its thickness and the
    mirror holds tissue there (bone on this side only: the mirror of a missing piece, or bone that moved)."""
    i = wp.tid()
    c = int(code[i])
    t = thick[i]
    k = int(0)
    if (c & 4) != 0 and (c & 1) == 0 and (c & 8) != 0 and to_bone[i] > t:
        k = 1
    elif (c & 2) != 0 and (c & 4) == 0 and (c & 16) != 0 and to_mirror[i] > t:
        k = 2
    core[i] = wp.uint8(k)


@wp.func
def _value(a: wp.array(dtype=wp.float32), nz: int, ny: int, nx: int, z: int, y: int, x: int) -> float:
    """a[z, y, x] with the index clamped to the array."""
    return a[_at(wp.clamp(z, 0, nz - 1), wp.clamp(y, 0, ny - 1), wp.clamp(x, 0, nx - 1), ny, nx)]


@wp.func
def _gradient(mirrored: wp.array(dtype=wp.float32), box: Box, z: int, y: int, x: int) -> wp.vec3:
    """The mirrored field's gradient at voxel (z, y, x) of the box, Sobel 3x3x3 in mm: (z, y, x) components."""
    gz = float(0.0)
    gy = float(0.0)
    gx = float(0.0)
    for k in range(27):
        dz = k // 9 - 1
        dy = (k // 3) % 3 - 1
        dx = k % 3 - 1
        v = _value(mirrored, box.nz, box.ny, box.nx, z + dz, y + dy, x + dx)
        wz = float(2 - dy * dy) * float(2 - dx * dx)
        wy = float(2 - dz * dz) * float(2 - dx * dx)
        wx = float(2 - dz * dz) * float(2 - dy * dy)
        gz = gz + float(dz) * wz * v / box.sz
        gy = gy + float(dy) * wy * v / box.sy
        gx = gx + float(dx) * wx * v / box.sx
    return wp.vec3(gz, gy, gx)


@wp.kernel
def grow_kernel(
    data: wp.array(dtype=wp.float32),
    mirrored: wp.array(dtype=wp.float32),
    code: wp.array(dtype=wp.uint8),
    thick: wp.array(dtype=wp.float32),
    to_core: wp.array(dtype=wp.float32),
    box: Box,
    level: float,
    reach: float,
    grown: wp.array(dtype=wp.uint8),
):
    """The candidate region: mirrored skull not in the bone, within the shell's thickness + ``reach`` mm of a core
    (the core grown back to the rim), where the bone is missing across the mirrored shell: no sample of the scan at
    or above the level along the mirrored shell's normal (the mirrored field's unit gradient, Sobel 3x3x3 in mm)
    within the shell's local thickness either way. A sliver beside bone that the mirror is slightly off from has
    that bone along its normal; the voxels of a hole have bone beside them (the rim) but not across."""
    z, y, x = wp.tid()
    i = _at(z, y, x, box.ny, box.nx)
    c = int(code[i])
    g = int(0)
    t = thick[i]
    if (c & 4) != 0 and (c & 1) == 0 and to_core[i] <= t + reach:
        g = int(1)
        grad = _gradient(mirrored, box, z, y, x)
        gz = grad[0]
        gy = grad[1]
        gx = grad[2]
        n = wp.sqrt(gz * gz + gy * gy + gx * gx)
        if n > 0.0:
            nz_ = gz / n
            ny_ = gy / n
            nx_ = gx / n
            step = 0.5 * wp.min(box.sz, wp.min(box.sy, box.sx))
            k = int(1)
            while float(k) * step <= 0.5 * t + step and g == 1:
                for s in range(2):
                    d = float(k) * step * (1.0 - 2.0 * float(s))
                    fz = float(z) + d * nz_ / box.sz
                    fy = float(y) + d * ny_ / box.sy
                    fx = float(x) + d * nx_ / box.sx
                    if _sample(data, box.nz, box.ny, box.nx, fz, fy, fx, -1.0e30) >= level:
                        g = 0
                k += 1
    grown[i] = wp.uint8(g)


@wp.kernel
def select_kernel(src: wp.array(dtype=wp.uint8), value: int, out: wp.array(dtype=wp.uint8)):
    """out = 1 where src == value."""
    i = wp.tid()
    out[i] = wp.uint8(1) if int(src[i]) == value else wp.uint8(0)


@wp.kernel
def bits_kernel(src: wp.array(dtype=wp.uint8), bits: int, out: wp.array(dtype=wp.uint8)):
    """out = 1 where any of ``bits`` is set in src."""
    i = wp.tid()
    out[i] = wp.uint8(1) if (int(src[i]) & bits) != 0 else wp.uint8(0)


@wp.kernel
def ridge_kernel(half: wp.array(dtype=wp.float32), nz: int, ny: int, nx: int, ridge: wp.array(dtype=wp.uint8)):
    """1 at the shell's middle: inside voxels whose inner distance is at least each of their 26 neighbours'."""
    z, y, x = wp.tid()
    h = half[_at(z, y, x, ny, nx)]
    r = int(0)
    if h > 0.0:
        r = int(1)
        for c in range(27):
            zz = z + c // 9 - 1
            yy = y + (c // 3) % 3 - 1
            xx = x + c % 3 - 1
            if zz >= 0 and zz < nz and yy >= 0 and yy < ny and xx >= 0 and xx < nx:
                if half[_at(zz, yy, xx, ny, nx)] > h:
                    r = 0
    ridge[_at(z, y, x, ny, nx)] = wp.uint8(r)
