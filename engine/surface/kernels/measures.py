"""Warp kernels that measure a device mesh (host side: ``engine.surface.devmesh``, ``engine.surface.islands``):
the edge census (borders, non-manifold and inconsistently wound edges), face volumes and areas, and connected
pieces (min-label hooking with pointer jumping), their volumes and their removal. OpenCL C twins: ``measures.cl``.
"""

from __future__ import annotations

import warp as wp

from engine.surface.kernels.topology import has_vertex, next_of, prev_of


@wp.func
def xyz64(p: wp.vec3) -> wp.vec3d:
    """A (z, y, x) position as float64 (x, y, z), the frame in which outward faces have positive volume."""
    return wp.vec3d(wp.float64(p[2]), wp.float64(p[1]), wp.float64(p[0]))


@wp.kernel
def edge_census(
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    totals: wp.array(dtype=wp.int64),
):
    """Per vertex v, over its distinct neighbours w > v: edges, edges in one face (border), in three or more
    (non-manifold), and in two faces that run them the same way (inconsistent); summed into ``totals[0..3]``."""
    v = wp.tid()
    lo = offset[v]
    n = count[v]
    edges = int(0)
    border = int(0)
    nonmanifold = int(0)
    inconsistent = int(0)
    for i in range(n):
        t = faces[star[lo + i]]
        for side in range(2):
            w = next_of(t, v)
            if side == 1:
                w = prev_of(t, v)
            if w <= v or w == v:
                continue
            seen = int(0)
            for j in range(i):
                if has_vertex(faces[star[lo + j]], w):
                    seen = 1
            if side == 1 and next_of(t, v) == w:
                seen = 1
            if seen != 0:
                continue
            c = int(0)
            fwd = int(0)
            for j in range(n):
                u = faces[star[lo + j]]
                if has_vertex(u, w):
                    c += 1
                    if next_of(u, v) == w:
                        fwd += 1
            edges += 1
            if c == 1:
                border += 1
            elif c > 2:
                nonmanifold += 1
            elif fwd != 1:
                inconsistent += 1
    if edges > 0:  # one total that every thread adds to; the faults' only where there are some (a sound mesh
        wp.atomic_add(totals, 0, wp.int64(edges))  # has none: three atomics on one address per vertex saved)
    if border > 0:
        wp.atomic_add(totals, 1, wp.int64(border))
    if nonmanifold > 0:
        wp.atomic_add(totals, 2, wp.int64(nonmanifold))
    if inconsistent > 0:
        wp.atomic_add(totals, 3, wp.int64(inconsistent))


@wp.kernel
def face_measures(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    first: int,
    volume: wp.array(dtype=wp.float64),
    area: wp.array(dtype=wp.float64),
    degenerate: wp.array(dtype=wp.float64),
):
    """Per face ``first + f``, into slot ``f``: signed volume a.(b x c)/6 with vertices in (x, y, z) order, area,
    and whether a vertex repeats."""
    f = wp.tid()
    t = faces[first + f]
    a = xyz64(pos[t[0]])
    b = xyz64(pos[t[1]])
    c = xyz64(pos[t[2]])
    volume[f] = wp.dot(a, wp.cross(b, c)) / wp.float64(6.0)
    area[f] = wp.float64(0.5) * wp.length(wp.cross(b - a, c - a))
    degenerate[f] = wp.float64(0.0)
    if t[0] == t[1] or t[1] == t[2] or t[0] == t[2]:
        degenerate[f] = wp.float64(1.0)


@wp.kernel
def run_sums(values: wp.array(dtype=wp.float64), n: int, run: int, out: wp.array(dtype=wp.float64)):
    """The sum of every run ``[r * run, min((r + 1) * run, n))`` of ``values``, in order, into ``out[r]`` (a
    deterministic reduction: the host adds the runs in order)."""
    r = wp.tid()
    lo = r * run
    hi = wp.min(lo + run, n)
    s = wp.float64(0.0)
    for k in range(lo, hi):
        s = s + values[k]
    out[r] = s


@wp.kernel
def hook_labels(faces: wp.array(dtype=wp.vec3i), label: wp.array(dtype=wp.int32), changed: wp.array(dtype=wp.int32)):
    """Connected components: every face pulls its vertices' labels, and their roots, down to the smallest."""
    f = wp.tid()
    t = faces[f]
    m = wp.min(wp.min(label[t[0]], label[t[1]]), label[t[2]])
    for k in range(3):
        r = label[t[k]]
        if r > m:
            wp.atomic_min(label, r, m)
            wp.atomic_min(label, t[k], m)
            changed[0] = 1


@wp.kernel
def own_labels(label: wp.array(dtype=wp.int32)):
    """Every vertex its own piece (made on the device: no volume-sized copy up)."""
    v = wp.tid()
    label[v] = v


@wp.kernel
def jump_labels(label: wp.array(dtype=wp.int32)):
    """Pointer jumping: every labelled entry's label becomes its chain's root (a negative label: none, left)."""
    v = wp.tid()
    r = label[v]
    if r >= 0:
        while label[r] != r:
            r = label[r]
        label[v] = r


@wp.kernel
def count_roots(label: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), roots: wp.array(dtype=wp.int32)):
    v = wp.tid()
    if count[v] > 0 and label[v] == v:
        wp.atomic_add(roots, 0, 1)


@wp.kernel
def piece_volumes(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    label: wp.array(dtype=wp.int32),
    n_faces: int,
    run: int,
    volume: wp.array(dtype=wp.float64),
    nfaces: wp.array(dtype=wp.int32),
):
    """Signed volume (vertices in (x, y, z) order) and face count of every piece, at its root vertex: each thread
    takes a run of ``run`` faces and adds once per change of piece (neighbouring faces mostly share one: few
    atomics on the big pieces' roots)."""
    r = wp.tid()
    lo = r * run
    hi = wp.min(lo + run, n_faces)
    cur = int(-1)
    acc = wp.float64(0.0)
    cnt = int(0)
    for f in range(lo, hi):
        t = faces[f]
        root = label[t[0]]
        if root != cur:
            if cur >= 0:
                wp.atomic_add(volume, cur, acc)
                wp.atomic_add(nfaces, cur, cnt)
            cur = root
            acc = wp.float64(0.0)
            cnt = 0
        a = xyz64(pos[t[0]])
        acc = acc + wp.dot(a, wp.cross(xyz64(pos[t[1]]), xyz64(pos[t[2]]))) / wp.float64(6.0)
        cnt = cnt + 1
    if cur >= 0:
        wp.atomic_add(volume, cur, acc)
        wp.atomic_add(nfaces, cur, cnt)


@wp.kernel
def drop_pieces(faces: wp.array(dtype=wp.vec3i), label: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32)):
    f = wp.tid()
    if keep[label[faces[f][0]]] == 0:
        faces[f] = wp.vec3i(-1, -1, -1)
