"""Warp kernels for parallel, topology-preserving quadric-error edge collapse (host loop: ``engine.stages.decimate``).

The mesh lives on the device as ``pos`` (V) ``vec3`` (z, y, x) mm and ``faces`` (F) ``vec3i``; a collapsed face is
marked ``(-1, -1, -1)`` and a collapsed vertex ``DEAD``. One pass:

1. incidence: every vertex's *star* (the faces around it) as CSR, counted, scanned, filled and sorted per vertex
   (sorted so that every later sum runs in a fixed order: the result is deterministic);
2. ``edge_costs``: every collapsible edge (once, from its half-edge ``a < b``) gets its Garland-Heckbert cost, its
   new position and every guard (link condition, valences, face flips, degenerate faces); it writes a 31-bit cost
   code (monotonic in the cost) or ``NO_KEY``;
3. a histogram of the codes gives the host the cost quantile under which edges compete;
4. claims: each competing edge does an atomic min of its key ``(cost code << 32) | mix32(edge slot)`` onto every
   face of its two stars and wins only where it holds all of them (a few rounds; winners take their faces for
   the rest of the pass). Winners' stars are face-disjoint, so their collapses and guards are independent;
5. ``apply_collapses`` moves the survivor, adds the quadrics (``Q_s += Q_r``) and rewrites the removed vertex's star.

Quadrics are float64, taken about a local origin (the mesh's centre) so that they do not cancel at scan scale.
"""

from __future__ import annotations

import warp as wp

quadric = wp.types.vector(length=10, dtype=wp.float64)

FREE = wp.constant(0)  # interior vertex with one closed fan of faces: may move or be removed
BORDER = wp.constant(1)  # on an open border with one open fan: never moves, may absorb a free neighbour
LOCKED = wp.constant(2)  # non-manifold, inconsistently wound or degenerate surroundings: never touched
DEAD = wp.constant(3)  # collapsed away, or used by no face

NO_KEY = wp.constant(0x7FFFFFFF)  # int32: not collapsible this pass
CLAIM_FREE = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
CLAIM_TAKEN = wp.constant(wp.int64(-1))
TRIMMED = wp.constant(5)  # ``cand`` of a winner trimmed off (the pass has more winners than collapses left to do)
HIST_SHIFT = wp.constant(15)  # 2^31 cost codes -> 65536 histogram bins
QUALITY_MIN = wp.constant(wp.float64(1.0e-3))  # new faces below this quality are degenerate (unless not worse)
QUALITY_SOFT = wp.constant(wp.float64(0.3))  # below this a collapse's cost is raised (MeshLab's qualitythr)


# ------------------------------------------------------------------------------------------------ helpers
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


@wp.func
def local(p: wp.vec3, origin: wp.vec3d) -> wp.vec3d:
    return wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2])) - origin


MIX_A = wp.constant(wp.uint32(0x7FEB352D))
MIX_B = wp.constant(wp.uint32(0x846CA68B))


@wp.func
def mix32(x: int) -> wp.int64:
    """A bijective 32-bit integer hash (tie-break of equal costs: neighbours must not tie in index order)."""
    h = wp.uint32(x)
    h = h ^ (h >> wp.uint32(16))
    h = h * MIX_A
    h = h ^ (h >> wp.uint32(15))
    h = h * MIX_B
    h = h ^ (h >> wp.uint32(16))
    return wp.int64(h)


@wp.func
def listed(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    want: int,
    i: int,
) -> int:
    """The ``i``-th slot of the pass's candidate list (``select_candidates``) where its ``cand`` state is ``want``,
    else -1 (past the list's end too): the kernels after the selection run over the candidates only, not over every
    slot."""
    h = int(-1)
    if i < n_listed[0]:
        if cand[listing[i]] == want:
            h = listing[i]
    return h


@wp.func
def priority(code: int, h: int) -> wp.int64:
    """An edge's claim priority, lower wins: its cost code, ties broken by the hashed slot."""
    return (wp.int64(code) << wp.int64(32)) | mix32(h)


@wp.func
def plane_quadric(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> quadric:
    """Area-weighted quadric of the plane through a, b, c (zero for a degenerate face)."""
    n = wp.cross(b - a, c - a)
    length = wp.length(n)
    q = quadric()
    if length > wp.float64(0.0):
        u = n / length
        d = -wp.dot(u, a)
        w = wp.float64(0.5) * length
        q = w * quadric(
            u[0] * u[0], u[0] * u[1], u[0] * u[2], u[0] * d,
            u[1] * u[1], u[1] * u[2], u[1] * d,
            u[2] * u[2], u[2] * d,
            d * d,
        )  # fmt: skip
    return q


@wp.func
def q_eval(q: quadric, p: wp.vec3d) -> wp.float64:
    x = p[0]
    y = p[1]
    z = p[2]
    two = wp.float64(2.0)
    return (
        q[0] * x * x
        + two * q[1] * x * y
        + two * q[2] * x * z
        + two * q[3] * x
        + q[4] * y * y
        + two * q[5] * y * z
        + two * q[6] * y
        + q[7] * z * z
        + two * q[8] * z
        + q[9]
    )


@wp.func
def quality(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d) -> wp.float64:
    """2 sqrt(3) |n| / (sum of squared edges): 1 for an equilateral triangle, 0 for a degenerate one."""
    s = wp.length_sq(b - a) + wp.length_sq(c - b) + wp.length_sq(a - c)
    q = wp.float64(0.0)
    if s > wp.float64(0.0):
        q = wp.float64(3.4641016151377544) * wp.length(wp.cross(b - a, c - a)) / s
    return q


@wp.func
def cost_code(cost: wp.float64) -> int:
    """31-bit code, monotonic in the cost: 0 for (nearly) zero, then 2^22 steps per octave."""
    c = int(0)
    if cost > wp.float64(1.0e-30):
        x = (wp.log2(cost) + wp.float64(110.0)) * wp.float64(4194304.0)
        x = wp.clamp(x, wp.float64(0.0), wp.float64(2147483000.0))
        c = int(x) + 1
    return c


# ------------------------------------------------------------------------------------------------ incidence
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
def vertex_quadrics(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    origin: wp.vec3d,
    quad: wp.array(dtype=quadric),
):
    v = wp.tid()
    q = quadric()
    lo = offset[v]
    for i in range(count[v]):
        t = faces[star[lo + i]]
        q = q + plane_quadric(local(pos[t[0]], origin), local(pos[t[1]], origin), local(pos[t[2]], origin))
    quad[v] = q


# ------------------------------------------------------------------------------------------------ costs and guards
@wp.func
def placement(q: quadric, pa: wp.vec3d, pb: wp.vec3d) -> wp.vec3d:
    """The point minimising the quadric (3x3 solve) when it is well defined and near the edge, else the best of
    the endpoints and the midpoint."""
    m = wp.mat33d(q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7])
    scale = (q[0] + q[4] + q[7]) / wp.float64(3.0)
    det = wp.determinant(m)
    mid = wp.float64(0.5) * (pa + pb)
    best = wp.vec3d(mid)
    found = bool(False)
    if scale > wp.float64(0.0) and wp.abs(det) > wp.float64(1.0e-9) * scale * scale * scale:
        x = -(wp.inverse(m) @ wp.vec3d(q[3], q[6], q[8]))
        if wp.length_sq(x - mid) <= wp.length_sq(pb - pa):
            best = x
            found = True
    if not found:
        ca = q_eval(q, pa)
        cb = q_eval(q, pb)
        cm = q_eval(q, mid)
        if ca < cm and ca <= cb:
            best = pa
        elif cb < cm:
            best = pb
    return best


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


@wp.func
def edge_ends(faces: wp.array(dtype=wp.vec3i), h: int) -> wp.vec2i:
    f = h // 3
    k = h - 3 * f
    t = faces[f]
    return wp.vec2i(t[k], t[(k + 1) % 3])


@wp.func
def survivor_of(a: int, b: int, sa: int, sb: int) -> wp.vec2i:
    """(s, r) of a collapsible edge: r, the removed vertex, is always FREE (its star one closed fan), s survives;
    (-1, -1) when the classes forbid the collapse."""
    if not ((sa == FREE and (sb == FREE or sb == BORDER)) or (sa == BORDER and sb == FREE)):
        return wp.vec2i(-1, -1)
    if sb == BORDER:
        return wp.vec2i(b, a)
    return wp.vec2i(a, b)


@wp.func
def collapse_cost(q: quadric, p: wp.vec3d, pa: wp.vec3d, pb: wp.vec3d) -> wp.float64:
    """The quadric error at ``p``, plus a tiny length term that orders collapses in flat regions (zero quadric
    error) shortest first."""
    length_sq = wp.length_sq(pb - pa)
    return wp.max(q_eval(q, p), wp.float64(0.0)) + wp.float64(1.0e-8) * length_sq * length_sq


@wp.kernel
def edge_costs(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    count: wp.array(dtype=wp.int32),
    state: wp.array(dtype=wp.int32),
    quad: wp.array(dtype=quadric),
    origin: wp.vec3d,
    dirty: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    target: wp.array(dtype=wp.vec3),
    checked: wp.array(dtype=wp.int32),
):
    """Pricing, first phase, per half-edge slot ``3 f + k``: the quadric cost code of collapsing edge
    (a, b) = (t[k], t[k+1]) when a < b and the vertex classes allow it, else ``NO_KEY``; and the new position. The
    guards that read the stars run only for the edges that compete (``check_candidates``). An edge whose ends are
    both clean (nothing it reads has changed since the last pass, see ``apply_collapses``) keeps its code, position
    and checked mark."""
    h = wp.tid()
    f = h // 3
    k = h - 3 * f
    t = faces[f]
    if t[0] < 0:
        key[h] = NO_KEY
        return
    a = t[k]
    b = t[(k + 1) % 3]
    if a > b:
        key[h] = NO_KEY
        return
    if dirty[a] == 0 and dirty[b] == 0:
        return
    key[h] = NO_KEY
    checked[h] = 0
    sa = state[a]
    sb = state[b]
    sr = survivor_of(a, b, sa, sb)
    if sr[0] < 0:
        return
    if sa == FREE and sb == FREE and count[a] + count[b] - 4 < 3:
        return
    pa = local(pos[a], origin)
    pb = local(pos[b], origin)
    q = quad[a] + quad[b]
    p = local(pos[sr[0]], origin)
    if sa == FREE and sb == FREE:
        p = placement(q, pa, pb)
    key[h] = cost_code(collapse_cost(q, p, pa, pb))
    target[h] = wp.vec3(wp.float32(p[0] + origin[0]), wp.float32(p[1] + origin[1]), wp.float32(p[2] + origin[2]))


@wp.func
def below_cut(c: int, h: int, bin_below: int, frac_bits: wp.int64) -> bool:
    """Whether key ``c`` of slot ``h`` is under the pass's cost quantile: bins below ``bin_below``, and in that bin
    a hashed share (``frac_bits`` / 2^32)."""
    b = c >> HIST_SHIFT
    return c != NO_KEY and (b < bin_below or (b == bin_below and mix32(h) < frac_bits))


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


@wp.kernel
def cost_histogram(key: wp.array(dtype=wp.int32), hist: wp.array(dtype=wp.int32)):
    h = wp.tid()
    c = key[h]
    if c != NO_KEY:
        wp.atomic_add(hist, c >> HIST_SHIFT, 1)


@wp.kernel
def select_candidates(
    key: wp.array(dtype=wp.int32),
    bin_below: int,
    frac_bits: wp.int64,
    cand: wp.array(dtype=wp.int32),
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
):
    """Edges under the pass's cost quantile compete (``below_cut``), and are listed (in no particular order: what
    the later kernels decide does not depend on the order of the list)."""
    h = wp.tid()
    cand[h] = 0
    if below_cut(key[h], h, bin_below, frac_bits):
        cand[h] = 1
        listing[wp.atomic_add(n_listed, 0, 1)] = h


# ------------------------------------------------------------------------------------------------ claims
@wp.kernel
def claim_stars(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    claim: wp.array(dtype=wp.int64),
):
    """Each competing edge bids its key on every face of its two stars."""
    h = listed(listing, n_listed, cand, 1, wp.tid())
    if h < 0:
        return
    mine = priority(key[h], h)
    ends = edge_ends(faces, h)
    for e in range(2):
        v = ends[e]
        lo = offset[v]
        for i in range(count[v]):
            wp.atomic_min(claim, star[lo + i], mine)


@wp.kernel
def settle_claims(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    claim: wp.array(dtype=wp.int64),
    winners: wp.array(dtype=wp.int32),
):
    """An edge holding every face of its stars wins (and takes them for the pass, in ``take_stars``); one that meets
    a face taken in an earlier round drops out; the rest compete again in the next round.

    Winners' stars share no face, hence no winner's end is a neighbour of another's: every collapse reads and
    writes only its own stars, the vertices it reads do not move, and a vertex opposite several winners has at
    least three faces per winner around it, so the guards of each hold together.
    """
    h = listed(listing, n_listed, cand, 1, wp.tid())
    if h < 0:
        return
    mine = priority(key[h], h)
    ends = edge_ends(faces, h)
    won = int(1)
    for e in range(2):
        v = ends[e]
        lo = offset[v]
        for i in range(count[v]):
            c = claim[star[lo + i]]
            if c == CLAIM_TAKEN:
                won = -1
            elif c != mine and won == 1:
                won = 0
    if won == 1:
        cand[h] = 3  # won this round: ``take_stars`` marks its faces taken, after every edge has looked
        wp.atomic_add(winners, 0, 1)
    elif won == -1:
        cand[h] = 0


@wp.kernel
def take_stars(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    faces: wp.array(dtype=wp.vec3i),
    offset: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    star: wp.array(dtype=wp.int32),
    claim: wp.array(dtype=wp.int64),
):
    """This round's winners take their faces for the rest of the pass (a kernel of its own, so that what a losing
    edge saw in ``settle_claims`` does not depend on the order threads ran in)."""
    h = listed(listing, n_listed, cand, 3, wp.tid())
    if h < 0:
        return
    cand[h] = 2
    ends = edge_ends(faces, h)
    for e in range(2):
        v = ends[e]
        lo = offset[v]
        for i in range(count[v]):
            claim[star[lo + i]] = CLAIM_TAKEN


@wp.kernel
def release_claims(claim: wp.array(dtype=wp.int64)):
    i = wp.tid()
    if claim[i] != CLAIM_TAKEN:
        claim[i] = CLAIM_FREE


@wp.kernel
def winner_histogram(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    hist: wp.array(dtype=wp.int32),
):
    h = listed(listing, n_listed, cand, 2, wp.tid())
    if h >= 0:
        wp.atomic_add(hist, key[h] >> HIST_SHIFT, 1)


@wp.kernel
def trim_winners(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    bin_below: int,
    frac_bits: wp.int64,
    salt: int,
):
    """Keep only the cheapest winners (bins below ``bin_below``, a share of that bin hashed with ``salt``): near the
    target a pass may collapse no more than what is left to do. A repeated trim takes another salt, so that a share
    that missed its count does not miss it the same way again."""
    h = listed(listing, n_listed, cand, 2, wp.tid())
    if h < 0:
        return
    b = key[h] >> HIST_SHIFT
    if b > bin_below or (b == bin_below and mix32(h ^ salt) >= frac_bits):
        cand[h] = TRIMMED


@wp.kernel
def cheapest_trimmed(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int64),
):
    h = listed(listing, n_listed, cand, TRIMMED, wp.tid())
    if h >= 0:
        wp.atomic_min(best, 0, priority(key[h], h))


@wp.kernel
def restore_cheapest(
    listing: wp.array(dtype=wp.int32),
    n_listed: wp.array(dtype=wp.int32),
    cand: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int64),
):
    """The cheapest trimmed winner collapses after all, where the trim (a hashed share of a cost bin) kept none:
    a pass one collapse short of the target would otherwise trim the same way every pass."""
    h = listed(listing, n_listed, cand, TRIMMED, wp.tid())
    if h >= 0 and priority(key[h], h) == best[0]:
        cand[h] = 2


# ------------------------------------------------------------------------------------------------ collapse
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


# ------------------------------------------------------------------------------------------------ compaction
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
def scatter_kept(
    count: wp.array(dtype=wp.int32),
    slot: wp.array(dtype=wp.int32),
    quad: wp.array(dtype=quadric),
    kept: wp.array(dtype=wp.int32),
    out_quad: wp.array(dtype=quadric),
):
    """For a compaction that carries the quadrics: each kept vertex's old index and its quadric."""
    v = wp.tid()
    if count[v] > 0:
        kept[slot[v]] = v
        out_quad[slot[v]] = quad[v]


@wp.kernel
def lock_vertices(lock: wp.array(dtype=wp.int32), state: wp.array(dtype=wp.int32)):
    """Vertices the caller pins (a tile's border): LOCKED, so no collapse moves, removes or extends them."""
    v = wp.tid()
    if lock[v] != 0 and state[v] != DEAD:
        state[v] = LOCKED


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


# ------------------------------------------------------------------------------------------------ diagnostics
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
    if edges > 0:
        wp.atomic_add(totals, 0, wp.int64(edges))
        wp.atomic_add(totals, 1, wp.int64(border))
        wp.atomic_add(totals, 2, wp.int64(nonmanifold))
        wp.atomic_add(totals, 3, wp.int64(inconsistent))


@wp.kernel
def face_measures(
    pos: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=wp.vec3i),
    first: int,
    volume: wp.array(dtype=wp.float64),
    area: wp.array(dtype=wp.float64),
    degenerate: wp.array(dtype=wp.float32),
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
    degenerate[f] = 0.0
    if t[0] == t[1] or t[1] == t[2] or t[0] == t[2]:
        degenerate[f] = 1.0


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
def jump_labels(label: wp.array(dtype=wp.int32)):
    v = wp.tid()
    r = label[v]
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
    volume: wp.array(dtype=wp.float64),
    nfaces: wp.array(dtype=wp.int32),
):
    """Signed volume (vertices in (x, y, z) order) and face count of every piece, at its root vertex."""
    f = wp.tid()
    t = faces[f]
    root = label[t[0]]
    a = xyz64(pos[t[0]])
    wp.atomic_add(volume, root, wp.dot(a, wp.cross(xyz64(pos[t[1]]), xyz64(pos[t[2]]))) / wp.float64(6.0))
    wp.atomic_add(nfaces, root, 1)


@wp.kernel
def drop_pieces(faces: wp.array(dtype=wp.vec3i), label: wp.array(dtype=wp.int32), keep: wp.array(dtype=wp.int32)):
    f = wp.tid()
    if keep[label[faces[f][0]]] == 0:
        faces[f] = wp.vec3i(-1, -1, -1)
