"""Warp kernels of the defect's voxel rules: the mirrored scan (trilinear) with each voxel's class and shell
thickness, then the core tests and the grown region. Volumes are (z, y, x) arrays of a crop whose first voxel is
``lo`` in the whole grid; points are grid (x, y, z) mm."""

from __future__ import annotations

import warp as wp

# voxel classes (bits of ``code``)
BONE = 1  # the sample is at or above the level
SKULL = 2  # in the skull (the largest bone piece)
MIRROR = 4  # the mirrored skull is at or above the level here
ABSENT = 8  # the sample is nearer the tissue around the bone than the level: no bone here, not even thin bone
MIRROR_ABSENT = 16  # the same for the mirrored sample


@wp.func
def _sample(data: wp.array3d(dtype=wp.float32), f: wp.vec3, outside: float) -> float:
    """Trilinear sample at fractional index f = (z, y, x); ``outside`` beyond the array."""
    nz = data.shape[0]
    ny = data.shape[1]
    nx = data.shape[2]
    z0 = int(wp.floor(f[0]))
    y0 = int(wp.floor(f[1]))
    x0 = int(wp.floor(f[2]))
    fz = f[0] - float(z0)
    fy = f[1] - float(y0)
    fx = f[2] - float(x0)
    acc = float(0.0)
    for c in range(8):
        dz = c // 4
        dy = (c // 2) % 2
        dx = c % 2
        z = z0 + dz
        y = y0 + dy
        x = x0 + dx
        w = (fz if dz == 1 else 1.0 - fz) * (fy if dy == 1 else 1.0 - fy) * (fx if dx == 1 else 1.0 - fx)
        v = outside
        if z >= 0 and z < nz and y >= 0 and y < ny and x >= 0 and x < nx:
            v = data[z, y, x]
        acc += w * v
    return acc


@wp.func
def _any_corner(mask: wp.array3d(dtype=wp.uint8), f: wp.vec3) -> int:
    """1 when any of the 8 trilinear corners around fractional index f is set."""
    nz = mask.shape[0]
    ny = mask.shape[1]
    nx = mask.shape[2]
    z0 = int(wp.floor(f[0]))
    y0 = int(wp.floor(f[1]))
    x0 = int(wp.floor(f[2]))
    hit = int(0)
    for c in range(8):
        z = z0 + c // 4
        y = y0 + (c // 2) % 2
        x = x0 + c % 2
        if z >= 0 and z < nz and y >= 0 and y < ny and x >= 0 and x < nx:
            if mask[z, y, x] != wp.uint8(0):
                hit = 1
    return hit


@wp.func
def _local_thickness(
    half: wp.array3d(dtype=wp.float32),
    cz: int,
    cy: int,
    cx: int,
    rad: wp.vec3i,
    spacing: wp.vec3,
    reach: float,
    slack: float,
) -> float:
    """The shell's local thickness around voxel (cz, cy, cx): the diameter of the largest ball inside the shell
    centred within ``reach`` mm of it (``half``: each voxel's distance to outside the shell, the ball's radius;
    ``rad``: the reach in voxels; ``slack``: half a voxel). A voxel anywhere across a shell up to twice the reach
    thick sees the shell's middle, so the thickness is the shell's, not the voxel's depth in it."""
    nz = half.shape[0]
    ny = half.shape[1]
    nx = half.shape[2]
    best = float(0.0)
    for z in range(wp.max(cz - rad[0], 0), wp.min(cz + rad[0] + 1, nz)):
        dz = float(z - cz) * spacing[0]
        for y in range(wp.max(cy - rad[1], 0), wp.min(cy + rad[1] + 1, ny)):
            dy = float(y - cy) * spacing[1]
            for x in range(wp.max(cx - rad[2], 0), wp.min(cx + rad[2] + 1, nx)):
                h = half[z, y, x]
                if 2.0 * h > best:
                    dx = float(x - cx) * spacing[2]
                    if wp.sqrt(dz * dz + dy * dy + dx * dx) <= reach + slack:
                        best = 2.0 * h
    return best


@wp.kernel
def mirror_kernel(
    data: wp.array3d(dtype=wp.float32),
    skull: wp.array3d(dtype=wp.uint8),
    lo: wp.vec3i,
    source: wp.array3d(dtype=wp.float32),
    source_skull: wp.array3d(dtype=wp.uint8),
    half: wp.array3d(dtype=wp.float32),
    source_lo: wp.vec3i,
    mirror_a: wp.mat33,
    mirror_b: wp.vec3,
    spacing: wp.vec3,
    level: float,
    mid: float,
    outside: float,
    rad: wp.vec3i,
    reach: float,
    mirrored: wp.array3d(dtype=wp.float32),
    code: wp.array3d(dtype=wp.uint8),
    thick: wp.array3d(dtype=wp.float32),
):
    """Per voxel of a box (``data``, ``skull``: the scan and the skull there, its first voxel ``lo`` in the whole
    grid): the mirrored sample (trilinear in ``source``, a larger crop holding the mirror images, first voxel
    ``source_lo``, at the mirror image ``mirror_a @ p + mirror_b`` of the voxel's grid point p), the voxel's classes,
    and the shell's local thickness where the mirror and the scan disagree (``half``: the source's distances to
    outside the skull): at the mirror image for a voxel of the mirrored skull not in the bone (the healthy side's
    thickness), at the voxel itself for a skull voxel whose mirror image is not bone; 0 elsewhere."""
    z, y, x = wp.tid()
    p = wp.vec3(
        float(x + lo[2]) * spacing[2],
        float(y + lo[1]) * spacing[1],
        float(z + lo[0]) * spacing[0],
    )
    q = mirror_a * p + mirror_b
    f = wp.vec3(
        q[2] / spacing[0] - float(source_lo[0]),
        q[1] / spacing[1] - float(source_lo[1]),
        q[0] / spacing[2] - float(source_lo[2]),
    )
    m = _sample(source, f, outside)
    mirrored[z, y, x] = m
    v = data[z, y, x]
    c = int(0)
    if v >= level:
        c = c | 1
    if skull[z, y, x] != wp.uint8(0):
        c = c | 2
    if m >= level and _any_corner(source_skull, f) != 0:
        c = c | 4
    if v < mid:
        c = c | 8
    if m < mid:
        c = c | 16
    code[z, y, x] = wp.uint8(c)
    t = float(0.0)
    slack = 0.5 * wp.max(spacing[0], wp.max(spacing[1], spacing[2]))
    if (c & 4) != 0 and (c & 1) == 0:
        t = _local_thickness(
            half, int(wp.round(f[0])), int(wp.round(f[1])), int(wp.round(f[2])), rad, spacing, reach, slack
        )
    elif (c & 2) != 0 and (c & 4) == 0:
        sz = z + lo[0] - source_lo[0]
        sy = y + lo[1] - source_lo[1]
        sx = x + lo[2] - source_lo[2]
        t = _local_thickness(half, sz, sy, sx, rad, spacing, reach, slack)
    thick[z, y, x] = t


@wp.kernel
def core_kernel(
    code: wp.array3d(dtype=wp.uint8),
    thick: wp.array3d(dtype=wp.float32),
    to_bone: wp.array3d(dtype=wp.float32),
    to_mirror: wp.array3d(dtype=wp.float32),
    core: wp.array3d(dtype=wp.uint8),
):
    """The cores: 1 where the mirrored shell has no bone of the scan within its thickness and the scan holds
    tissue there (missing bone); 2 where the scan's shell has no mirrored bone within its thickness and the
    mirror holds tissue there (bone on this side only: the mirror of a missing piece, or bone that moved)."""
    z, y, x = wp.tid()
    c = int(code[z, y, x])
    t = thick[z, y, x]
    k = int(0)
    if (c & 4) != 0 and (c & 1) == 0 and (c & 8) != 0 and to_bone[z, y, x] > t:
        k = 1
    elif (c & 2) != 0 and (c & 4) == 0 and (c & 16) != 0 and to_mirror[z, y, x] > t:
        k = 2
    core[z, y, x] = wp.uint8(k)


@wp.func
def _value(a: wp.array3d(dtype=wp.float32), z: int, y: int, x: int) -> float:
    """a[z, y, x] with the index clamped to the array."""
    return a[wp.clamp(z, 0, a.shape[0] - 1), wp.clamp(y, 0, a.shape[1] - 1), wp.clamp(x, 0, a.shape[2] - 1)]


@wp.func
def _normal(m: wp.array3d(dtype=wp.float32), z: int, y: int, x: int, spacing: wp.vec3) -> wp.vec3:
    """The unit gradient (z, y, x) of a field at a voxel: Sobel, 3x3x3, in mm; zero where flat."""
    g = wp.vec3(0.0, 0.0, 0.0)
    for c in range(27):
        dz = c // 9 - 1
        dy = (c // 3) % 3 - 1
        dx = c % 3 - 1
        v = _value(m, z + dz, y + dy, x + dx)
        wz = float(2 - dy * dy) * float(2 - dx * dx)
        wy = float(2 - dz * dz) * float(2 - dx * dx)
        wx = float(2 - dz * dz) * float(2 - dy * dy)
        gz = float(dz) * wz * v / spacing[0]
        gy = float(dy) * wy * v / spacing[1]
        gx = float(dx) * wx * v / spacing[2]
        g = g + wp.vec3(gz, gy, gx)
    n = wp.length(g)
    if n > 0.0:
        return g / n
    return g


@wp.kernel
def grow_kernel(
    data: wp.array3d(dtype=wp.float32),
    mirrored: wp.array3d(dtype=wp.float32),
    code: wp.array3d(dtype=wp.uint8),
    thick: wp.array3d(dtype=wp.float32),
    to_core: wp.array3d(dtype=wp.float32),
    spacing: wp.vec3,
    level: float,
    reach: float,
    grown: wp.array3d(dtype=wp.uint8),
):
    """The candidate region: mirrored skull not in the bone, within the shell's thickness + ``reach`` mm of a core
    (the core grown back to the rim), where the bone is
    missing across the mirrored shell: no sample of the scan at or above the level along the mirrored shell's normal
    (the mirrored field's gradient) within the shell's local thickness either way. A sliver beside bone that the
    mirror is slightly off from has that bone along its normal; the voxels of a hole have bone beside them (the rim)
    but not across."""
    z, y, x = wp.tid()
    c = int(code[z, y, x])
    g = int(0)
    t = thick[z, y, x]
    if (c & 4) != 0 and (c & 1) == 0 and to_core[z, y, x] <= t + reach:
        g = int(1)
        n = _normal(mirrored, z, y, x, spacing)
        if wp.length(n) > 0.0:
            step = 0.5 * wp.min(spacing[0], wp.min(spacing[1], spacing[2]))
            k = int(1)
            while float(k) * step <= 0.5 * t + step and g == 1:
                for s in range(2):
                    d = float(k) * step * (1.0 - 2.0 * float(s))
                    f = wp.vec3(
                        float(z) + d * n[0] / spacing[0],
                        float(y) + d * n[1] / spacing[1],
                        float(x) + d * n[2] / spacing[2],
                    )
                    if _sample(data, f, -1.0e30) >= level:
                        g = 0
                k += 1
    grown[z, y, x] = wp.uint8(g)


@wp.kernel
def select_kernel(src: wp.array3d(dtype=wp.uint8), value: int, out: wp.array3d(dtype=wp.uint8)):
    """out = 1 where src == value."""
    z, y, x = wp.tid()
    out[z, y, x] = wp.uint8(1) if int(src[z, y, x]) == value else wp.uint8(0)


@wp.kernel
def bits_kernel(src: wp.array3d(dtype=wp.uint8), bits: int, out: wp.array3d(dtype=wp.uint8)):
    """out = 1 where any of ``bits`` is set in src."""
    z, y, x = wp.tid()
    out[z, y, x] = wp.uint8(1) if (int(src[z, y, x]) & bits) != 0 else wp.uint8(0)


@wp.kernel
def ridge_kernel(half: wp.array3d(dtype=wp.float32), ridge: wp.array3d(dtype=wp.uint8)):
    """1 at the shell's middle: inside voxels whose inner distance is at least each of their 26 neighbours'."""
    z, y, x = wp.tid()
    h = half[z, y, x]
    r = int(0)
    if h > 0.0:
        r = int(1)
        for c in range(27):
            zz = z + c // 9 - 1
            yy = y + (c // 3) % 3 - 1
            xx = x + c % 3 - 1
            if zz >= 0 and zz < half.shape[0] and yy >= 0 and yy < half.shape[1] and xx >= 0 and xx < half.shape[2]:
                if half[zz, yy, xx] > h:
                    r = 0
    ridge[z, y, x] = wp.uint8(r)
