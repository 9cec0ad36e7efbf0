"""Warp kernels of a device mesh's topology: every vertex's star (the faces around it) as sorted CSR, and each
vertex's class (host side: ``engine.surface.devmesh``). OpenCL C twins: ``topology.cl``.

The mesh lives on the device as ``pos`` (V) ``vec3`` (z, y, x) mm and ``faces`` (F) ``vec3i``; a removed face is
``(-1, -1, -1)``. Stars are sorted per vertex, so that every later sum over a star runs in a fixed order (the
results are deterministic).
"""

from __future__ import annotations

import warp as wp

FREE = wp.constant(0)  # interior vertex with one closed fan of faces: may move or be removed
BORDER = wp.constant(1)  # on an open border with one open fan: never moves, may absorb a free neighbour
LOCKED = wp.constant(2)  # non-manifold, inconsistently wound or degenerate surroundings: never touched
DEAD = wp.constant(3)  # collapsed away, or used by no face


@wp.func
def next_of(t: wp.vec3i, v: int) -> int:
    """The vertex after ``v`` in face ``t`` (its winding)."""
    r = t[0]
    if t[0] == v:
        r = t[1]
    elif t[1] == v:
        r = t[2]
    return r


@wp.func
def prev_of(t: wp.vec3i, v: int) -> int:
    r = t[1]
    if t[0] == v:
        r = t[2]
    elif t[1] == v:
        r = t[0]
    return r


@wp.func
def has_vertex(t: wp.vec3i, v: int) -> bool:
    return t[0] == v or t[1] == v or t[2] == v


@wp.kernel
def count_incidence(faces: wp.array(dtype=wp.vec3i), count: wp.array(dtype=wp.int32)):
    f = wp.tid()
    t = faces[f]
    if t[0] >= 0:
        wp.atomic_add(count, t[0], 1)
        wp.atomic_add(count, t[1], 1)
        wp.atomic_add(count, t[2], 1)


@wp.kernel
def fill_incidence(
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    cursor: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
):
    f = wp.tid()
    t = faces[f]
    if t[0] >= 0:
        for k in range(3):
            v = t[k]
            slot = wp.atomic_add(cursor, v, 1)
            star[offset[v] + slot] = f


@wp.kernel
def sort_incidence(offset: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), star: wp.array(dtype=wp.int32)):
    """Insertion sort of each star (short lists) so that results do not depend on the fill's atomic order."""
    v = wp.tid()
    lo = offset[v]
    n = count[v]
    for i in range(1, n):
        x = star[lo + i]
        j = int(i - 1)
        while j >= 0:
            y = star[lo + j]
            if y > x:
                star[lo + j + 1] = y
                j -= 1
            else:
                break
        star[lo + j + 1] = x


@wp.kernel
def classify_vertices(
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
):
    """FREE (one closed fan), BORDER (one open fan), LOCKED (anything else) or DEAD (no face)."""
    v = wp.tid()
    n = count[v]
    if n == 0:
        state[v] = DEAD
        return
    lo = offset[v]
    bad = int(0)
    open_fwd = int(0)
    open_bwd = int(0)
    start = int(0)
    for i in range(n):
        t = faces[star[lo + i]]
        if t[0] == t[1] or t[1] == t[2] or t[0] == t[2]:
            bad = 1
        nx = next_of(t, v)
        pv = prev_of(t, v)
        same_next = int(0)
        same_prev = int(0)
        fwd = int(0)  # faces across the edge v-nx (they run nx -> v)
        bwd = int(0)  # faces across the edge v-pv (they run v -> pv)
        for j in range(n):
            u = faces[star[lo + j]]
            nj = next_of(u, v)
            pj = prev_of(u, v)
            if nj == nx:
                same_next += 1
            if pj == pv:
                same_prev += 1
            if pj == nx:
                fwd += 1
            if nj == pv:
                bwd += 1
        if same_next != 1 or same_prev != 1 or fwd > 1 or bwd > 1:
            bad = 1
        if fwd == 0:
            open_fwd += 1
        if bwd == 0:
            open_bwd += 1
            start = i
    if bad != 0 or open_fwd > 1 or open_fwd != open_bwd:
        state[v] = LOCKED
        return
    # walk the fan from its start: it must visit every face (one fan only)
    i = int(start)
    steps = int(0)
    while steps < n:
        steps += 1
        nx = next_of(faces[star[lo + i]], v)
        found = int(-1)
        for j in range(n):
            if prev_of(faces[star[lo + j]], v) == nx:
                found = j
        if found < 0 or found == start:
            break
        i = found
    if steps != n:
        state[v] = LOCKED
    elif open_fwd == 0:
        state[v] = FREE
    else:
        state[v] = BORDER


@wp.kernel
def count_classes(state: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32)):
    """How many vertices of each class but FREE (``counts`` has one slot per class, zeroed by the caller; the
    caller takes FREE's as the rest): four numbers come back to the host instead of a class per vertex, and the
    common class adds to no counter (every vertex adding to one address cost more than classifying them)."""
    c = state[wp.tid()]
    if c != FREE:
        wp.atomic_add(counts, c, 1)
