"""Warp kernels for decimating a mesh piece by piece (``engine.isosurface.stream``, ``engine.decimation.tiles``)."""

from __future__ import annotations

import warp as wp

from engine.decimation.kernels.quadrics import quadric


@wp.kernel
def localize_faces(
    faces: wp.array(dtype=wp.vec3i),
    v0: int,
    n_foreign: int,
    fmin: int,
    fmap: wp.array(dtype=wp.int32),
):
    """A group of slabs' faces in its local numbering: the group's own vertices (ids ``v0`` ..) after the
    ``n_foreign`` vertices it shares with the slab below (ids ``fmin`` .. ``v0``, numbered by ``fmap``)."""
    f = wp.tid()
    t = faces[f]
    out = wp.vec3i(0, 0, 0)
    for k in range(3):
        v = t[k]
        if v >= v0:
            out[k] = v - v0 + n_foreign
        else:
            out[k] = fmap[v - fmin]
    faces[f] = out


@wp.kernel
def globalize_faces(faces: wp.array(dtype=wp.vec3i), n_foreign: int, foreign_out: wp.array(dtype=wp.int32), base: int):
    """A decimated group's faces in the output's numbering: its first ``n_foreign`` vertices are shared with the
    group below (ids ``foreign_out``), the others follow the output's vertices so far (``base`` + row)."""
    f = wp.tid()
    t = faces[f]
    out = wp.vec3i(0, 0, 0)
    for k in range(3):
        v = t[k]
        if v < n_foreign:
            out[k] = foreign_out[v]
        else:
            out[k] = v + base
    faces[f] = out


@wp.kernel
def add_quadrics(ids: wp.array(dtype=wp.int32), shares: wp.array(dtype=quadric), quad: wp.array(dtype=quadric)):
    """Each shared vertex's quadric gets the other side's share (the ids are distinct)."""
    i = wp.tid()
    quad[ids[i]] = quad[ids[i]] + shares[i]


# ------------------------------------------------------------------------------------------------ seam pass
@wp.kernel
def seam_flags(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    borders: wp.array(dtype=wp.float32),
    n_borders: int,
    width: float,
    flag: wp.array(dtype=wp.int32),
):
    """1 for a face whose first vertex lies within ``width`` (mm, in z) of one of the ``n_borders`` borders, else 0."""
    f = wp.tid()
    z = pos[faces[f][0]][0]
    near = wp.int32(0)
    for i in range(n_borders):
        if wp.abs(z - borders[i]) <= width:
            near = wp.int32(1)
    flag[f] = near


@wp.kernel
def range_flags(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    axis: int,
    lo: float,
    hi: float,
    flag: wp.array(dtype=wp.int32),
):
    """1 for a face whose first vertex's coordinate ``axis`` lies in [lo, hi), else 0 (a tile along that axis)."""
    f = wp.tid()
    c = pos[faces[f][0]][axis]
    flag[f] = wp.where(c >= lo and c < hi, 1, 0)


@wp.kernel
def face_sample(
    pos: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.vec3i), stride: int, out: wp.array(dtype=wp.vec3)
):
    """The first vertex of every ``stride``-th face (where to cut the tiles)."""
    i = wp.tid()
    out[i] = pos[faces[i * stride][0]]


@wp.kernel
def mark_used(
    faces: wp.array(dtype=wp.vec3i), flag: wp.array(dtype=wp.int32), want: int, used: wp.array(dtype=wp.int32)
):
    """``used[v] = 1`` for the vertices of the faces whose flag is ``want``."""
    f = wp.tid()
    if flag[f] == want:
        t = faces[f]
        used[t[0]] = 1
        used[t[1]] = 1
        used[t[2]] = 1


@wp.kernel
def split_faces(
    faces: wp.array(dtype=wp.vec3i),
    flag: wp.array(dtype=wp.int32),
    slot: wp.array(dtype=wp.int32),
    vslot: wp.array(dtype=wp.int32),
    seam: wp.array(dtype=wp.vec3i),
    rest: wp.array(dtype=wp.vec3i),
):
    """Seam faces (flag 1, at ``slot``) in the seam's local numbering (``vslot``); the others (at ``f - slot``) as
    they are."""
    f = wp.tid()
    t = faces[f]
    if flag[f] == 1:
        seam[slot[f]] = wp.vec3i(vslot[t[0]], vslot[t[1]], vslot[t[2]])
    else:
        rest[f - slot[f]] = t


@wp.kernel
def gather_seam(
    pos: wp.array(dtype=wp.vec3),
    in_seam: wp.array(dtype=wp.int32),
    in_rest: wp.array(dtype=wp.int32),
    vslot: wp.array(dtype=wp.int32),
    vids: wp.array(dtype=wp.int32),
    local_pos: wp.array(dtype=wp.vec3),
    lock: wp.array(dtype=wp.int32),
):
    """The seam's vertices: positions, global ids, and pinned where a face outside the seam uses them too."""
    v = wp.tid()
    if in_seam[v] != 0:
        i = vslot[v]
        vids[i] = v
        local_pos[i] = pos[v]
        lock[i] = in_rest[v]


@wp.kernel
def new_vertex_flags(kept: wp.array(dtype=wp.int32), lock: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    i = wp.tid()
    flag[i] = 1 - wp.min(lock[kept[i]], 1)


@wp.kernel
def join_seam(
    out_pos: wp.array(dtype=wp.vec3),
    kept: wp.array(dtype=wp.int32),
    lock: wp.array(dtype=wp.int32),
    vids: wp.array(dtype=wp.int32),
    new_slot: wp.array(dtype=wp.int32),
    n_old: int,
    out_id: wp.array(dtype=wp.int32),
    new_pos: wp.array(dtype=wp.vec3),
):
    """Each decimated seam vertex's id in the joined mesh: a pinned one keeps its own, a new one follows the old
    vertices (and its position goes to ``new_pos``)."""
    i = wp.tid()
    k = kept[i]
    if lock[k] != 0:
        out_id[i] = vids[k]
    else:
        out_id[i] = n_old + new_slot[i]
        new_pos[new_slot[i]] = out_pos[i]
