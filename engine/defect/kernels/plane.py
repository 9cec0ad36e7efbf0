"""Warp kernels of the symmetry plane's nearest-surface queries (issue 42): a closest-feature transform (the exact
Euclidean distance transform of ``edt.py`` carrying, beside each voxel's squared distance, the rank of the feature
it belongs to) and the query that pairs each mirrored point with the nearest feature of the voxels around it.
Volumes are flat (z, y, x) arrays; features are flat voxel indices, ranked by their place in the feature list;
points are grid (x, y, z) mm, three floats each. OpenCL C twins: ``plane.cl`` (the same arithmetic)."""

from __future__ import annotations

import warp as wp

from engine.defect.kernels.edt import BIG, _line, lower_envelope
from engine.defect.kernels.mirror import Box


@wp.kernel
def seed_kernel(features: wp.array(dtype=wp.int32), f: wp.array(dtype=wp.float32), rank: wp.array(dtype=wp.int32)):
    """f = 0 and rank = the feature's rank at each feature voxel (f = BIG and rank = -1 elsewhere, set before)."""
    i = wp.tid()
    at = features[i]
    f[at] = 0.0
    rank[at] = i


@wp.kernel
def cft_pass_kernel(
    f: wp.array(dtype=wp.float32),
    g: wp.array(dtype=wp.float32),
    fr: wp.array(dtype=wp.int32),
    gr: wp.array(dtype=wp.int32),
    nz: int,
    ny: int,
    nx: int,
    axis: int,
    spacing: float,
    v: wp.array(dtype=wp.int32),
    zb: wp.array(dtype=wp.float32),
):
    """One axis of the closest-feature transform: ``edt_pass_kernel``'s lower envelope, each voxel taking the rank
    ``fr`` of the voxel whose parabola it lies under into ``gr``."""
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
            gr[base + q * stride] = -1
    else:
        j = int(0)
        for q in range(n):
            xq = float(q) * spacing
            while zb[so + j + 1] < xq:
                j += 1
            vj = int(v[so + j])
            d = xq - float(vj) * spacing
            g[base + q * stride] = d * d + f[base + vj * stride]
            gr[base + q * stride] = fr[base + vj * stride]


@wp.func
def _dist2(at: int, box: Box, px: float, py: float, pz: float) -> float:
    """Squared distance (mm^2) from the point (x, y, z mm) to the centre of the voxel at flat index ``at``."""
    fz = at // (box.ny * box.nx)
    rest = at - fz * (box.ny * box.nx)
    fy = rest // box.nx
    fx = rest - fy * box.nx
    dx = px - float(fx) * box.sx
    dy = py - float(fy) * box.sy
    dz = pz - float(fz) * box.sz
    return dx * dx + dy * dy + dz * dz


@wp.func
def _span(p: float, reach: float, s: float, n: int) -> wp.vec2i:
    """The voxels (first, last along one axis, clamped into the grid) whose centres may lie within ``reach`` mm of
    coordinate ``p``."""
    lo = wp.clamp(int(wp.floor((p - reach) / s)), 0, n - 1)
    hi = wp.clamp(int(wp.floor((p + reach) / s)) + 1, 0, n - 1)
    return wp.vec2i(lo, hi)


@wp.func
def _bound(
    points: wp.array(dtype=wp.float32),
    rank: wp.array(dtype=wp.int32),
    features: wp.array(dtype=wp.int32),
    box: Box,
    i: int,
):  # Warp infers the two values' types
    """The nearest of the closest features of the 8 voxels around point ``i`` (clamped into the grid), ties to the
    lower rank: its rank (-1 where there are none) and its squared distance (mm^2)."""
    px = points[3 * i]
    py = points[3 * i + 1]
    pz = points[3 * i + 2]
    z0 = int(wp.floor(pz / box.sz))
    y0 = int(wp.floor(py / box.sy))
    x0 = int(wp.floor(px / box.sx))
    best = float(BIG)
    pick = int(-1)
    for c in range(8):
        z = wp.clamp(z0 + c // 4, 0, box.nz - 1)
        y = wp.clamp(y0 + (c // 2) % 2, 0, box.ny - 1)
        x = wp.clamp(x0 + c % 2, 0, box.nx - 1)
        r = rank[(z * box.ny + y) * box.nx + x]
        if r >= 0:
            d2 = _dist2(features[r], box, px, py, pz)
            if d2 < best or (d2 == best and r < pick):
                best = d2
                pick = r
    return pick, best


@wp.kernel
def nearest_part_kernel(
    points: wp.array(dtype=wp.float32),
    rank: wp.array(dtype=wp.int32),
    features: wp.array(dtype=wp.int32),
    box: Box,
    max_scan: int,
    parts: int,
    part_d2: wp.array(dtype=wp.float32),
    part_rank: wp.array(dtype=wp.int32),
):
    """One of ``parts`` threads of point ``tid // parts``: the nearest feature (ties to the lower rank) among the
    closest features of the 8 voxels around the point (``_bound``) and the voxels of every ``parts``-th row (z, y)
    of the box whose centres may lie within that bound (a feature is its own closest feature, so the nearest is
    among them all), where the box holds at most ``max_scan`` voxels; else the bound's feature. ``nearest_join``
    takes the point's nearest over its parts: the order of the looks does not change the answer."""
    tid = wp.tid()
    i = tid // parts
    k = tid - i * parts
    near, near_d2 = _bound(points, rank, features, box, i)
    pick = int(near)  # loop-carried: declared as such
    best = float(near_d2)
    if pick >= 0:
        px = points[3 * i]
        py = points[3 * i + 1]
        pz = points[3 * i + 2]
        reach = wp.sqrt(best)
        sz = _span(pz, reach, box.sz, box.nz)
        sy = _span(py, reach, box.sy, box.ny)
        sx = _span(px, reach, box.sx, box.nx)
        ny = sy[1] - sy[0] + 1
        rows = (sz[1] - sz[0] + 1) * ny
        if rows * (sx[1] - sx[0] + 1) <= max_scan:
            for row in range(k, rows, parts):
                vz = sz[0] + row // ny
                vy = sy[0] + row - (row // ny) * ny
                for vx in range(sx[0], sx[1] + 1):
                    r = rank[(vz * box.ny + vy) * box.nx + vx]
                    if r >= 0 and r != pick:
                        e2 = _dist2(features[r], box, px, py, pz)
                        if e2 < best or (e2 == best and r < pick):
                            best = e2
                            pick = r
    part_d2[tid] = best
    part_rank[tid] = pick


@wp.kernel
def nearest_join_kernel(
    part_d2: wp.array(dtype=wp.float32),
    part_rank: wp.array(dtype=wp.int32),
    parts: int,
    out: wp.array(dtype=wp.int32),
):
    """out[i]: the nearest of point i's parts' features (ties to the lower rank), -1 where there are none."""
    i = wp.tid()
    best = float(BIG)
    pick = int(-1)
    for k in range(parts):
        r = part_rank[i * parts + k]
        d2 = part_d2[i * parts + k]
        if r >= 0 and (pick < 0 or d2 < best or (d2 == best and r < pick)):
            best = d2
            pick = r
    out[i] = pick


@wp.func
def _set(mask: wp.array(dtype=wp.uint8), nz: int, ny: int, nx: int, z: int, y: int, x: int) -> int:
    """1 where voxel (z, y, x) is in the grid and set, else 0."""
    if z < 0 or z >= nz or y < 0 or y >= ny or x < 0 or x >= nx:
        return 0
    if mask[(z * ny + y) * nx + x] != wp.uint8(0):
        return 1
    return 0


@wp.kernel
def flags_kernel(
    mask: wp.array(dtype=wp.uint8), nz: int, ny: int, nx: int, surface: int, flags: wp.array(dtype=wp.int32)
):
    """flags = 1 at the set voxels (with ``surface``: only those with a face neighbour clear or outside the grid),
    else 0."""
    i = wp.tid()
    z = i // (ny * nx)
    rest = i - z * (ny * nx)
    y = rest // nx
    x = rest - y * nx
    f = _set(mask, nz, ny, nx, z, y, x)
    if f != 0 and surface != 0:
        inner = (
            _set(mask, nz, ny, nx, z - 1, y, x)
            * _set(mask, nz, ny, nx, z + 1, y, x)
            * _set(mask, nz, ny, nx, z, y - 1, x)
            * _set(mask, nz, ny, nx, z, y + 1, x)
            * _set(mask, nz, ny, nx, z, y, x - 1)
            * _set(mask, nz, ny, nx, z, y, x + 1)
        )
        f = 1 - inner
    flags[i] = f


@wp.func
def _weight(o: int) -> int:
    """The Sobel smoothing weight of an offset across the derivative's axis: 1, 2, 1."""
    if o == 0:
        return 2
    return 1


@wp.kernel
def sobel_kernel(
    mask: wp.array(dtype=wp.uint8),
    nz: int,
    ny: int,
    nx: int,
    at: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.int32),
):
    """The mask's 3x3x3 Sobel gradient (x, y, z; integer, the grid outside clear) at flat voxel ``at[i]``."""
    i = wp.tid()
    a = at[i]
    z = a // (ny * nx)
    rest = a - z * (ny * nx)
    y = rest // nx
    x = rest - y * nx
    gx = int(0)
    gy = int(0)
    gz = int(0)
    for c in range(27):
        dz = c // 9 - 1
        dy = (c // 3) % 3 - 1
        dx = c % 3 - 1
        v = _set(mask, nz, ny, nx, z + dz, y + dy, x + dx)
        if v != 0:
            gx += _weight(dy) * _weight(dz) * dx
            gy += _weight(dx) * _weight(dz) * dy
            gz += _weight(dx) * _weight(dy) * dz
    out[3 * i] = gx
    out[3 * i + 1] = gy
    out[3 * i + 2] = gz
