"""Warp kernels for decimating a mesh piece by piece (``engine.stages.stream``, ``engine.stages.tiled``)."""

from __future__ import annotations

import warp as wp

from engine.kernels.decimate import quadric


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
def lock_plane(plane: wp.array3d(dtype=wp.int32), v0: int, n_foreign: int, lock: wp.array(dtype=wp.int32)):
    """Pin the group's own vertices that lie on its top plane (shared with the next slab)."""
    a, y, x = wp.tid()
    v = plane[a, y, x]
    if v >= v0:
        lock[v - v0 + n_foreign] = 1


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
