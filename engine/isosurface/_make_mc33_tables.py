"""Generator of the Marching Cubes 33 lookup tables (run: ``python -m engine.isosurface._make_mc33_tables``).

The tables are *derived*, not transcribed: for every cell key the generator reconstructs the topology of the
trilinear interpolant's isosurface inside the cell and triangulates it.

Conventions (shared with ``engine/isosurface/kernels/mc33.py``):

* corner ``i`` sits at ``(x, y, z) = (i & 1, (i >> 1) & 1, (i >> 2) & 1)``;
* edges 0-3 run along x (``k = y + 2 z``), 4-7 along y (``k = x + 2 z``), 8-11 along z (``k = x + 2 y``);
* faces 0-5 are ``x=0, x=1, y=0, y=1, z=0, z=1``;
* a corner is *positive* when its value is at or above the level; a face or body saddle exactly at the level
  joins the positive values (both: the limit of lowering the level by an infinitesimal amount).

A cell key has 18 bits: ``config`` (bit ``i`` = corner ``i`` positive), 6 face bits (bit ``f`` set when face ``f``
is ambiguous and the asymptotic decider joins its *positive* diagonal) and 4 body bits from the sweep along z
(``posAC, posBD, negAC, negBD``: the positive or negative values of the diagonal vertical edges ``A``-``C``
(corners 0/4 and 3/7) or ``B``-``D`` (1/5 and 2/6) are joined inside the cell, at a height where the slice is a
saddle configuration). Bits that cannot be set for a config are always zero at run time, and at most one body
bit is set: each needs the vertex of the same parabola (the slice's saddle value along z) inside its own
height interval, with its own sign of curvature.

From a key the generator builds:

1. the contour on the cube's surface: per face, segments between cut edges (the asymptotic decider pairs the
   four cut edges of an ambiguous face), oriented so that the positive side is on the right seen from outside;
   the segments close into loops;
2. the connected groups of positive and of negative corners on the surface, and in 3-D (surface groups merged
   by the body bits). A trilinear function is harmonic, so every component of either region contains a corner,
   and each surface piece inside the cell is a disk bounded by one loop, or a tube joining two loops when two
   surface groups of one sign meet only through the interior (at most one such tube per cell);
3. a triangulation: disks as fans (a centre vertex where a fan would need a diagonal between two vertices on
   one face, which could be shared with the neighbouring cell) and tubes as a three-rail strip through a ring
   of interior vertices. No triangle edge joins two boundary vertices on a common face except the contour
   segments themselves, which makes the global mesh 2-manifold across cells.

Interior vertices are weighted means of the cell's edge points (weights stored per vertex).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

CORNERS = tuple(((i & 1), (i >> 1) & 1, (i >> 2) & 1) for i in range(8))


def _edge_corners() -> tuple[tuple[int, int], ...]:
    edges = []
    for k in range(4):  # x edges
        y, z = k & 1, k >> 1
        c = 2 * y + 4 * z
        edges.append((c, c + 1))
    for k in range(4):  # y edges
        x, z = k & 1, k >> 1
        c = x + 4 * z
        edges.append((c, c + 2))
    for k in range(4):  # z edges
        x, y = k & 1, k >> 1
        c = x + 2 * y
        edges.append((c, c + 4))
    return tuple(edges)


EDGES = _edge_corners()
EDGE_MID = tuple(tuple((CORNERS[a][d] + CORNERS[b][d]) / 2 for d in range(3)) for a, b in EDGES)


def _face_data() -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    """Per face: corners in cyclic order, and the 4 edges of the face."""
    faces = []
    for f in range(6):
        axis, side = divmod(f, 2)
        u, v = [a for a in range(3) if a != axis]
        cyc = []
        for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
            p = [0, 0, 0]
            p[axis], p[u], p[v] = side, du, dv
            cyc.append(p[0] + 2 * p[1] + 4 * p[2])
        fe = tuple(e for e, (a, b) in enumerate(EDGES) if a in cyc and b in cyc)
        faces.append((tuple(cyc), fe))
    return tuple(faces)


FACES = _face_data()
EDGE_FACES = tuple(tuple(f for f in range(6) if e in FACES[f][1]) for e in range(12))
# vertical edges of the z sweep: A=(0,0), B=(1,0), C=(1,1), D=(0,1); each as (bottom, top) corners
SWEEP_A, SWEEP_B, SWEEP_C, SWEEP_D = (0, 4), (1, 5), (3, 7), (2, 6)
BODY_PAIRS = (  # (sign, edge, edge, other, other): body bit b joins `sign` values of the two edges
    (1, SWEEP_A, SWEEP_C, SWEEP_B, SWEEP_D),
    (1, SWEEP_B, SWEEP_D, SWEEP_A, SWEEP_C),
    (0, SWEEP_A, SWEEP_C, SWEEP_B, SWEEP_D),
    (0, SWEEP_B, SWEEP_D, SWEEP_A, SWEEP_C),
)
OUTWARD = ((-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1))


def _sub(a, b):
    return tuple(a[i] - b[i] for i in range(3))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return sum(a[i] * b[i] for i in range(3))


def positive(config: int, corner: int) -> bool:
    return bool((config >> corner) & 1)


def ambiguous_faces(config: int) -> tuple[int, ...]:
    out = []
    for f, (cyc, _) in enumerate(FACES):
        s = [positive(config, c) for c in cyc]
        if s[0] == s[2] and s[1] == s[3] and s[0] != s[1]:
            out.append(f)
    return tuple(out)


def feasible_body_bits(config: int) -> tuple[int, ...]:
    """Body bits that the run-time sweep can set for this sign configuration."""
    out = []
    for b, (sign, e1, e2, o1, o2) in enumerate(BODY_PAIRS):
        want = bool(sign)
        ok = all(any(positive(config, c) == want for c in e) for e in (e1, e2))
        ok = ok and all(any(positive(config, c) != want for c in e) for e in (o1, o2))
        if ok:
            out.append(b)
    return tuple(out)


class _UF:
    def __init__(self, n: int) -> None:
        self.p = list(range(n))

    def find(self, a: int) -> int:
        while self.p[a] != a:
            self.p[a] = self.p[self.p[a]]
            a = self.p[a]
        return a

    def union(self, a: int, b: int) -> bool:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.p[max(ra, rb)] = min(ra, rb)
        return True


def surface_segments(config: int, facebits: int) -> list[tuple[int, int]]:
    """Oriented contour segments (edge -> edge) on the cube's faces: positive side on the right seen from outside."""
    segs = []
    for f, (cyc, fedges) in enumerate(FACES):
        cut = [e for e in fedges if positive(config, EDGES[e][0]) != positive(config, EDGES[e][1])]
        if not cut:
            continue
        if len(cut) == 2:
            pairs = [tuple(cut)]
        else:
            joined_positive = bool((facebits >> f) & 1)
            # the isolated corners are the negative ones when the positive diagonal is joined
            iso_sign = not joined_positive
            pairs = []
            for c in cyc:
                if positive(config, c) == iso_sign:
                    pairs.append(tuple(e for e in cut if c in EDGES[e]))
        for p, q in pairs:
            shared = set(EDGES[p]) & set(EDGES[q])
            corner = shared.pop() if shared else next(c for c in EDGES[p] if positive(config, c))
            d = _sub(EDGE_MID[q], EDGE_MID[p])
            left = _dot(_cross(d, _sub(CORNERS[corner], EDGE_MID[p])), OUTWARD[f]) > 0
            if left == positive(config, corner):
                p, q = q, p
            segs.append((p, q))
    return segs


def trace_loops(segs: list[tuple[int, int]]) -> list[list[int]]:
    nxt = {}
    for p, q in segs:
        assert p not in nxt, "edge point with two outgoing segments"
        nxt[p] = q
    assert sorted(nxt) == sorted(q for _, q in segs), "open contour"
    loops, seen = [], set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop, e = [], start
        while e not in seen:
            seen.add(e)
            loop.append(e)
            e = nxt[e]
        loops.append(loop)
    return loops


def surface_groups(config: int, facebits: int) -> _UF:
    uf = _UF(8)
    for a, b in EDGES:
        if positive(config, a) == positive(config, b):
            uf.union(a, b)
    for f in ambiguous_faces(config):
        cyc = FACES[f][0]
        joined_positive = bool((facebits >> f) & 1)
        for i in (0, 1):
            a, c = cyc[i], cyc[i + 2]
            if positive(config, a) == joined_positive:
                uf.union(a, c)
    return uf


def volume_groups(config: int, facebits: int, bodybits: int) -> _UF:
    uf = surface_groups(config, facebits)
    for b, (sign, e1, e2, _, _) in enumerate(BODY_PAIRS):
        if (bodybits >> b) & 1:
            c1 = next(c for c in e1 if positive(config, c) == bool(sign))
            c2 = next(c for c in e2 if positive(config, c) == bool(sign))
            uf.union(c1, c2)
    return uf


def loop_groups(config: int, loop: list[int], uf: _UF) -> tuple[int, int]:
    """(positive group, negative group) on the two sides of a loop."""
    a, b = EDGES[loop[0]]
    pos, neg = (a, b) if positive(config, a) else (b, a)
    return uf.find(pos), uf.find(neg)


class Unsupported(Exception):
    """A key whose interior topology is not a set of disks plus at most one tube."""


def cell_topology(config: int, facebits: int, bodybits: int):
    """Loops, and the pair of loop indices joined by a tube (or None)."""
    loops = trace_loops(surface_segments(config, facebits))
    suf = surface_groups(config, facebits)
    vuf = volume_groups(config, facebits, bodybits)
    merged = []  # pairs of surface groups joined only through the interior
    groups = sorted({suf.find(c) for c in range(8)})
    for g1, g2 in itertools.combinations(groups, 2):
        if vuf.find(g1) == vuf.find(g2):
            merged.append((g1, g2))
    if not merged:
        return loops, None
    if len(merged) > 1:
        raise Unsupported(f"{len(merged)} interior joins")
    g1, g2 = merged[0]
    # region tree: nodes = surface groups, edges = loops; the tube joins the loops next to g1 and g2 on their path
    adj: dict[int, list[tuple[int, int]]] = {}
    for i, loop in enumerate(loops):
        p, n = loop_groups(config, loop, suf)
        adj.setdefault(p, []).append((n, i))
        adj.setdefault(n, []).append((p, i))
    prev = {g1: (None, None)}
    todo = [g1]
    while todo:
        g = todo.pop()
        for h, i in adj.get(g, []):
            if h not in prev:
                prev[h] = (g, i)
                todo.append(h)
    path = []
    g = g2
    while prev[g][0] is not None:
        g, i = prev[g]
        path.append(i)
    if len(path) != 2:
        raise Unsupported(f"tube across {len(path)} loops")
    return loops, (path[1], path[0])


# ---------------------------------------------------------------------------------------------- triangulation
def _angle_quality(tris: list[tuple[int, int, int]]) -> float:
    worst = math.pi
    for t in tris:
        pts = [EDGE_MID[v] for v in t]
        for k in range(3):
            a, b, c = pts[k], pts[(k + 1) % 3], pts[(k + 2) % 3]
            u, v = _sub(b, a), _sub(c, a)
            nu, nv = math.sqrt(_dot(u, u)), math.sqrt(_dot(v, v))
            cosang = max(-1.0, min(1.0, _dot(u, v) / (nu * nv)))
            worst = min(worst, math.acos(cosang))
    return worst


def _share_face(e1: int, e2: int) -> bool:
    return bool(set(EDGE_FACES[e1]) & set(EDGE_FACES[e2]))


def triangulate_disk(loop: list[int], new_vertex) -> list[tuple[int, int, int]]:
    """A fan from the loop vertex that gives the best minimum angle, or from a centre vertex if no fan avoids a
    diagonal between two vertices on one face."""
    n = len(loop)
    if n == 3:
        return [tuple(loop)]
    best = None
    for s in range(n):
        rot = loop[s:] + loop[:s]
        if any(_share_face(rot[0], rot[i]) for i in range(2, n - 1)):
            continue
        tris = [(rot[0], rot[i], rot[i + 1]) for i in range(1, n - 1)]
        q = _angle_quality(tris)
        if best is None or q > best[0] + 1e-12:
            best = (q, tris)
    if best is not None:
        return best[1]
    c = new_vertex(dict.fromkeys(loop, 1.0 / n))
    return [(loop[i], loop[(i + 1) % n], c) for i in range(n)]


def _dist(e1: int, e2: int) -> float:
    d = _sub(EDGE_MID[e1], EDGE_MID[e2])
    return math.sqrt(_dot(d, d))


def _direct_band(u: list[int], w: list[int]) -> list[tuple[int, int, int]] | None:
    """Zipper triangles between two loops running the same way, without new vertices, using only rungs whose ends
    share no face (so no triangle lies in a face plane). Shortest total rung length; None if impossible.

    A zipper is a monotone lattice path from rung (0, 0) to (n1, n2) = (0, 0) mod (n1, n2) that must not visit
    a rung twice: if it leaves row 0 at column c0, it may reach row n2 only after column c0 (and likewise for
    columns), which the search enforces by fixing the first run.
    """
    n1, n2 = len(u), len(w)
    inf = float("inf")
    best: tuple[float, list[tuple[int, int, int]]] | None = None
    for k in range(n2):

        def rung_ok(i: int, j: int, k: int = k) -> bool:
            return not _share_face(u[i % n1], w[(j + k) % n2])

        if not rung_ok(0, 0):
            continue
        firsts = [((c, 0), 0, c) for c in range(1, n1)] + [((0, r), r, 0) for r in range(1, n2)]
        for (fi, fj), r0, c0 in firsts:
            run = [(i, 0) for i in range(fi + 1)] if fj == 0 else [(0, j) for j in range(fj + 1)]
            if not all(rung_ok(i, j) for i, j in run):
                continue
            nxt = (fi, 1) if fj == 0 else (1, fj)  # turn after the first run

            def allowed(i: int, j: int, r0: int = r0, c0: int = c0) -> bool:
                if i == n1 and j <= r0 and (i, j) != (n1, n2):
                    return False
                if j == n2 and i <= c0 and (i, j) != (n1, n2):
                    return False
                return rung_ok(i, j)

            if not allowed(*nxt):
                continue
            cost = dict.fromkeys(run, 0.0)
            back = {run[t + 1]: run[t] for t in range(len(run) - 1)}
            cost[nxt] = _dist(u[nxt[0] % n1], w[(nxt[1] + k) % n2])
            back[nxt] = run[-1]
            for i in range(nxt[0], n1 + 1):
                for j in range(nxt[1], n2 + 1):
                    if (i, j) == nxt or not allowed(i, j):
                        continue
                    here = _dist(u[i % n1], w[(j + k) % n2])
                    for p in ((i - 1, j), (i, j - 1)):
                        if p in cost and p not in run[:-1] and cost[p] + here < cost.get((i, j), inf):
                            cost[(i, j)] = cost[p] + here
                            back[(i, j)] = p
            total = cost.get((n1, n2), inf)
            if total == inf or (best is not None and total >= best[0] - 1e-12):
                continue
            path = [(n1, n2)]
            while path[-1] != (0, 0):
                path.append(back[path[-1]])
            path.reverse()
            tris = []
            for (i0, j0), (i1, j1) in itertools.pairwise(path):
                ua, wa = u[i0 % n1], w[(j0 + k) % n2]
                if i1 != i0:
                    tris.append((ua, u[i1 % n1], wa))
                else:
                    tris.append((ua, w[(j1 + k) % n2], wa))
            best = (total, tris)
    return None if best is None else best[1]


def triangulate_tube(l1: list[int], l2: list[int], new_vertex) -> list[tuple[int, int, int]]:
    """A tube between two loops: a direct zipper band where possible, else a strip through a ring of interior
    vertices (no triangle then has two boundary vertices on one face unless they form a contour segment)."""
    direct = _direct_band(l1, l2[::-1])
    if direct is not None:
        return direct
    u = l1
    w = l2[::-1]  # runs along the strip in the same direction as l1
    n1, n2 = len(u), len(w)
    k0 = min(range(n2), key=lambda k: (_dist(u[0], w[k]), k))
    w = w[k0:] + w[:k0]
    rungs = [(0, 0)]
    i = j = 0
    while i + j < n1 + n2 - 1:
        adv_u = i < n1 and (j >= n2 or _dist(u[(i + 1) % n1], w[j % n2]) <= _dist(u[i % n1], w[(j + 1) % n2]))
        if adv_u:
            i += 1
        else:
            j += 1
        rungs.append((i, j))
    m = len(rungs)
    centre = dict.fromkeys(u + w, 0.5 / (n1 + n2))
    ring, seen = [], set()
    for k, (i, j) in enumerate(rungs):
        # half the loops' centroid, half this rung and the next: a rung pair alone can repeat (when one loop's
        # steps all come in one run, rungs (0, j) and (n1, j) join the same two points) and would stack two ring
        # vertices on one spot
        wts = dict(centre)
        i2, j2 = rungs[(k + 1) % m]
        for e in (u[i % n1], w[j % n2], u[i2 % n1], w[j2 % n2]):
            wts[e] = wts[e] + 0.125
        key = tuple(sorted(wts.items()))
        if key in seen:
            raise AssertionError(f"two ring vertices at one place in the tube between {l1} and {l2}")
        seen.add(key)
        ring.append(new_vertex(wts))
    tris = []
    for k in range(m):
        (i0, j0), (i1, j1) = rungs[k], rungs[(k + 1) % m]
        if k == m - 1:  # closing step back to rung 0
            i1, j1 = i0 + (1 if i0 < n1 else 0), j0 + (1 if i0 >= n1 else 0)
        ua, ub, wa, wb = u[i0 % n1], u[i1 % n1], w[j0 % n2], w[j1 % n2]
        ra, rb = ring[k], ring[(k + 1) % m]
        if i1 != i0:
            tris += [(ua, ub, rb), (ua, rb, ra), (ra, rb, wa)]
        else:
            tris += [(ua, rb, ra), (ra, rb, wb), (ra, wb, wa)]
    return tris


def triangulate(config: int, facebits: int, bodybits: int):
    """Triangles over local vertex ids (0-11 edges, 12+ interior) and interior vertex weights."""
    loops, tube = cell_topology(config, facebits, bodybits)
    interior: list[tuple[float, ...]] = []

    def new_vertex(weights: dict[int, float]) -> int:
        interior.append(tuple(float(weights.get(e, 0.0)) for e in range(12)))
        return 12 + len(interior) - 1

    tris = []
    for i, loop in enumerate(loops):
        if tube is not None and i in tube:
            continue
        tris += triangulate_disk(loop, new_vertex)
    if tube is not None:
        tris += triangulate_tube(loops[tube[0]], loops[tube[1]], new_vertex)
    check_triangulation(loops, tris, tube)
    return tris, interior


def check_triangulation(loops, tris, tube) -> None:
    """Boundary = the oriented loops; interior edges used once each way; no face-plane shortcut edges."""
    directed: dict[tuple[int, int], int] = {}
    for t in tris:
        assert len(set(t)) == 3, t
        for k in range(3):
            e = (t[k], t[(k + 1) % 3])
            directed[e] = directed.get(e, 0) + 1
    loop_edges = {(lp[i], lp[(i + 1) % len(lp)]) for lp in loops for i in range(len(lp))}
    for (a, b), cnt in directed.items():
        assert cnt == 1, ("edge used twice in one direction", a, b)
        if (a, b) in loop_edges:
            assert (b, a) not in directed
            continue
        assert (b, a) in directed, ("open edge", a, b)
        if a < 12 and b < 12:
            assert not _share_face(a, b), ("diagonal on a face", a, b)
    for e in loop_edges:
        assert e in directed, ("missing contour segment", e)


# ---------------------------------------------------------------------------------------------- table build
def build_tables():
    tri_ids: dict[tuple, int] = {}
    triangulations: list[tuple[tuple[tuple[int, int, int], ...], tuple[tuple[float, ...], ...]]] = []
    keys: list[int] = []
    ids: list[int] = []
    unsupported: list[int] = []
    for config in range(256):
        amb = ambiguous_faces(config)
        body = feasible_body_bits(config)
        for fsel in range(1 << len(amb)):
            facebits = sum(1 << f for k, f in enumerate(amb) if (fsel >> k) & 1)
            for bodybits in (0, *(1 << b for b in body)):  # one parabola vertex: at most one body bit
                try:
                    tris, interior = triangulate(config, facebits, bodybits)
                except Unsupported:
                    unsupported.append(config | facebits << 8 | bodybits << 14)
                    tris, interior = triangulate(config, facebits, 0)
                entry = (tuple(tris), tuple(interior))
                if entry not in tri_ids:
                    tri_ids[entry] = len(triangulations)
                    triangulations.append(entry)
                keys.append(config | facebits << 8 | bodybits << 14)
                ids.append(tri_ids[entry])
    return keys, ids, triangulations, unsupported


def _orientation_convention_check() -> None:
    """Corner 0 alone above the level: the triangle's normal must point away from it (toward lower values)."""
    tris, _ = triangulate(1, 0, 0)
    (a, b, c) = [EDGE_MID[e] for e in tris[0]]
    n = _cross(_sub(b, a), _sub(c, a))
    assert _dot(n, _sub(a, CORNERS[0])) > 0, "orientation convention broken"


def render_module() -> str:
    _orientation_convention_check()
    keys, ids, triangulations, unsupported = build_tables()
    tri_flat, tri_off, tri_cnt, iv_flat, iv_off, iv_cnt = [], [], [], [], [], []
    for tris, interior in triangulations:
        tri_off.append(len(tri_flat) // 3)
        tri_cnt.append(len(tris))
        for t in tris:
            tri_flat.extend(t)
        iv_off.append(len(iv_flat) // 12)
        iv_cnt.append(len(interior))
        for w in interior:
            iv_flat.extend(w)

    def fmt(name: str, typ: str, values, per_line: int = 24) -> str:
        lines = [f"{name}: Final[tuple[{typ}, ...]] = ("]
        for i in range(0, len(values), per_line):
            lines.append("    " + " ".join(f"{v!r}," for v in values[i : i + per_line]))
        lines.append(")")
        return "\n".join(lines)

    parts = [
        '"""Marching Cubes 33 tables. GENERATED by ``python -m engine.isosurface._make_mc33_tables``: do not edit.',
        "",
        "See the generator's docstring for the conventions. ``KEYS[i]`` (config | facebits << 8 | bodybits << 14)",
        "maps to triangulation ``TRI_ID[i]``; triangulation ``t`` has ``TRI_COUNT[t]`` triangles starting at triangle",
        "``TRI_OFFSET[t]`` of ``TRIANGLES`` (flat local vertex ids: 0-11 edge points, 12+ interior vertices) and",
        "``IVERT_COUNT[t]`` interior vertices whose 12 edge weights start at row ``IVERT_OFFSET[t]`` of",
        "``IVERT_WEIGHTS``. ``UNSUPPORTED`` lists keys outside the disks-plus-one-tube topology (expected empty).",
        '"""',
        "",
        "from typing import Final",
        "",
        f"N_KEYS_DENSE: Final[int] = {1 << 18}",
        fmt("KEYS", "int", keys),
        fmt("TRI_ID", "int", ids),
        fmt("TRI_OFFSET", "int", tri_off),
        fmt("TRI_COUNT", "int", tri_cnt),
        fmt("TRIANGLES", "int", tri_flat, 30),
        fmt("IVERT_OFFSET", "int", iv_off),
        fmt("IVERT_COUNT", "int", iv_cnt),
        fmt("IVERT_WEIGHTS", "float", iv_flat, 12),
        fmt("UNSUPPORTED", "int", unsupported),
        "",
    ]
    return "\n".join(parts)


def main() -> None:
    out = Path(__file__).with_name("mc33_tables.py")
    out.write_text(render_module())
    print(f"wrote {out}")  # noqa: T201 - the generator reports its output


if __name__ == "__main__":
    main()
