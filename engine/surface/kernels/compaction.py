"""Warp kernels that compact a device mesh: drop removed faces and unused vertices, keeping the order of the rest
(host side: ``engine.surface.devmesh``); and its bounding box. OpenCL C twins: ``compaction.cl``.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def alive_flags(faces: wp.array(dtype=wp.vec3i), flag: wp.array(dtype=wp.int32)):
    f = wp.tid()
    flag[f] = 0
    if faces[f][0] >= 0:
        flag[f] = 1


@wp.kernel
def scatter_faces(
    faces: wp.array(dtype=wp.vec3i),
    slot: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3i),
):
    f = wp.tid()
    t = faces[f]
    if t[0] >= 0:
        out[slot[f]] = t


@wp.kernel
def used_flags(count: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    v = wp.tid()
    flag[v] = 0
    if count[v] > 0:
        flag[v] = 1


@wp.kernel
def scatter_vertices(
    pos: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=wp.int32),
    slot: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3),
):
    v = wp.tid()
    if count[v] > 0:
        out[slot[v]] = pos[v]


@wp.kernel
def remap_faces(faces: wp.array(dtype=wp.vec3i), slot: wp.array(dtype=wp.int32)):
    f = wp.tid()
    t = faces[f]
    faces[f] = wp.vec3i(slot[t[0]], slot[t[1]], slot[t[2]])


@wp.kernel
def bounds_kernel(pos: wp.array(dtype=wp.vec3), box: wp.array(dtype=wp.vec3)):
    """``box[0]`` = component-wise minimum, ``box[1]`` = maximum (atomic per component)."""
    v = wp.tid()
    wp.atomic_min(box, 0, pos[v])
    wp.atomic_max(box, 1, pos[v])
