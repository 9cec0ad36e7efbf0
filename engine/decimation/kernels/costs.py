"""Warp kernels that price the edges of a decimation pass and pick the ones that compete (host side:
``engine.decimation.phases``).

``edge_costs``: every collapsible edge (once, from its half-edge ``a < b``) gets its Garland-Heckbert cost and its
new position; it writes a 31-bit cost code (monotonic in the cost) or ``NO_KEY``. A histogram of the codes gives
the host the cost quantile under which edges compete (``select_candidates``), and the later kernels run over the
listed candidates only (``listed``).
"""

from __future__ import annotations

import warp as wp

from engine.decimation.kernels.quadrics import local, q_eval, quadric
from engine.surface.kernels.topology import BORDER, FREE

NO_KEY = wp.constant(0x7FFFFFFF)  # int32: not collapsible this pass
HIST_SHIFT = wp.constant(15)  # 2^31 cost codes -> 65536 histogram bins
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
def cost_code(cost: wp.float64) -> int:
    """31-bit code, monotonic in the cost: 0 for (nearly) zero, then 2^22 steps per octave."""
    c = int(0)
    if cost > wp.float64(1.0e-30):
        x = (wp.log2(cost) + wp.float64(110.0)) * wp.float64(4194304.0)
        x = wp.clamp(x, wp.float64(0.0), wp.float64(2147483000.0))
        c = int(x) + 1
    return c


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
