"""The phases of one decimation pass (meshoptimizer's simplifier loop, read as named phases), each a function over
the mesh under decimation and the work arrays its passes reuse (``Collapsing``); the loop that runs them is
``engine.decimation.passes.decimate_carrying``. In the order of a pass:

1. ``update_adjacency``: every vertex's star again, after the last pass's collapses (not on the first pass);
2. ``price``: each changed edge's quadric cost code and new position (``kernels.costs.edge_costs``);
3. ``rank``: a histogram of the codes gives the cost quantile under which edges compete (``Cut``);
4. ``guard``: the edges under the cut are listed and checked (link condition, valences, turns, degeneracy:
   ``kernels.guards.check_candidates``);
5. ``claim``: the listed edges claim their stars in rounds; the winners' stars are face-disjoint;
6. ``trim``: the winners beyond the collapses still needed give way, cheapest kept;
7. ``perform``: the winners collapse (``kernels.collapse.apply_collapses``), and mark what they changed dirty;
8. ``compact``: the faces array drops its removed faces once few enough are alive.

``start`` builds the state (stars, vertex classes, quadrics, pinned vertices) and ``finish`` compacts the result.
Every sync point is labelled. Written once over the backend interface (``engine.backend``): the Warp kernels and
their OpenCL C twins are named in ``engine.decimation.kernel_specs``; the device mesh's stars, classes and
compaction are ``engine.decimation.meshops``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC10D, Backend
from engine.backend.select import backend_of
from engine.decimation import kernel_specs as K
from engine.decimation import meshops
from engine.decimation.meshops import Stars
from engine.surface import devmesh
from engine.surface.devmesh import CLASS_NAMES

OVERSHOOT = 4  # near the target, this many candidates per collapse still needed (the surplus winners are trimmed)
TRIMS = 4  # at most this many trims of a pass's surplus winners (each a hashed share of the last cost bin)
HIST_BINS = 1 << 16
COMPACT_BELOW = 0.85  # the faces array is compacted when its live share falls below this (swept: 0.5 -> 0.85, -8 %)


@dataclass
class Collapsing:
    """A device mesh under decimation on backend ``be`` (its own copies of ``pos`` and ``faces``; removed faces are
    ``(-1, -1, -1)``, ``alive`` of them are not), its stars, vertex classes and quadrics about ``origin`` (a kernel
    argument: ``meshops.origin_arg``), and the work arrays every pass reuses (the per-slot arrays grow with the
    faces array: ``price``)."""

    be: Backend
    pos: Any
    faces: Any
    inc: Stars
    state: Any
    quad: Any
    origin: Any
    cos_max: Any  # the cosine of the largest turn of a face normal (a float64 argument)
    alive: int
    hist: Any
    counter: Any
    removed: Any
    n_listed: Any
    dirty: Any  # per vertex: something an edge at it reads has changed since it was priced
    key: Any = None  # per half-edge slot: its cost code (``NO_KEY``: not collapsible)
    target_pos: Any = None  # per slot: the survivor's new position
    cand: Any = None  # per slot: competing (1), won (2), trimmed (``TRIMMED``) or not (0)
    checked: Any = None  # per slot: its guards ran since it was priced
    listing: Any = None  # the slots listed as candidates (``n_listed`` of them)
    boost: int = 1  # grows while passes fall short of what is needed (candidates refused by the guards)

    @property
    def listed(self) -> list[Any]:
        return [self.listing, self.n_listed]


@dataclass(frozen=True)
class Cut:
    """A pass's cost quantile: the bin below which edges compete, the hashed share of that bin (of 2^32) that
    competes too, and ``most``, at least the number of candidates listed (the kernels after it run over as many)."""

    bin_below: int
    frac_bits: int
    most: int


def vertex_quadrics(pos: Any, faces: Any, origin: Any = None) -> tuple[Stars, Any, Any, Any]:
    """What the collapses start from, for a device mesh without removed faces (on its backend): the vertices'
    stars, their classes (``meshops.vertex_classes``), the local origin (``origin``, by default the bounding box's
    centre; returned as a kernel argument) and each vertex's quadric (the sum of its faces' area-weighted plane
    quadrics, float64, about that origin)."""
    be = backend_of(pos)
    inc = Stars(be, len(pos)).build(faces, len(faces))
    state = meshops.vertex_classes(be, faces, inc)
    origin = meshops.origin_arg(be, meshops.bbox_centre(be, pos) if origin is None else origin)
    quad = be.empty(len(pos), VEC10D)
    be.launch(K.VERTEX_QUADRICS, len(pos), [pos, faces, *inc.inputs, origin, quad])
    return inc, state, origin, quad


def compact_carrying(pos: Any, faces: Any, quad: Any) -> tuple[Any, Any, Any, Any]:
    """``compact_vertices`` that also carries the quadrics and says where each kept vertex was:
    ``(pos, faces, quad, kept)`` with ``kept[i]`` the input index of output vertex ``i`` (``faces`` is remapped in
    place)."""
    return meshops.compact_carrying(backend_of(pos), pos, faces, quad)


def _quantile(hist: np.ndarray, m: int) -> tuple[int, int, int]:
    """The cost bin holding the ``m``-th cheapest entry of a histogram, the share of that bin (of 2^32) that brings
    the count to about ``m``, and the count up to and with that bin. (Cumulative sums over rows of 256 bins, then
    within the row found: a whole-histogram cumsum cost 0.26 ms a pass on the H100 host.)"""
    rows = hist.reshape(-1, 256)
    cum_rows = np.cumsum(rows.sum(axis=1, dtype=np.int64))
    r = min(int(np.searchsorted(cum_rows, m)), len(rows) - 1)
    cum = np.cumsum(rows[r], dtype=np.int64) + (int(cum_rows[r - 1]) if r else 0)
    k = min(int(np.searchsorted(cum, m)), 255)
    below = int(cum[k - 1]) if k else (int(cum_rows[r - 1]) if r else 0)
    kbin = r * 256 + k
    frac_bits = min(max(m - below, 0) * (1 << 32) // max(int(hist[kbin]), 1), 1 << 32)
    return kbin, frac_bits, int(cum[k])


def _winner_histogram(c: Collapsing, n: int) -> np.ndarray:
    """The pass's winners counted by cost bin (on the host)."""
    c.be.fill(c.hist, 0)
    c.be.launch(K.WINNER_HISTOGRAM, n, [*c.listed, c.cand, c.key, c.hist])
    return c.be.to_host(c.hist)  # sync point


def start(
    pos: Any, faces: Any, *, locked: Any, quadrics: Any, origin: Any, max_normal_turn_deg: float
) -> tuple[Collapsing, dict[str, int]]:
    """The state a decimation starts from (on the mesh's backend): copies of the mesh, its stars and vertex
    classes, the quadrics (each vertex's faces' about ``origin``, or carried in as ``quadrics``), the vertices in
    ``locked`` pinned; and the count of each vertex class (a sync point)."""
    be = backend_of(pos)
    pos = be.clone(pos)
    faces = be.clone(faces)
    nv = len(pos)
    if quadrics is None:
        inc, state, origin, quad = vertex_quadrics(pos, faces, origin)
    else:  # carried in: the error stays measured against the surface before the earlier collapses
        inc = Stars(be, nv).build(faces, len(faces))
        state = meshops.vertex_classes(be, faces, inc)
        origin = meshops.origin_arg(be, meshops.bbox_centre(be, pos) if origin is None else origin)
        quad = be.clone(quadrics)
    if locked is not None:
        be.launch(K.LOCK_VERTICES, nv, [locked, state])
    classes = devmesh.class_counts(state)  # sync point
    c = Collapsing(
        be=be,
        pos=pos,
        faces=faces,
        inc=inc,
        state=state,
        quad=quad,
        origin=origin,
        cos_max=be.scalar(math.cos(math.radians(max_normal_turn_deg)), np.float64),
        alive=len(faces),
        hist=be.zeros(HIST_BINS, np.int32),
        counter=be.zeros(1, np.int32),
        removed=be.zeros(1, np.int32),
        n_listed=be.zeros(1, np.int32),
        dirty=be.full(nv, 1, np.int32),
    )
    return c, {name: int(n) for name, n in zip(CLASS_NAMES, classes, strict=True)}


def update_adjacency(c: Collapsing) -> None:
    """Every vertex's star again, from the faces the last pass left."""
    c.inc.build(c.faces, c.alive)


def price(c: Collapsing) -> None:
    """The cost code and new position of every edge whose ends are dirty (the per-slot arrays grown first where the
    faces array outgrew them)."""
    be, slots = c.be, 3 * len(c.faces)
    if c.key is None or len(c.key) < slots:
        c.key = be.empty(slots, np.int32)
        c.target_pos = be.empty(slots, VEC3F)
        c.cand = be.empty(slots, np.int32)
        c.checked = be.empty(slots, np.int32)
        c.listing = be.empty(slots, np.int32)
    inputs = [c.pos, c.faces, c.inc.count, c.state, c.quad, c.origin, c.dirty, c.key, c.target_pos, c.checked]
    be.launch(K.EDGE_COSTS, slots, inputs)


def rank(c: Collapsing, needed: int, candidate_fraction: float) -> Cut | None:
    """The pass's cut: about ``candidate_fraction`` of the collapsible edges, cheapest first, but no more than
    ``OVERSHOOT`` (times the boost) per collapse still ``needed``; None where no edge may collapse."""
    c.be.fill(c.hist, 0)
    c.be.launch(K.COST_HISTOGRAM, 3 * len(c.faces), [c.key, c.hist])
    h = c.be.to_host(c.hist)  # sync point: 256 KB
    n_valid = int(h.sum())
    if n_valid == 0:
        return None
    m = max(1, min(int(candidate_fraction * n_valid), OVERSHOOT * needed * c.boost))
    return Cut(*_quantile(h, m))


def guard(c: Collapsing, cut: Cut) -> None:
    """List the edges under the cut and run their guards (an edge refused drops out of the pass)."""
    be = c.be
    bits = be.scalar(cut.frac_bits, np.int64)
    be.fill(c.n_listed, 0)
    be.launch(K.SELECT_CANDIDATES, 3 * len(c.faces), [c.key, cut.bin_below, bits, c.cand, c.listing, c.n_listed])
    inputs = [*c.listed, c.cand, c.pos, c.faces, *c.inc.inputs, c.state, c.quad, c.origin, c.cos_max]
    be.launch(K.CHECK_CANDIDATES, cut.most, [*inputs, cut.bin_below, bits, c.key, c.target_pos, c.checked])


def claim(c: Collapsing, cut: Cut, claim_rounds: int) -> int:
    """The candidates claim their stars in ``claim_rounds`` rounds; returns how many won (a sync point)."""
    be = c.be
    claim = be.full(len(c.faces), K.CLAIM_FREE, np.int64)
    be.fill(c.counter, 0)
    star = [*c.listed, c.cand, c.key, c.faces, *c.inc.inputs, claim]
    rounds = [  # packed once, launched every round (packing the arguments cost more than the launch)
        be.prepared(K.CLAIM_STARS, cut.most, star),
        be.prepared(K.SETTLE_CLAIMS, cut.most, [*star, c.counter]),
        be.prepared(K.TAKE_STARS, cut.most, [*c.listed, c.cand, c.faces, *c.inc.inputs, claim]),
        be.prepared(K.RELEASE_CLAIMS, len(c.faces), [claim]),
    ]
    for r in range(claim_rounds):  # (the last round's claims are made afresh next pass: not released)
        for launch in rounds if r < claim_rounds - 1 else rounds[:3]:
            launch()
    return int(be.to_host(c.counter)[0])  # sync point


def trim(c: Collapsing, cut: Cut, needed: int, won: int) -> int:
    """Keep no more winners than the collapses still ``needed``, cheapest first (up to ``TRIMS`` hashed shares of
    the last cost bin; if every winner went, the cheapest comes back); returns the winners left."""
    be = c.be
    for salt in range(TRIMS):
        if won <= needed:
            break
        if salt == 0:
            h_won = _winner_histogram(c, cut.most)
        kbin, frac_bits, _ = _quantile(h_won, needed)
        be.launch(K.TRIM_WINNERS, cut.most, [*c.listed, c.cand, c.key, kbin, be.scalar(frac_bits, np.int64), salt])
        h_won = _winner_histogram(c, cut.most)
        won = int(h_won.sum())
        if won == 0:
            best = be.full(1, K.CLAIM_FREE, np.int64)
            be.launch(K.CHEAPEST_TRIMMED, cut.most, [*c.listed, c.cand, c.key, best])
            be.launch(K.RESTORE_CHEAPEST, cut.most, [*c.listed, c.cand, c.key, best])
            won = 1
    return won


def perform(c: Collapsing, cut: Cut) -> int:
    """Collapse the winners; returns the faces removed (a sync point) and leaves dirty what they changed."""
    be = c.be
    be.fill(c.dirty, 0)
    be.fill(c.removed, 0)
    inputs = [*c.listed, c.cand, c.target_pos, c.faces, *c.inc.inputs, c.state, c.quad, c.pos, c.removed, c.dirty]
    be.launch(K.APPLY_COLLAPSES, cut.most, inputs)
    n_removed = int(be.to_host(c.removed)[0])  # sync point
    c.alive -= n_removed
    return n_removed


def compact(c: Collapsing) -> None:
    """Drop the removed faces once fewer than ``COMPACT_BELOW`` of the slots are alive (new slots: every edge is
    priced and checked again)."""
    if c.alive < len(c.faces) * COMPACT_BELOW:
        c.faces = meshops.compact_faces(c.be, c.faces, c.alive)
        c.be.fill(c.dirty, 1)


def finish(c: Collapsing, carry: bool) -> tuple[Any, Any, Any, Any]:
    """The compact result: ``(pos, faces, quad, kept)``, with the kept vertices' quadrics and input indices where
    ``carry`` (else None)."""
    faces = meshops.compact_faces(c.be, c.faces, c.alive) if c.alive < len(c.faces) else c.faces
    if carry:
        return meshops.compact_carrying(c.be, c.pos, faces, c.quad)
    out_pos, out_faces = devmesh.compact_vertices(c.pos, faces)
    return out_pos, out_faces, None, None
