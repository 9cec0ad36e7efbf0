"""Warp kernels of a decimation pass's guards (host side: ``engine.decimation.phases``): the link condition, the
opposite vertices' valences, face flips and turns, and degenerate faces, checked for the competing edges only.
"""

from __future__ import annotations

import warp as wp

from engine.decimation.kernels.costs import NO_KEY, below_cut, collapse_cost, cost_code, edge_ends, listed, survivor_of
from engine.decimation.kernels.quadrics import local, quadric
from engine.surface.kernels.topology import BORDER, FREE, has_vertex, next_of

QUALITY_MIN = wp.constant(wp.float64(1.0e-3))  # new faces below this quality are degenerate (unless not worse)
QUALITY_SOFT = wp.constant(wp.float64(0.3))  # below this a collapse's cost is raised (MeshLab's qualitythr)


@wp.func
def quality(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    """2 sqrt(3) |n| / (sum of squared edges): 1 for an equilateral triangle, 0 for a degenerate one."""
    s = wp.length_sq(b - a) + wp.length_sq(c - b) + wp.length_sq(a - c)
    q = wp.float64(0.0)
    if s > wp.float64(0.0):
        q = wp.float64(3.4641016151377544) * wp.length(wp.cross(b - a, c - a)) / s
    return q


@wp.func
def star_turns(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    star: wp.array(dtype=wp.int32),
    lo: int,
    n: int,
    moved: int,
    other: int,
    p: wp.vec3d,
    origin: wp.vec3d,
    cos_max: wp.float64,
) -> wp.float64:
    """Worst quality of the faces of ``moved``'s star (those without ``other``) once ``moved`` is at ``p``; -1 if
    one of them would flip or turn by more than the angle, or become degenerate while it was not."""
    worst = wp.float64(1.0)
    worst = worst + wp.float64(0.0)  # a dynamic variable (mutated in the loop)
    for i in range(n):
        t = faces[star[lo + i]]
        if has_vertex(t, other):
            continue
        a = local(pos[t[0]], origin)
        b = local(pos[t[1]], origin)
        c = local(pos[t[2]], origin)
        n_old = wp.cross(b - a, c - a)
        q_old = quality(a, b, c)
        if t[0] == moved:
            a = p
        elif t[1] == moved:
            b = p
        else:
            c = p
        n_new = wp.cross(b - a, c - a)
        q_new = quality(a, b, c)
        lo_n = wp.length(n_old)
        ln_n = wp.length(n_new)
        if ln_n <= wp.float64(0.0):
            return wp.float64(-1.0)
        if lo_n > wp.float64(0.0) and wp.dot(n_old, n_new) < cos_max * lo_n * ln_n:
            return wp.float64(-1.0)
        if q_new < QUALITY_MIN and q_new < q_old:
            return wp.float64(-1.0)
        worst = wp.min(worst, q_new)
    return worst


@wp.func
def adjacent(faces: wp.array(dtype=wp.vec3i), star: wp.array(dtype=wp.int32), lo: int, n: int, w: int) -> bool:
    """Whether ``w`` is a vertex of one of the ``n`` faces of the star starting at ``lo``."""
    hit = bool(False)
    for i in range(n):
        if has_vertex(faces[star[lo + i]], w):
            hit = True
            break
    return hit


@wp.kernel
def check_candidates(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    quad: wp.array(dtype=quadric),
    origin: wp.vec3d,
    cos_max: wp.float64,
    bin_below: int,
    frac_bits: wp.int64,
    key: wp.array(dtype=wp.int32),
    target: wp.array(dtype=wp.vec3),
    checked: wp.array(dtype=wp.int32),
):
    """Pricing, second phase, for the competing edges not checked since they were priced: the guards. An edge that
    fails one gets ``NO_KEY`` (until something it reads changes); one that passes keeps its code, raised where the
    new faces are poor (MeshLab's quality threshold), and competes only if that code is still under the cut."""
    h = listed(listing, n_listed, cand, 1, wp.tid())
    if h < 0 or checked[h] != 0:
        return
    checked[h] = 1
    ends = edge_ends(faces, h)
    a = ends[0]
    b = ends[1]
    sa = state[a]
    sb = state[b]
    sr = survivor_of(a, b, sa, sb)
    s = sr[0]
    r = sr[1]
    lo_r = offset[r]
    n_r = count[r]
    lo_s = offset[s]
    n_s = count[s]
    ok = bool(True)
    # link condition: the common neighbours of r and s are exactly the two vertices opposite the edge. r's star
    # is one closed fan, so each neighbour of r is the next vertex after r in exactly one of its faces.
    common = int(0)
    for i in range(n_r):
        w = next_of(faces[star[lo_r + i]], r)
        if w != s:
            if adjacent(faces, star, lo_s, n_s, w):
                common += 1
    if common != 2:
        ok = False
    # each opposite vertex loses a face: an interior one keeps at least three (else a closed piece would fall
    # below a tetrahedron), a border one at least one
    for i in range(n_r):
        u = faces[star[lo_r + i]]
        if ok and has_vertex(u, s):
            x = u[0] + u[1] + u[2] - r - s
            least = 4
            if state[x] == BORDER:
                least = 2
            if count[x] < least:
                ok = False
    worst = wp.float64(1.0)
    tp = target[h]
    p = local(tp, origin)
    if ok:
        worst = star_turns(pos, faces, star, lo_r, n_r, r, s, p, origin, cos_max)
    if ok and worst >= wp.float64(0.0) and sa == FREE and sb == FREE:
        worst = wp.min(worst, star_turns(pos, faces, star, lo_s, n_s, s, r, p, origin, cos_max))
    if not ok or worst < wp.float64(0.0):
        key[h] = NO_KEY
        cand[h] = 0
        return
    if worst < QUALITY_SOFT:
        pa = local(pos[a], origin)
        pb = local(pos[b], origin)
        cost = collapse_cost(quad[a] + quad[b], p, pa, pb) * QUALITY_SOFT / wp.max(worst, QUALITY_MIN)
        c = cost_code(cost)
        key[h] = c
        if not below_cut(c, h, bin_below, frac_bits):
            cand[h] = 0
