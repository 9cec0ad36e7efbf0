"""Warp kernels of Marching Cubes 33: block classification, per-cell counting and emission.

No host logic lives here (see ``engine.isosurface.mc33``); ``mc33.cl`` holds the same kernels in OpenCL C, the
same arithmetic (named in ``engine.isosurface.kernel_specs``; the blocks' compaction is the backend's). Conventions
for corners, edges, faces and cell keys are those of ``engine.isosurface._make_mc33_tables``.

Grid bookkeeping: cells are indexed by their lowest corner (``origin``), from -1 to ``n - 1`` along every axis,
so that with ``closed=True`` the cells half outside the array close the surface. Samples outside the array have
the value ``pad`` (below the level). Each grid edge has one owner cell: the x and y edges of sample plane ``z``
belong to the cell at ``z - 1`` that has them on its top face, a z edge to the cell whose origin starts it. An
owner cell numbers its vertices as [x edge, y edge, z edge (each if cut), interior vertices]. Cells are grouped
in blocks of ``BLOCK``^3; only blocks whose samples straddle the level are visited.
"""

from __future__ import annotations

from typing import Any

import warp as wp

BLOCK = 8
BLOCK_CELLS = BLOCK * BLOCK * BLOCK

vec8f = wp.types.vector(length=8, dtype=wp.float32)
vec12f = wp.types.vector(length=12, dtype=wp.float32)
vec12i = wp.types.vector(length=12, dtype=wp.int32)


@wp.struct
class Grid:
    """Geometry of the current slab (all z values are global sample/cell coordinates)."""

    nz: int
    ny: int
    nx: int
    zoff: int  # global z of plane 0 of the slab array
    bz0: int  # first block layer of the slab
    nbz: int  # block layers in the slab
    nby: int
    nbx: int
    cz_first: int  # first cell layer of the slab (owners below it are in plane_prev)
    level: float
    pad: float
    closed: int
    tau: float
    sz: float
    sy: float
    sx: float


@wp.func
def inside(g: Grid, z: int, y: int, x: int) -> bool:
    return z >= 0 and z < g.nz and y >= 0 and y < g.ny and x >= 0 and x < g.nx


@wp.func
def sample(vol: wp.array3d(dtype=Any), g: Grid, z: int, y: int, x: int) -> float:
    """Value minus level; ``pad`` outside the array."""
    s = g.pad
    if inside(g, z, y, x):
        s = float(vol[z - g.zoff, y, x]) - g.level
    return s


@wp.func
def corner_dz(c: int) -> int:
    return (c >> 2) & 1


@wp.func
def corner_dy(c: int) -> int:
    return (c >> 1) & 1


@wp.func
def corner_dx(c: int) -> int:
    return c & 1


@wp.func
def edge_c0(e: int) -> int:
    c = 0
    if e < 4:
        c = 2 * (e & 1) + 4 * (e >> 1)
    elif e < 8:
        c = ((e - 4) & 1) + 4 * ((e - 4) >> 1)
    else:
        c = ((e - 8) & 1) + 2 * ((e - 8) >> 1)
    return c


@wp.func
def edge_step(e: int) -> int:
    step = 4
    if e < 4:
        step = 1
    elif e < 8:
        step = 2
    return step


@wp.func
def cell_values(vol: wp.array3d(dtype=Any), g: Grid, oz: int, oy: int, ox: int) -> vec8f:
    v = vec8f()
    for c in range(8):
        v[c] = sample(vol, g, oz + corner_dz(c), oy + corner_dy(c), ox + corner_dx(c))
    return v


@wp.func
def cell_config(v: vec8f) -> int:
    cfg = int(0)
    for c in range(8):
        if v[c] >= 0.0:
            cfg = cfg | (1 << c)
    return cfg


@wp.func
def corner_inside(g: Grid, oz: int, oy: int, ox: int, c: int) -> bool:
    return inside(g, oz + corner_dz(c), oy + corner_dy(c), ox + corner_dx(c))


@wp.func
def edge_cut(g: Grid, v: vec8f, oz: int, oy: int, ox: int, e: int) -> int:
    c0 = edge_c0(e)
    c1 = c0 + edge_step(e)
    cut = 0
    if (v[c0] >= 0.0) != (v[c1] >= 0.0):
        if g.closed != 0 or (corner_inside(g, oz, oy, ox, c0) and corner_inside(g, oz, oy, ox, c1)):
            cut = 1
    return cut


@wp.func
def face_bits(v: vec8f, face_cyc: wp.array(dtype=wp.int32)) -> int:
    """Asymptotic decider on the ambiguous faces: bit f set when the positive diagonal is joined.

    A saddle exactly at the level joins the positive diagonal: like samples at the level, it counts as above
    (the limit of lowering the level by an infinitesimal amount).
    """
    bits = int(0)
    for f in range(6):
        a = v[face_cyc[4 * f + 0]]
        b = v[face_cyc[4 * f + 1]]
        c = v[face_cyc[4 * f + 2]]
        d = v[face_cyc[4 * f + 3]]
        pa = a >= 0.0
        pb = b >= 0.0
        if pa == (c >= 0.0) and pb == (d >= 0.0) and pa != pb:
            joined = False
            if pa:
                joined = a * c >= b * d
            else:
                joined = b * d >= a * c
            if joined:
                bits = bits | (1 << f)
    return bits


@wp.func
def body_bits(v: vec8f) -> int:
    """Interior joins found by sweeping z: the slice saddle value q(t) is a parabola; its vertex decides.

    Along z the four vertical edges A (corners 0/4), B (1/5), C (3/7), D (2/6) are linear in t; where the slice
    alternates in sign, its positive diagonal is joined iff q(t) = a c - b d >= 0 (A, C positive). A join that
    exists only inside the cell needs the parabola's vertex strictly inside (0, 1) with the slice alternating
    there: a maximum q >= 0 joins the positive diagonal, a minimum q < 0 the negative one. Anything else is
    already decided on the faces. Values at the level count as above it, as everywhere.
    """
    a0 = v[0]
    a1 = v[4]
    b0 = v[1]
    b1 = v[5]
    c0 = v[3]
    c1 = v[7]
    d0 = v[2]
    d1 = v[6]
    da = a1 - a0
    db = b1 - b0
    dc = c1 - c0
    dd = d1 - d0
    alpha = da * dc - db * dd
    beta = a0 * dc + c0 * da - b0 * dd - d0 * db
    bits = int(0)
    if alpha != 0.0:
        t = -beta / (2.0 * alpha)
        if t > 0.0 and t < 1.0:
            a = a0 + t * da
            b = b0 + t * db
            c = c0 + t * dc
            d = d0 + t * dd
            if a >= 0.0 and c >= 0.0 and b < 0.0 and d < 0.0:
                q = a * c - b * d
                if alpha < 0.0 and q >= 0.0:
                    bits = 1  # positive A-C
                elif alpha > 0.0 and q < 0.0:
                    bits = 8  # negative B-D
            elif a < 0.0 and c < 0.0 and b >= 0.0 and d >= 0.0:
                q2 = b * d - a * c
                if alpha > 0.0 and q2 >= 0.0:
                    bits = 2  # positive B-D
                elif alpha < 0.0 and q2 < 0.0:
                    bits = 4  # negative A-C
    return bits


@wp.func
def cell_triangulation(
    g: Grid,
    v: vec8f,
    cfg: int,
    oz: int,
    oy: int,
    ox: int,
    face_cyc: wp.array(dtype=wp.int32),
    key_map: wp.array(dtype=wp.int32),
) -> int:
    """Table entry of a cell. Outside samples are infinitely far below the level: faces that touch them are
    never ambiguous and, in that limit, no interior join exists in a cell that touches them."""
    key = cfg | (face_bits(v, face_cyc) << 8)
    if inside(g, oz, oy, ox) and inside(g, oz + 1, oy + 1, ox + 1):
        key = key | (body_bits(v) << 14)
    return key_map[key]


@wp.func
def emits(g: Grid, oz: int, oy: int, ox: int, cfg: int) -> bool:
    ok = cfg != 0 and cfg != 255
    if ok and g.closed == 0:
        ok = oz >= 0 and oy >= 0 and ox >= 0 and oz + 1 < g.nz and oy + 1 < g.ny and ox + 1 < g.nx
    return ok


@wp.func
def slot_origin(g: Grid, alist: wp.array(dtype=wp.int32), slot: int) -> wp.vec3i:
    b = alist[slot // BLOCK_CELLS]
    local = slot % BLOCK_CELLS
    bx = b % g.nbx
    by = (b // g.nbx) % g.nby
    bz = b // (g.nbx * g.nby) + g.bz0
    oz = bz * BLOCK + local // (BLOCK * BLOCK) - 1
    oy = by * BLOCK + (local // BLOCK) % BLOCK - 1
    ox = bx * BLOCK + local % BLOCK - 1
    return wp.vec3i(oz, oy, ox)


@wp.func
def owned_cuts(g: Grid, v: vec8f, oz: int, oy: int, ox: int) -> wp.vec3i:
    """Cut flags of the edges a cell owns: top-face x edge (2), top-face y edge (6), z edge (8)."""
    return wp.vec3i(edge_cut(g, v, oz, oy, ox, 2), edge_cut(g, v, oz, oy, ox, 6), edge_cut(g, v, oz, oy, ox, 8))


@wp.kernel
def block_kernel(
    vol: wp.array3d(dtype=Any),
    g: Grid,
    active: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """Mark blocks whose samples (pad included when closed) straddle the level; note signs seen in the array."""
    b = wp.tid()
    bx = b % g.nbx
    by = (b // g.nbx) % g.nby
    bz = b // (g.nbx * g.nby) + g.bz0
    z0 = bz * BLOCK - 1
    y0 = by * BLOCK - 1
    x0 = bx * BLOCK - 1
    pos = int(0)
    neg = int(0)
    outside = int(0)
    z1 = wp.min(z0 + BLOCK, g.nz)
    y1 = wp.min(y0 + BLOCK, g.ny)
    x1 = wp.min(x0 + BLOCK, g.nx)
    if z0 < 0 or y0 < 0 or x0 < 0 or z0 + BLOCK >= g.nz or y0 + BLOCK >= g.ny or x0 + BLOCK >= g.nx:
        outside = 1
    for z in range(wp.max(z0, 0), z1 + 1):
        if pos == 1 and neg == 1:
            break
        for y in range(wp.max(y0, 0), y1 + 1):
            for x in range(wp.max(x0, 0), x1 + 1):
                if z < g.nz and y < g.ny and x < g.nx:
                    if float(vol[z - g.zoff, y, x]) - g.level >= 0.0:
                        pos = 1
                    else:
                        neg = 1
    if pos == 1:
        flags[1] = 1
    if neg == 1:
        flags[0] = 1
    if outside == 1 and g.closed != 0:
        neg = 1
    active[b] = pos * neg


@wp.kernel
def nan_kernel(vol: wp.array3d(dtype=wp.float32), flags: wp.array(dtype=wp.int32)):
    z, y, x = wp.tid()
    if wp.isnan(vol[z, y, x]):
        flags[2] = 1


@wp.func
def pack_code(tid: int, mask: int) -> int:
    return (tid + 1) | (mask << 16)


@wp.func
def code_tri(c: int) -> int:
    return (c & 0xFFFF) - 1


@wp.func
def code_mask(c: int) -> int:
    return c >> 16


@wp.func
def owner_slot(g: Grid, bmap: wp.array(dtype=wp.int32), oz: int, oy: int, ox: int) -> int:
    cz = oz + 1
    cy = oy + 1
    cx = ox + 1
    b = ((cz // BLOCK - g.bz0) * g.nby + cy // BLOCK) * g.nbx + cx // BLOCK
    local = ((cz % BLOCK) * BLOCK + (cy % BLOCK)) * BLOCK + (cx % BLOCK)
    return bmap[b] * BLOCK_CELLS + local


@wp.kernel
def count_kernel(
    vol: wp.array3d(dtype=Any),
    g: Grid,
    alist: wp.array(dtype=wp.int32),
    face_cyc: wp.array(dtype=wp.int32),
    key_map: wp.array(dtype=wp.int32),
    tri_count: wp.array(dtype=wp.int32),
    ivert_count: wp.array(dtype=wp.int32),
    vcount: wp.array(dtype=wp.int32),
    tcount: wp.array(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """Per cell: vertices it owns, triangles it emits, and its code (table entry + 1, owned-cut mask << 16)."""
    slot = wp.tid()
    o = slot_origin(g, alist, slot)
    nv = int(0)
    nt = int(0)
    tid = int(-1)
    mask = int(0)
    if o[0] < g.nz and o[1] < g.ny and o[2] < g.nx:
        v = cell_values(vol, g, o[0], o[1], o[2])
        cfg = cell_config(v)
        cuts = owned_cuts(g, v, o[0], o[1], o[2])
        nv = cuts[0] + cuts[1] + cuts[2]
        mask = cuts[0] | (cuts[1] << 1) | (cuts[2] << 2)
        if emits(g, o[0], o[1], o[2], cfg):
            tid = cell_triangulation(g, v, cfg, o[0], o[1], o[2], face_cyc, key_map)
            if tid < 0:
                flags[3] = 1  # key outside the generated tables: should never happen
                tid = key_map[cfg]
            nt = tri_count[tid]
            nv = nv + ivert_count[tid]
    vcount[slot] = nv
    tcount[slot] = nt
    code[slot] = pack_code(tid, mask)


@wp.func
def owner_vertex(
    g: Grid,
    bmap: wp.array(dtype=wp.int32),
    voff: wp.array(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    plane_prev: wp.array3d(dtype=wp.int32),
    vstart: int,
    oz: int,
    oy: int,
    ox: int,
    kind: int,
) -> int:
    """Global id of the vertex on edge ``kind`` (0 x, 1 y, 2 z) owned by the cell at origin (oz, oy, ox)."""
    vid = int(-1)
    if oz < g.cz_first:
        vid = plane_prev[kind, oy + 1, ox + 1]
    else:
        slot = owner_slot(g, bmap, oz, oy, ox)
        mask = code_mask(code[slot])
        rank = int(0)
        if kind >= 1:
            rank = rank + (mask & 1)
        if kind >= 2:
            rank = rank + ((mask >> 1) & 1)
        vid = vstart + voff[slot] + rank
    return vid


@wp.func
def edge_point(g: Grid, v: vec8f, oz: int, oy: int, ox: int, e: int) -> wp.vec3:
    """Point where the level crosses edge e, as (z, y, x) in mm."""
    c0 = edge_c0(e)
    c1 = c0 + edge_step(e)
    t = 0.5
    if corner_inside(g, oz, oy, ox, c0) and corner_inside(g, oz, oy, ox, c1):
        t = wp.clamp(v[c0] / (v[c0] - v[c1]), g.tau, 1.0 - g.tau)
    z = float(oz + corner_dz(c0))
    y = float(oy + corner_dy(c0))
    x = float(ox + corner_dx(c0))
    if e < 4:
        x = x + t
    elif e < 8:
        y = y + t
    else:
        z = z + t
    return wp.vec3(z * g.sz, y * g.sy, x * g.sx)


@wp.func
def edge_owner_vertex(
    g: Grid,
    bmap: wp.array(dtype=wp.int32),
    voff: wp.array(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    plane_prev: wp.array3d(dtype=wp.int32),
    vstart: int,
    oz: int,
    oy: int,
    ox: int,
    e: int,
) -> int:
    """Global id of the vertex on edge e of the cell at (oz, oy, ox), found at the edge's owner."""
    kind = e // 4
    lo = (e % 4) & 1
    hi = (e % 4) >> 1
    wz = oz
    wy = oy
    wx = ox
    if kind == 0:
        wz = oz + hi - 1
        wy = oy + lo
    elif kind == 1:
        wz = oz + hi - 1
        wx = ox + lo
    else:
        wx = ox + lo
        wy = oy + hi
    return owner_vertex(g, bmap, voff, code, plane_prev, vstart, wz, wy, wx, kind)


@wp.func
def local_to_global(ids: vec12i, gbase: int, loc: int) -> int:
    r = gbase + loc - 12
    if loc < 12:
        r = ids[loc]
    return r


@wp.kernel
def emit_kernel(
    vol: wp.array3d(dtype=Any),
    g: Grid,
    alist: wp.array(dtype=wp.int32),
    bmap: wp.array(dtype=wp.int32),
    voff: wp.array(dtype=wp.int32),
    toff: wp.array(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    plane_prev: wp.array3d(dtype=wp.int32),
    vstart: int,
    tri_offset: wp.array(dtype=wp.int32),
    tri_count: wp.array(dtype=wp.int32),
    tri_local: wp.array(dtype=wp.int32),
    ivert_offset: wp.array(dtype=wp.int32),
    ivert_count: wp.array(dtype=wp.int32),
    ivert_weights: wp.array(dtype=wp.float32),
    verts: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
):
    slot = wp.tid()
    c = code[slot]
    tid = code_tri(c)
    mask = code_mask(c)
    if mask == 0 and tid < 0:
        return
    o = slot_origin(g, alist, slot)
    oz = o[0]
    oy = o[1]
    ox = o[2]
    v = cell_values(vol, g, oz, oy, ox)
    base = voff[slot]
    rank = int(0)
    if (mask & 1) != 0:
        verts[base + rank] = edge_point(g, v, oz, oy, ox, 2)
        rank = rank + 1
    if (mask & 2) != 0:
        verts[base + rank] = edge_point(g, v, oz, oy, ox, 6)
        rank = rank + 1
    if (mask & 4) != 0:
        verts[base + rank] = edge_point(g, v, oz, oy, ox, 8)
        rank = rank + 1
    if tid < 0:
        return
    # global ids and positions of the cell's 12 edge points
    ids = vec12i()
    px = vec12f()
    py = vec12f()
    pz = vec12f()
    for e in range(12):
        if edge_cut(g, v, oz, oy, ox, e) != 0:
            pe = edge_point(g, v, oz, oy, ox, e)
            pz[e] = pe[0]
            py[e] = pe[1]
            px[e] = pe[2]
            ids[e] = edge_owner_vertex(g, bmap, voff, code, plane_prev, vstart, oz, oy, ox, e)
    # interior vertices
    ni = ivert_count[tid]
    i0 = ivert_offset[tid]
    for i in range(ni):
        pi = wp.vec3(0.0, 0.0, 0.0)
        for e2 in range(12):
            w = ivert_weights[(i0 + i) * 12 + e2]
            if w != 0.0:
                pi = pi + w * wp.vec3(pz[e2], py[e2], px[e2])
        verts[base + rank + i] = pi
    gbase = vstart + base + rank
    t0 = tri_offset[tid]
    nt = tri_count[tid]
    out = toff[slot]
    for t in range(nt):
        a = local_to_global(ids, gbase, tri_local[3 * (t0 + t) + 0])
        b = local_to_global(ids, gbase, tri_local[3 * (t0 + t) + 1])
        c = local_to_global(ids, gbase, tri_local[3 * (t0 + t) + 2])
        faces[out + t] = wp.vec3i(a, b, c)


@wp.kernel
def plane_kernel(
    g: Grid,
    bmap: wp.array(dtype=wp.int32),
    voff: wp.array(dtype=wp.int32),
    code: wp.array(dtype=wp.int32),
    vstart: int,
    oz: int,
    plane_next: wp.array3d(dtype=wp.int32),
):
    """Ids of the x and y edge vertices of sample plane ``oz + 1`` (owned by cell layer ``oz``), for the next slab."""
    j, i = wp.tid()
    idx = int(-1)
    idy = int(-1)
    b = (((oz + 1) // BLOCK - g.bz0) * g.nby + j // BLOCK) * g.nbx + i // BLOCK
    if bmap[b] >= 0:
        slot = owner_slot(g, bmap, oz, j - 1, i - 1)
        mask = code_mask(code[slot])
        first = vstart + voff[slot]
        if (mask & 1) != 0:
            idx = first
            idy = first + 1
        else:
            idy = first
        if (mask & 2) == 0:
            idy = -1
    plane_next[0, j, i] = idx
    plane_next[1, j, i] = idy
