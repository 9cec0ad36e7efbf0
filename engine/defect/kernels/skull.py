"""Warp kernels of the skull mask on a device (issue 42): the bone's 26-connected pieces by min-label hooking with
pointer jumping (every voxel ends labelled with the flat index of its piece's first voxel), their sizes, and the
mask of one piece. Volumes are flat (z, y, x) arrays, labels int32 (-1: not bone). OpenCL C twins: ``skull.cl``."""

from __future__ import annotations

import warp as wp


@wp.kernel
def init_kernel(bone: wp.array(dtype=wp.uint8), label: wp.array(dtype=wp.int32)):
    """label = the voxel's own flat index where it is bone, else -1."""
    i = wp.tid()
    if bone[i] != wp.uint8(0):
        label[i] = i
    else:
        label[i] = -1


@wp.func
def _pull(label: wp.array(dtype=wp.int32), i: int, j: int) -> int:
    """Hook voxels i and j (both bone, neighbours) onto the smaller of their labels; 1 where a label changed."""
    a = label[i]
    b = label[j]
    if a == b:
        return 0
    m = wp.min(a, b)
    if a > m:
        wp.atomic_min(label, a, m)
        wp.atomic_min(label, i, m)
    if b > m:
        wp.atomic_min(label, b, m)
        wp.atomic_min(label, j, m)
    return 1


@wp.kernel
def hook_kernel(nz: int, ny: int, nx: int, label: wp.array(dtype=wp.int32), changed: wp.array(dtype=wp.int32)):
    """Every bone voxel pulls itself and its 13 forward 26-neighbours that are bone (later in the flat order:
    each pair once) down to the smaller label, and their labels' voxels too."""
    i = wp.tid()
    if label[i] < 0:
        return
    z = i // (ny * nx)
    rest = i - z * (ny * nx)
    y = rest // nx
    x = rest - y * nx
    moved = int(0)
    for c in range(13):
        # the 13 offsets after (0, 0, 0) in (z, y, x) order: (0, 0, 1), (0, 1, -1..1), (1, -1..1, -1..1)
        k = c + 14
        dz = k // 9 - 1
        dy = (k // 3) % 3 - 1
        dx = k % 3 - 1
        zz = z + dz
        yy = y + dy
        xx = x + dx
        if zz < nz and yy >= 0 and yy < ny and xx >= 0 and xx < nx:
            j = (zz * ny + yy) * nx + xx
            if label[j] >= 0:
                moved += _pull(label, i, j)
    if moved != 0:
        changed[0] = 1


@wp.kernel
def roots_kernel(label: wp.array(dtype=wp.int32), size: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """size[root] += 1 for every bone voxel; flags = 1 at the roots (each piece's first voxel)."""
    i = wp.tid()
    r = label[i]
    f = int(0)
    if r >= 0:
        wp.atomic_add(size, r, 1)
        if r == i:
            f = 1
    flags[i] = f


@wp.kernel
def gather_kernel(src: wp.array(dtype=wp.int32), at: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    """out[k] = src[at[k]]."""
    k = wp.tid()
    out[k] = src[at[k]]


@wp.kernel
def piece_kernel(label: wp.array(dtype=wp.int32), root: int, out: wp.array(dtype=wp.uint8)):
    """out = 1 in the piece whose root is ``root``, else 0."""
    i = wp.tid()
    if label[i] == root:
        out[i] = wp.uint8(1)
    else:
        out[i] = wp.uint8(0)
