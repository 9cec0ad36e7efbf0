"""Warp kernels for quadric vertex clustering (host side: ``engine.decimation.cluster``).

Vertices are binned in a grid of cubic cells; each occupied cell becomes one vertex placed where the sum of its
vertices' quadrics is least (inside the cell, else the cell's mean); faces whose three vertices fall in three
different cells survive, once per set of cells. The piece census counts each piece's used vertices.
"""

from __future__ import annotations

import warp as wp

from engine.decimation.kernels.quadrics import q_eval, quadric

CELL_BITS = wp.constant(21)
CELL_MAX = wp.constant(2097151)  # 2^21 - 1 cells per axis


@wp.kernel
def cell_keys(
    pos: wp.array(dtype=wp.vec3),
    lo: wp.vec3,
    inv_h: float,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    v = wp.tid()
    p = (pos[v] - lo) * inv_h
    ix = wp.int64(wp.clamp(int(wp.floor(p[2])), 0, CELL_MAX))
    iy = wp.int64(wp.clamp(int(wp.floor(p[1])), 0, CELL_MAX))
    iz = wp.int64(wp.clamp(int(wp.floor(p[0])), 0, CELL_MAX))
    keys[v] = ix | (iy << wp.int64(21)) | (iz << wp.int64(42))
    values[v] = v


@wp.kernel
def assign_cells(
    flag: wp.array(dtype=wp.int32),
    scan: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    cell_of: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
):
    """Sorted slot i: its vertex's cell is the number of runs started up to i; a run's first slot is its start."""
    i = wp.tid()
    c = scan[i] + flag[i] - 1
    cell_of[order[i]] = c
    if flag[i] == 1:
        start[c] = i


@wp.kernel
def face_cells(
    faces: wp.array(dtype=wp.vec3i),
    cell_of: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3i),
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    """Each face in cells; a face that spans fewer than three cells gets the largest key (sorted last, dropped)."""
    f = wp.tid()
    t = faces[f]
    a = cell_of[t[0]]
    b = cell_of[t[1]]
    c = cell_of[t[2]]
    out[f] = wp.vec3i(a, b, c)
    values[f] = f
    lo = wp.min(wp.min(a, b), c)
    hi = wp.max(wp.max(a, b), c)
    mid = a + b + c - lo - hi
    keys[f] = wp.int64(0x7FFFFFFFFFFFFFFF)
    if a != b and b != c and a != c:
        keys[f] = wp.int64(lo) | (wp.int64(mid) << wp.int64(21)) | (wp.int64(hi) << wp.int64(42))


@wp.kernel
def run_starts(keys: wp.array(dtype=wp.int64), flag: wp.array(dtype=wp.int32)):
    """1 at the first entry of each run of equal sorted keys (sorted stably: the lowest index), 0 for repeats and
    for the dropped (largest) key."""
    i = wp.tid()
    flag[i] = 0
    if keys[i] != wp.int64(0x7FFFFFFFFFFFFFFF):
        if i == 0:
            flag[i] = 1
        elif keys[i] != keys[i - 1]:
            flag[i] = 1


@wp.kernel
def gather_faces(
    flag: wp.array(dtype=wp.int32),
    scan: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    cells: wp.array(dtype=wp.vec3i),
    out: wp.array(dtype=wp.vec3i),
):
    i = wp.tid()
    if flag[i] == 1:
        out[scan[i]] = cells[order[i]]


@wp.kernel
def cell_positions(
    pos: wp.array(dtype=wp.vec3),
    quad: wp.array(dtype=quadric),
    order: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
    n_sorted: int,
    n_cells: int,
    origin: wp.vec3d,
    out: wp.array(dtype=wp.vec3),
):
    """A cell's vertex: the minimiser of its quadric sum (when well defined), kept inside the members' bounding box,
    if it is no worse than the members' mean; else the mean (sums in sorted order: deterministic)."""
    c = wp.tid()
    lo = start[c]
    hi = n_sorted
    if c + 1 < n_cells:
        hi = start[c + 1]
    q = quadric()
    mean = wp.vec3d(0.0, 0.0, 0.0)
    bmin = wp.vec3d(1.0e30, 1.0e30, 1.0e30)
    bmax = wp.vec3d(-1.0e30, -1.0e30, -1.0e30)
    for i in range(lo, hi):
        v = order[i]
        q = q + quad[v]
        p = pos[v]
        pd = wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2])) - origin
        mean = mean + pd
        bmin = wp.min(bmin, pd)
        bmax = wp.max(bmax, pd)
    mean = mean / wp.float64(hi - lo)
    best = wp.vec3d(mean)
    m = wp.mat33d(q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7])
    scale = (q[0] + q[4] + q[7]) / wp.float64(3.0)
    det = wp.determinant(m)
    if scale > wp.float64(0.0) and wp.abs(det) > wp.float64(1.0e-6) * scale * scale * scale:
        x = -(wp.inverse(m) @ wp.vec3d(q[3], q[6], q[8]))
        x = wp.min(wp.max(x, bmin), bmax)  # kept inside the members' box
        if q_eval(q, x) <= q_eval(q, mean):
            best = x
    out[c] = wp.vec3(wp.float32(best[0] + origin[0]), wp.float32(best[1] + origin[1]), wp.float32(best[2] + origin[2]))


@wp.kernel
def piece_vertices(used: wp.array(dtype=wp.int32), label: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32)):
    """The used vertices of every piece (``used``: a vertex's face count), counted at its root."""
    v = wp.tid()
    if used[v] > 0:
        wp.atomic_add(count, label[v], 1)
