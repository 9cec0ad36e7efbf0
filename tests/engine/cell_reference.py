"""Independent reference for the topology of the trilinear interpolant's isosurface inside one cube cell.

Nothing here reads or imports ``engine.kernels`` (no tables, no table generator): the topology is derived from the
eight corner values alone, with the theory below. Corner ``i`` sits at ``(x, y, z) = (i & 1, (i >> 1) & 1,
(i >> 2) & 1)``; values are taken minus the level, a value ``>= 0`` counts as positive (above the level). An edge is
named by its two corner indices ``(i, j)`` with ``i < j``.

Theory
------
Let ``F`` be the trilinear interpolant on the closed cube ``C``, ``P = {F > 0}`` and ``N = {F < 0}`` (we only
handle generic values: no corner value, face saddle value or body saddle value equal to the level).

1. *Harmonicity.* ``F`` is harmonic (each monomial is at most linear in each variable), so it has no local
   extremum inside ``C``; its restriction to a face is bilinear, again harmonic, and its restriction to an edge is
   linear. Hence every component of ``P`` (or ``N``) meets the boundary, every component of ``P`` on a face meets
   the face's edges, and every component on an edge holds a corner: the components of ``P`` on the cube's surface
   (the *surface groups*) are groups of positive corners.
2. *Surface groups (asymptotic decider).* Two corners of one sign joined by a cube edge are in one surface group.
   On a face whose corners alternate in sign (positive ``a, c`` on one diagonal, negative ``b, d`` on the other)
   the bilinear saddle value is ``(ac - bd) / (a + c - b - d)`` with a positive denominator, so the positive
   diagonal is joined across the face iff ``ac > bd``, and the negative one iff ``ac < bd``. On other faces the
   same-sign corners are already joined along edges.
3. *Contour loops.* The contour ``F = 0`` on the surface meets each edge with corners of opposite sign once. On a
   face it is a segment between two cut edges, or on an ambiguous face two segments that cut off the two corners
   of the sign whose diagonal is *not* joined. Chaining the segments over the faces gives closed loops; each loop
   has one positive and one negative surface group beside it.
4. *Interior connectivity (stratified Morse theory).* Sweep ``t`` from ``max F`` down to ``0`` and watch the
   components of ``{F > t}``. A component is born only at a local maximum of ``F`` on ``C``, which by (1) is a
   corner. Components merge only at critical points of the stratification: (a) on an edge, never (``F`` is linear
   there); (b) at a corner, never (near a corner ``F`` is ``F(v) + grad F . d`` to first order, so the local upper
   set is empty -- a birth -- or convex); (c) at a face saddle ``p`` where ``grad F`` points out of the cube: the
   two sides merging there are joined *on the face* through ``p`` for every level below ``F(p)``, so at level 0
   they are already one surface group; (d) at an interior saddle ``s`` with ``F(s) > 0`` whose Hessian has exactly
   one positive eigenvalue (``det H > 0``, since ``trace H = 0``): the upper set near ``s`` is a double cone with
   two nappes, and the merge joins the components of ``{F > F(s)}`` holding the two nappes. (Saddles with two
   positive eigenvalues change ``H_1``/``H_2`` of the upper set, not its components.) So the components of ``P``
   are the positive surface groups united by the interior saddles of type (d); by symmetry (``-F``) the
   components of ``N`` are the negative surface groups united by the interior saddles with ``F(s) < 0`` and
   ``det H < 0``.
5. *Which groups a body saddle joins.* With ``F_xy, F_xz, F_yz`` the mixed derivatives at ``s`` (the Hessian of a
   trilinear function has a zero diagonal, so ``det H = 2 F_xy F_xz F_yz``), the restriction of ``F`` to the
   plane ``z = z_s`` is bilinear with its critical point at ``s``, hence exactly
   ``F(x, y, z_s) = F(s) + F_xy (x - x_s)(y - y_s)``. In that plane the two open quadrants where
   ``F_xy dx dy > 0`` lie entirely in ``{F > F(s)}``; each reaches a corner of the square ``[0,1]^2 x {z_s}``,
   i.e. a point ``E`` on a vertical cube edge, by a straight segment along which ``F > F(s)``. The plane section
   of the Hessian's double cone ``{d^T H d > 0}`` is two opposite sectors, one in each nappe, so the two
   segments leave ``s`` through the two different nappes. ``E`` lies in the surface group of the positive end of
   its vertical edge. Thus a type-(d) saddle joins the surface groups of the two vertical edges ``(x, y)`` with
   ``(x - x_s)(y - y_s)`` of the sign of ``F_xy``; a negative saddle (``F(s) < 0``, ``det H < 0``) joins the
   negative groups of the two other vertical edges.
6. *Interior critical points.* ``grad F = 0`` reduces to a quadratic: with ``F = a0 + a1 x + a2 y + a3 z +
   a4 xy + a5 yz + a6 xz + a7 xyz`` and ``a7 != 0``, the shift ``X = x + a5/a7, Y = y + a6/a7, Z = z + a4/a7``
   turns it into ``YZ = p, XZ = q, XY = r`` (``p = (a4 a6 - a1 a7)/a7^2``, ``q = (a4 a5 - a2 a7)/a7^2``,
   ``r = (a5 a6 - a3 a7)/a7^2``), whose solutions are ``(XYZ)^2 = pqr``, ``X = XYZ/p`` ... -- two critical points
   when ``pqr > 0``, none otherwise. With ``a7 = 0`` the gradient is linear and there is at most one. So there are
   at most two interior saddles.
7. *Surface pieces.* The cube is a ball; a properly embedded connected surface separates it, so the graph whose
   nodes are the 3-D components of ``P`` and ``N`` and whose arcs are the surface pieces is a tree:
   ``#pieces = #positive 3-D groups + #negative 3-D groups - 1``, and two adjacent components share exactly one
   piece. No piece is closed (by (1)), so each piece is bounded by the loops separating the surface groups of its
   two components. In a trilinear cell each piece has genus 0: a disk (one loop) or, when two surface groups of
   one sign connect only through the interior, a tube (two loops); its Euler characteristic is
   ``2 - #loops``. The module checks the tree count on every cell it analyses.

The function :func:`analyze_cell` returns all of this, plus a ``margin`` (the smallest relative distance to a
degeneracy: a corner value, a face decider or a body saddle near a tie, a body saddle near the boundary) that
callers use to keep away from ties the float32 engine may resolve either way. :func:`mc33_subcase` names the
Chernyaev/Lewiner Marching Cubes 33 subcase of an analysed cell. ``tests/engine/isosurface/test_mc33_cells.py`` checks this
reference against brute force (connected components and Betti numbers of a fine sampling).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import cache

CORNERS: tuple[tuple[int, int, int], ...] = tuple((i & 1, (i >> 1) & 1, (i >> 2) & 1) for i in range(8))
EDGES: tuple[tuple[int, int], ...] = tuple((i, i | (1 << a)) for a in range(3) for i in range(8) if not (i >> a) & 1)


def _face_corners(axis: int, side: int) -> tuple[int, int, int, int]:
    """The face's corners in cyclic order (so that 0/2 and 1/3 are the diagonals)."""
    u, v = [a for a in range(3) if a != axis]
    out = []
    for cu, cv in ((0, 0), (1, 0), (1, 1), (0, 1)):
        out.append((side << axis) | (cu << u) | (cv << v))
    return tuple(out)  # type: ignore[return-value]


# face k = 2 * axis + side; outward normal along +axis for side 1, -axis for side 0
FACES: tuple[tuple[int, int, int, int], ...] = tuple(_face_corners(a, s) for a in range(3) for s in (0, 1))
FACE_NORMALS: tuple[tuple[int, int, int], ...] = tuple(
    tuple((2 * s - 1) if b == a else 0 for b in range(3)) for a in range(3) for s in (0, 1)
)


def edge_key(i: int, j: int) -> tuple[int, int]:
    return (i, j) if i < j else (j, i)


def face_edges(face: int) -> tuple[tuple[int, int], ...]:
    c = FACES[face]
    return tuple(edge_key(c[k], c[(k + 1) % 4]) for k in range(4))


def faces_of_edge(edge: tuple[int, int]) -> tuple[int, ...]:
    return tuple(f for f in range(6) if edge[0] in FACES[f] and edge[1] in FACES[f])


class DegenerateCell(ValueError):
    """The values sit exactly on a degeneracy (a value or a saddle value equal to the level, ...)."""


class _UnionFind:
    def __init__(self, items: list[int]) -> None:
        self.parent = {i: i for i in items}

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def union(self, i: int, j: int) -> bool:
        ri, rj = self.find(i), self.find(j)
        if ri == rj:
            return False
        self.parent[max(ri, rj)] = min(ri, rj)
        return True

    def groups(self) -> tuple[frozenset[int], ...]:
        out: dict[int, set[int]] = {}
        for i in self.parent:
            out.setdefault(self.find(i), set()).add(i)
        return tuple(sorted((frozenset(g) for g in out.values()), key=min))


@dataclass(frozen=True)
class BodySaddle:
    point: tuple[float, float, float]  # (x, y, z)
    value: float  # F(s) minus level
    det_hessian: float
    joins: tuple[int, int] | None  # two corners (of the saddle's sign) whose groups it joins, if it is a merge saddle


@dataclass(frozen=True)
class CellTopology:
    values: tuple[float, ...]  # corner values minus the level
    positive: tuple[bool, ...]
    face_joins: tuple[bool | None, ...]  # per face: None (not ambiguous), True (positive diagonal joined), False
    surface_groups: tuple[tuple[frozenset[int], ...], tuple[frozenset[int], ...]]  # (positive, negative)
    groups: tuple[tuple[frozenset[int], ...], tuple[frozenset[int], ...]]  # 3-D groups (positive, negative)
    loops: tuple[frozenset[tuple[int, int]], ...]  # contour loops on the cube surface, as sets of cut edges
    loop_sides: tuple[tuple[int, int], ...]  # per loop: (index of positive, index of negative) surface group
    pieces: tuple[frozenset[int], ...]  # per surface piece: the indices of its loops
    saddles: tuple[BodySaddle, ...]  # interior critical points of F
    margin: float  # relative distance to the nearest degeneracy

    @property
    def mask(self) -> int:
        return sum(1 << i for i in range(8) if self.positive[i])

    @property
    def cut_edges(self) -> frozenset[tuple[int, int]]:
        return frozenset(e for e in EDGES if self.positive[e[0]] != self.positive[e[1]])

    @property
    def piece_loops(self) -> list[frozenset[frozenset[tuple[int, int]]]]:
        """Each piece as the set of its loops (each loop a set of cut edges)."""
        return [frozenset(self.loops[i] for i in p) for p in self.pieces]

    @property
    def piece_euler(self) -> list[int]:
        return [2 - len(p) for p in self.pieces]

    @property
    def tunnel(self) -> bool:
        """Two surface groups of one sign connect only through the interior (a tube piece)."""
        return any(len(p) > 1 for p in self.pieces)


def trilinear_coefficients(f: tuple[float, ...]) -> tuple[float, ...]:
    """``a0..a7`` of ``F = a0 + a1 x + a2 y + a3 z + a4 xy + a5 yz + a6 xz + a7 xyz``."""
    return (
        f[0],
        f[1] - f[0],
        f[2] - f[0],
        f[4] - f[0],
        f[3] - f[2] - f[1] + f[0],
        f[6] - f[4] - f[2] + f[0],
        f[5] - f[4] - f[1] + f[0],
        f[7] - f[6] - f[5] - f[3] + f[4] + f[2] + f[1] - f[0],
    )


def evaluate(f: tuple[float, ...], x: float, y: float, z: float) -> float:
    a = trilinear_coefficients(f)
    return a[0] + a[1] * x + a[2] * y + a[3] * z + a[4] * x * y + a[5] * y * z + a[6] * x * z + a[7] * x * y * z


def _gradient_hessian(a: tuple[float, ...], x: float, y: float, z: float):
    g = (
        a[1] + a[4] * y + a[6] * z + a[7] * y * z,
        a[2] + a[4] * x + a[5] * z + a[7] * x * z,
        a[3] + a[5] * y + a[6] * x + a[7] * x * y,
    )
    fxy, fyz, fxz = a[4] + a[7] * z, a[5] + a[7] * x, a[6] + a[7] * y
    return g, (fxy, fyz, fxz)


def _solve3(m: list[list[float]], b: list[float]) -> tuple[float, float, float] | None:
    det = (
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    )
    if det == 0.0 or not math.isfinite(det):
        return None
    out = []
    for col in range(3):
        mm = [row[:] for row in m]
        for r in range(3):
            mm[r][col] = b[r]
        d = (
            mm[0][0] * (mm[1][1] * mm[2][2] - mm[1][2] * mm[2][1])
            - mm[0][1] * (mm[1][0] * mm[2][2] - mm[1][2] * mm[2][0])
            + mm[0][2] * (mm[1][0] * mm[2][1] - mm[1][1] * mm[2][0])
        )
        out.append(d / det)
    return out[0], out[1], out[2]


def critical_points(f: tuple[float, ...]) -> list[tuple[float, float, float]]:
    """All critical points of the trilinear function on R^3 (isolated ones; at most two), polished by Newton."""
    a = trilinear_coefficients(f)
    scale = max(abs(v) for v in f)
    pts: list[tuple[float, float, float]] = []
    if abs(a[7]) > 1e-12 * scale:
        a7 = a[7]
        p = (a[4] * a[6] - a[1] * a7) / (a7 * a7)
        q = (a[4] * a[5] - a[2] * a7) / (a7 * a7)
        r = (a[5] * a[6] - a[3] * a7) / (a7 * a7)
        pqr = p * q * r
        if pqr > 0.0:
            m = math.sqrt(pqr)
            for sgn in (1.0, -1.0):
                xyz = sgn * m
                pts.append((xyz / p - a[5] / a7, xyz / q - a[6] / a7, xyz / r - a[4] / a7))
    else:  # gradient linear: [[0, a4, a6], [a4, 0, a5], [a6, a5, 0]] (x, y, z) = -(a1, a2, a3)
        sol = _solve3([[0.0, a[4], a[6]], [a[4], 0.0, a[5]], [a[6], a[5], 0.0]], [-a[1], -a[2], -a[3]])
        if sol is not None:
            pts.append(sol)
    polished = []
    for x, y, z in pts:
        for _ in range(3):
            g, (fxy, fyz, fxz) = _gradient_hessian(a, x, y, z)
            step = _solve3([[0.0, fxy, fxz], [fxy, 0.0, fyz], [fxz, fyz, 0.0]], [-g[0], -g[1], -g[2]])
            if step is None or not all(math.isfinite(s) for s in step):
                break
            x, y, z = x + step[0], y + step[1], z + step[2]
        polished.append((x, y, z))
    return polished


def analyze_cell(values, level: float = 0.0) -> CellTopology:
    """Topology of ``{F = level}`` in the unit cube for corner values ``values[i]`` (corner numbering above)."""
    f = tuple(float(v) - float(level) for v in values)
    if len(f) != 8:
        raise ValueError(f"Expected 8 corner values, got {len(f)}")
    if any(v == 0.0 for v in f):
        raise DegenerateCell(f"a corner value equals the level: {f}")
    scale = max(abs(v) for v in f)
    pos = tuple(v > 0 for v in f)
    margin = min(abs(v) for v in f) / scale

    # --- surface groups (edges + asymptotic decider) ---
    uf = _UnionFind(list(range(8)))
    for i, j in EDGES:
        if pos[i] == pos[j]:
            uf.union(i, j)
    face_joins: list[bool | None] = []
    for c in FACES:
        v = [f[k] for k in c]
        if pos[c[0]] == pos[c[2]] and pos[c[1]] == pos[c[3]] and pos[c[0]] != pos[c[1]]:
            (pa, pc), (nb, nd) = ((v[0], v[2]), (v[1], v[3])) if pos[c[0]] else ((v[1], v[3]), (v[0], v[2]))
            d = pa * pc - nb * nd
            if d == 0.0:
                raise DegenerateCell(f"face saddle value equals the level: {f}")
            margin = min(margin, abs(d) / max(pa * pc, nb * nd))
            joined_pos = d > 0
            face_joins.append(joined_pos)
            diag = (c[0], c[2]) if pos[c[0]] == joined_pos else (c[1], c[3])
            uf.union(*diag)
        else:
            face_joins.append(None)
    surface_root = {i: uf.find(i) for i in range(8)}
    pos_surface = tuple(g for g in uf.groups() if pos[min(g)])
    neg_surface = tuple(g for g in uf.groups() if not pos[min(g)])

    # --- contour loops ---
    cut = [e for e in EDGES if pos[e[0]] != pos[e[1]]]
    link = _UnionFind(list(range(len(cut))))
    index = {e: k for k, e in enumerate(cut)}
    for fi, c in enumerate(FACES):
        fe = [e for e in face_edges(fi) if e in index]
        if len(fe) == 2:
            link.union(index[fe[0]], index[fe[1]])
        elif len(fe) == 4:
            # the contour cuts off the corners of the sign whose diagonal is not joined
            cut_off = [k for k in c if pos[k] != face_joins[fi]]
            for k in cut_off:
                inc = [index[e] for e in fe if k in e]
                link.union(inc[0], inc[1])
        elif fe:
            raise AssertionError(f"a face with {len(fe)} cut edges")
    loops = tuple(frozenset(cut[k] for k in g) for g in link.groups())

    # --- body saddles and 3-D groups ---
    a = trilinear_coefficients(f)
    uf3 = _UnionFind(list(range(8)))
    for i in range(8):
        uf3.union(i, surface_root[i])
    saddles = []
    for x, y, z in critical_points(f):
        if not all(math.isfinite(t) for t in (x, y, z)):
            continue
        dist = min(x, 1 - x, y, 1 - y, z, 1 - z)  # > 0 inside
        margin = min(margin, abs(dist))
        if dist <= 0:
            continue
        fs = evaluate(f, x, y, z)
        _, (fxy, fyz, fxz) = _gradient_hessian(a, x, y, z)
        det = 2.0 * fxy * fyz * fxz
        if fs == 0.0 or det == 0.0:
            raise DegenerateCell(f"degenerate body saddle at {(x, y, z)}: F={fs}, det H={det}: {f}")
        margin = min(margin, abs(fs) / scale, abs(det) ** (1 / 3) / scale)
        joins = None
        if (fs > 0 and det > 0) or (fs < 0 and det < 0):
            # quadrants of the plane z = z_s on the saddle's side: sign(dx dy) = sign(F_xy) (positive merge) or
            # -sign(F_xy) (negative merge); they reach the vertical edges (cx, cy) of the matching quadrants
            want = (fxy > 0) == (fs > 0)
            ends = []
            for cx, cy in ((0, 0), (1, 0), (0, 1), (1, 1)):
                if ((cx - x) * (cy - y) > 0) == want:
                    lo, hi = cx | (cy << 1), cx | (cy << 1) | 4
                    end = [k for k in (lo, hi) if pos[k] == (fs > 0)]
                    if not end:
                        raise AssertionError(f"saddle quadrant reaches a vertical edge of the wrong sign: {f}")
                    ends.append(end[0])
            joins = (ends[0], ends[1])
            uf3.union(*joins)
        saddles.append(BodySaddle((x, y, z), fs, det, joins))
    groups3 = uf3.groups()
    pos_groups = tuple(g for g in groups3 if pos[min(g)])
    neg_groups = tuple(g for g in groups3 if not pos[min(g)])

    # --- loops -> sides -> pieces ---
    pos_idx = {k: n for n, g in enumerate(pos_surface) for k in g}
    neg_idx = {k: n for n, g in enumerate(neg_surface) for k in g}
    loop_sides = []
    pieces_by_key: dict[tuple[int, int], set[int]] = {}
    for li, loop in enumerate(loops):
        sides = {(pos_idx[i if pos[i] else j], neg_idx[j if pos[i] else i]) for i, j in loop}
        if len(sides) != 1:
            raise AssertionError(f"a contour loop borders several surface groups: {sides}")
        side = sides.pop()
        loop_sides.append(side)
        key = (uf3.find(min(pos_surface[side[0]])), uf3.find(min(neg_surface[side[1]])))
        pieces_by_key.setdefault(key, set()).add(li)
    pieces = tuple(sorted((frozenset(p) for p in pieces_by_key.values()), key=min))
    if pos_groups and neg_groups and len(pieces) != len(pos_groups) + len(neg_groups) - 1:
        raise AssertionError(
            f"tree count violated: {len(pieces)} pieces, {len(pos_groups)}+{len(neg_groups)} groups: {f}"
        )
    return CellTopology(
        values=f,
        positive=pos,
        face_joins=tuple(face_joins),
        surface_groups=(pos_surface, neg_surface),
        groups=(pos_groups, neg_groups),
        loops=loops,
        loop_sides=tuple(loop_sides),
        pieces=pieces,
        saddles=tuple(saddles),
        margin=margin,
    )


# ---------------------------------------------------------------------------------------------------------------
# Marching Cubes 33 subcases
# ---------------------------------------------------------------------------------------------------------------


@cache
def rotations() -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    """The 24 rotations of the cube as (corner permutation, face permutation)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for flips in itertools.product((0, 1), repeat=3):
            sign = (-1) ** sum(flips)
            # parity of the axis permutation
            inv = sum(1 for i in range(3) for j in range(i + 1, 3) if perm[i] > perm[j])
            if sign * (-1) ** inv != 1:
                continue
            cmap = []
            for v in range(8):
                c = CORNERS[v]
                n = [c[perm[a]] ^ flips[a] for a in range(3)]
                cmap.append(n[0] | (n[1] << 1) | (n[2] << 2))
            fmap = []
            for face in range(6):
                image = frozenset(cmap[k] for k in FACES[face])
                fmap.append(next(g for g in range(6) if frozenset(FACES[g]) == image))
            out.append((tuple(cmap), tuple(fmap)))
    assert len(out) == 24
    return tuple(out)


def _apply(cmap: tuple[int, ...], mask: int) -> int:
    return sum(1 << cmap[i] for i in range(8) if (mask >> i) & 1)


# Representatives of the 15 classes of sign configurations under rotations and complement (Lorensen's numbering;
# 11 and 14 are mirror images, told apart as in Lewiner's table: case 11 holds {0,1,3,4}, case 14 {0,2,3,4}).
BASE_REPRESENTATIVES: dict[int, tuple[int, ...]] = {
    0: (),
    1: (0,),
    2: (0, 1),
    3: (0, 3),
    4: (0, 7),
    5: (0, 1, 2),
    6: (0, 1, 7),
    7: (1, 2, 7),
    8: (0, 1, 2, 3),
    9: (0, 1, 2, 4),
    10: (0, 1, 6, 7),
    11: (0, 1, 3, 4),
    12: (0, 1, 2, 7),
    13: (0, 3, 5, 6),
    14: (0, 2, 3, 4),
}


@cache
def base_case_table() -> tuple[int, ...]:
    """Base MC case (0..14) of each of the 256 sign masks (bit i set: corner i positive)."""
    table = [-1] * 256
    for case, corners in BASE_REPRESENTATIVES.items():
        m0 = sum(1 << c for c in corners)
        for cmap, _ in rotations():
            for comp in (0, 255):
                m = _apply(cmap, m0) ^ comp
                if table[m] not in (-1, case):
                    raise AssertionError(f"mask {m} in cases {table[m]} and {case}")
                table[m] = case
    assert -1 not in table
    return tuple(table)


def _chiral_class_12(mask: int, face_joins: tuple[bool | None, ...]) -> str:
    """Case 12 with the two ambiguous faces deciding differently: two mirror-image classes (12.2 and 12.3).

    Convention: the class of ``{0,1,2,7}`` positive with face x=1 joining its positive diagonal (1-7) and face
    y=1 joining its negative diagonal (3-6) is called 12.2; its mirror image (x <-> y) is 12.3.
    """
    ref_mask = sum(1 << c for c in (0, 1, 2, 7))
    ref = [None] * 6
    ref[2 * 0 + 1] = True  # face x=1
    ref[2 * 1 + 1] = False  # face y=1
    for cmap, fmap in rotations():
        for comp in (False, True):
            m = _apply(cmap, ref_mask) ^ (255 if comp else 0)
            if m != mask:
                continue
            joins = [None] * 6
            for face in range(6):
                if ref[face] is not None:
                    joins[fmap[face]] = ref[face] != comp
            if tuple(joins) == face_joins:
                return "12.2"
    return "12.3"


def mc33_subcase(topo: CellTopology) -> str:
    """The Marching Cubes 33 subcase name (``"0"``, ``"1"``, ..., ``"13.5.2"``, ``"14"``) of an analysed cell.

    The base case is the class of the sign mask under the cube's rotations and complement; the subcase follows
    from which diagonals the ambiguous faces join (relative to the marked, i.e. minority, sign where there is
    one) and whether a tube is present. Returns ``"unexpected:..."`` for a combination outside the 33.
    """
    case = base_case_table()[topo.mask]
    npos = sum(topo.positive)
    marked_positive = npos <= 4
    amb = [fc for fc in range(6) if topo.face_joins[fc] is not None]
    joins_marked = [topo.face_joins[fc] == marked_positive for fc in amb]
    k = sum(joins_marked)
    tube = topo.tunnel
    tag = f"unexpected:case{case}:faces{joins_marked}:tube{tube}"
    if case in (0, 1, 2, 5, 8, 9, 11, 14):
        return tag if tube else str(case)
    if case == 3:
        return tag if tube else ("3.2" if k == 1 else "3.1")
    if case == 4:
        return "4.1.2" if tube else "4.1.1"
    if case == 6:
        if k == 1:
            return tag if tube else "6.2"
        return "6.1.2" if tube else "6.1.1"
    if case == 7:
        if k < 3:
            return tag if tube else ("7.1", "7.2", "7.3")[k]
        return "7.4.2" if tube else "7.4.1"
    if case == 10:
        if k == 1:
            return tag if tube else "10.2"
        return "10.1.2" if tube else "10.1.1"
    if case == 12:
        if k == 1:
            return tag if tube else _chiral_class_12(topo.mask, topo.face_joins)
        return "12.1.2" if tube else "12.1.1"
    if case == 13:
        kp = sum(1 for fc in range(6) if topo.face_joins[fc])  # faces joining the positive diagonal
        if kp in (0, 6):
            return tag if tube else "13.1"
        if kp in (1, 5):
            return tag if tube else "13.2"
        if kp in (2, 4):
            odd = [fc for fc in range(6) if topo.face_joins[fc] == (kp == 2)]
            if odd[0] // 2 == odd[1] // 2:  # opposite faces
                return tag
            return tag if tube else "13.3"
        joined = [fc for fc in range(6) if topo.face_joins[fc]]
        common = set(FACES[joined[0]]) & set(FACES[joined[1]]) & set(FACES[joined[2]])
        if not common:
            return tag  # three faces in a row
        if topo.positive[common.pop()]:  # the positive-joining faces meet at a positive corner
            return tag if tube else "13.4"
        return "13.5.2" if tube else "13.5.1"
    return tag


MC33_SUBCASES: tuple[str, ...] = (
    "0", "1", "2", "3.1", "3.2", "4.1.1", "4.1.2", "5", "6.1.1", "6.1.2", "6.2", "7.1", "7.2", "7.3", "7.4.1",
    "7.4.2", "8", "9", "10.1.1", "10.1.2", "10.2", "11", "12.1.1", "12.1.2", "12.2", "12.3", "13.1", "13.2", "13.3",
    "13.4", "13.5.1", "13.5.2", "14",
)  # fmt: skip
