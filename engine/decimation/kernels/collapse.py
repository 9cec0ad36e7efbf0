"""Warp kernels that perform a decimation pass's collapses (host side: ``engine.decimation.phases``): the survivor
moves and takes both quadrics (``Q_s += Q_r``), the removed vertex's star is rewritten; and the pinning of vertices
that no collapse may touch.
"""

from __future__ import annotations

import warp as wp

from engine.decimation.kernels.costs import edge_ends, listed
from engine.decimation.kernels.quadrics import quadric
from engine.surface.kernels.topology import BORDER, DEAD, FREE, LOCKED, has_vertex


@wp.kernel
def apply_collapses(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    target: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    quad: wp.array(dtype=quadric),
    pos: wp.array(dtype=wp.vec3),
    removed_faces: wp.array(dtype=wp.int32),
    dirty: wp.array(dtype=wp.int32),
):
    """Collapse every winner: the survivor takes the position and both quadrics, the removed vertex's star is
    rewritten. Marks dirty exactly the vertices whose edges may price or check differently now: the survivor and
    its new neighbours (every vertex of the two old stars: their stars, or the survivor's position, quadric and face
    count, changed) and the neighbours of the two opposite vertices (each lost a face, and an edge reads the face
    counts of the vertices opposite it)."""
    h = listed(listing, n_listed, cand, 2, wp.tid())
    if h < 0:
        return
    ends = edge_ends(faces, h)
    a = ends[0]
    b = ends[1]
    s = a
    r = b
    if state[b] == BORDER:
        s = b
        r = a
    if state[a] == FREE and state[b] == FREE:
        pos[s] = target[h]  # a border survivor keeps its position bit for bit
    quad[s] = quad[s] + quad[r]
    state[r] = DEAD
    opposite = wp.vec2i(-1, -1)
    n_opp = int(0)
    lo = offset[r]
    for i in range(count[r]):
        fi = star[lo + i]
        u = faces[fi]
        if has_vertex(u, s):
            if n_opp < 2:
                opposite[n_opp] = u[0] + u[1] + u[2] - r - s
            n_opp += 1
            faces[fi] = wp.vec3i(-1, -1, -1)
            wp.atomic_add(removed_faces, 0, 1)
        else:
            for j in range(3):
                if u[j] == r:
                    u[j] = s
            faces[fi] = u
    # another winner may be rewriting a face of an opposite vertex's star: each index is checked (an old index is
    # that winner's removed vertex, whose replacement that winner marks itself)
    for e in range(4):
        c = -1
        if e < 2:
            c = ends[e]
        else:
            c = opposite[e - 2]
        if c >= 0:
            for i in range(count[c]):
                u = faces[star[offset[c] + i]]
                for j in range(3):
                    if u[j] >= 0:
                        dirty[u[j]] = 1


@wp.kernel
def lock_vertices(lock: wp.array(dtype=wp.int32), state: wp.array(dtype=wp.int32)):
    """Vertices the caller pins (a tile's border): LOCKED, so no collapse moves, removes or extends them."""
    v = wp.tid()
    if lock[v] != 0 and state[v] != DEAD:
        state[v] = LOCKED
