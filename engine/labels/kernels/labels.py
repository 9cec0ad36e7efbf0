"""Warp kernels of the per-label meshing (``engine.labels.extract``): label boxes in one pass over the map, the
indicator atlas of a group of labels, the move of each label's vertices from the atlas to the grid, and per-label
sums. Generic over the label map's integer type (uint8, uint16, int32, uint32). ``labels.cl`` holds their OpenCL C
twins: same names, same arguments (shapes passed as ints, as OpenCL has no array shapes), same arithmetic in the
same order."""

from __future__ import annotations

from typing import Any

import warp as wp


@wp.kernel
def mark_extent(labels: wp.array3d(dtype=Any), lut: wp.array(dtype=wp.int32), n_lut: int,
                fz: wp.array2d(dtype=wp.int32), fy: wp.array2d(dtype=wp.int32), fx: wp.array2d(dtype=wp.int32),
                nz: int, ny: int, nx: int):  # fmt: skip
    """Per label slot, which z planes, y rows and x columns hold it (a read before the write keeps stores few)."""
    z, y, x = wp.tid()
    v = int(labels[z, y, x])
    if v <= 0 or v >= n_lut:
        return
    s = lut[v]
    if s < 0:
        return
    if fz[s, z] == 0:
        fz[s, z] = 1
    if fy[s, y] == 0:
        fy[s, y] = 1
    if fx[s, x] == 0:
        fx[s, x] = 1


@wp.kernel
def fill_atlas(labels: wp.array3d(dtype=Any), plane_crop: wp.array(dtype=wp.int32), crops: wp.array2d(dtype=wp.int32),
               other: float, out: wp.array3d(dtype=wp.float32), nz: int, ny: int, nx: int):  # fmt: skip
    """One group's atlas: crops stacked along z; crops[c] = (atlas z0, grid z0, y0, x0, dy, dx, value).
    1 on the crop's label, ``other`` (< 0) on another label, 0 on background and outside the map or the crop;
    ``nz, ny, nx`` is the map's shape."""
    z, y, x = wp.tid()
    c = plane_crop[z]
    val = 0.0
    if y < crops[c, 4] and x < crops[c, 5]:
        gz = crops[c, 1] + z - crops[c, 0]
        gy = crops[c, 2] + y
        gx = crops[c, 3] + x
        if gz >= 0 and gy >= 0 and gx >= 0 and gz < nz and gy < ny and gx < nx:
            v = int(labels[gz, gy, gx])
            if v == crops[c, 6]:
                val = 1.0
            elif v != 0:
                val = other
    out[z, y, x] = val


@wp.kernel
def place_vertices(pos: wp.array(dtype=wp.vec3), plane_crop: wp.array(dtype=wp.int32), n_planes: int,
                   crops: wp.array2d(dtype=wp.int32), crop_slot: wp.array(dtype=wp.int32),
                   labels: wp.array3d(dtype=Any), sz: float, sy: float, sx: float, first: int,
                   out_pos: wp.array(dtype=wp.vec3), slot: wp.array(dtype=wp.int32), near: wp.array(dtype=wp.int32),
                   nz: int, ny: int, nx: int):  # fmt: skip
    """Atlas (z, y, x) mm -> grid (z, y, x) mm, each vertex's label slot (its crop's), and whether another label
    holds a corner of its cell (``near``: pinned by the decimation), into ``first + i``."""
    i = wp.tid()
    p = pos[i]
    plane = int(wp.floor(p[0] / sz + 0.5))
    plane = wp.clamp(plane, 0, n_planes - 1)
    c = plane_crop[plane]
    g = wp.vec3(p[0] + float(crops[c, 1] - crops[c, 0]) * sz, p[1] + float(crops[c, 2]) * sy,
                p[2] + float(crops[c, 3]) * sx)  # fmt: skip
    out_pos[first + i] = g
    slot[first + i] = crop_slot[c]
    bz = int(wp.floor(g[0] / sz))
    by = int(wp.floor(g[1] / sy))
    bx = int(wp.floor(g[2] / sx))
    own = crops[c, 6]
    flag = 0
    for dz in range(0, 2):
        for dy in range(0, 2):
            for dx in range(0, 2):
                z = bz + dz
                y = by + dy
                x = bx + dx
                if z >= 0 and y >= 0 and x >= 0 and z < nz and y < ny and x < nx:
                    v = int(labels[z, y, x])
                    if v != 0 and v != own:
                        flag = 1
    near[first + i] = flag


@wp.kernel
def offset_faces(faces: wp.array(dtype=wp.vec3i), offset: int, first: int, out: wp.array(dtype=wp.vec3i)):
    i = wp.tid()
    f = faces[i]
    out[first + i] = wp.vec3i(f[0] + offset, f[1] + offset, f[2] + offset)


@wp.kernel
def gather_slots(slot: wp.array(dtype=wp.int32), kept: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out[i] = slot[kept[i]]


@wp.kernel
def face_sums(pos: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.vec3i), slot: wp.array(dtype=wp.int32),
              scale: float, count: wp.array(dtype=wp.int32), area: wp.array(dtype=wp.int64)):  # fmt: skip
    """Faces and area per label slot; the area in fixed point (``scale`` units per mm^2, rounded per face) so the
    sums are exact and the same in any order, on every backend."""
    i = wp.tid()
    f = faces[i]
    s = slot[f[0]]
    a = pos[f[0]]
    b = pos[f[1]]
    c = pos[f[2]]
    e0 = wp.vec3(b[0] - a[0], b[1] - a[1], b[2] - a[2])
    e1 = wp.vec3(c[0] - a[0], c[1] - a[1], c[2] - a[2])
    cz = e0[1] * e1[2] - e0[2] * e1[1]
    cy = e0[2] * e1[0] - e0[0] * e1[2]
    cx = e0[0] * e1[1] - e0[1] * e1[0]
    sq = cz * cz + cy * cy + cx * cx
    tri = 0.5 * wp.sqrt(sq)
    wp.atomic_add(count, s, 1)
    wp.atomic_add(area, s, wp.int64(tri * scale + 0.5))


@wp.kernel
def lock_slots(slot: wp.array(dtype=wp.int32), open_slot: wp.array(dtype=wp.int32), near: wp.array(dtype=wp.int32),
               locked: wp.array(dtype=wp.int32)):  # fmt: skip
    """Pinned in the next decimation round: vertices near another label, and those of labels within budget."""
    i = wp.tid()
    locked[i] = wp.max(near[i], 1 - open_slot[slot[i]])
