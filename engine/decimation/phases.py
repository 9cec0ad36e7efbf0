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
Every sync point is labelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.surface.devmesh import (
    CLASS_NAMES,
    Incidence,
    bbox_centre,
    compact_faces,
    compact_vertices,
    used_slots,
    vertex_classes,
)

OVERSHOOT = 4  # near the target, this many candidates per collapse still needed (the surplus winners are trimmed)
TRIMS = 4  # at most this many trims of a pass's surplus winners (each a hashed share of the last cost bin)
HIST_BINS = 1 << 16
COMPACT_BELOW = 0.85  # the faces array is compacted when its live share falls below this (swept: 0.5 -> 0.85, -8 %)


@dataclass
class Collapsing:
    """A device mesh under decimation (its own copies of ``pos`` and ``faces``; removed faces are ``(-1, -1, -1)``,
    ``alive`` of them are not), its stars, vertex classes and quadrics about ``origin``, and the work arrays every
    pass reuses (the per-slot arrays grow with the faces array: ``price``)."""

    pos: Any
    faces: Any
    inc: Incidence
    state: Any
    quad: Any
    origin: Any
    cos_max: Any  # the cosine of the largest turn of a face normal (float64)
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
    def listed(self) -> tuple[Any, Any]:
        return self.listing, self.n_listed


@dataclass(frozen=True)
class Cut:
    """A pass's cost quantile: the bin below which edges compete, the hashed share of that bin (of 2^32) that
    competes too, and ``most``, at least the number of candidates listed (the kernels after it run over as many)."""

    bin_below: int
    frac_bits: int
    most: int


def vertex_quadrics(pos: Any, faces: Any, origin: Any = None) -> tuple[Incidence, Any, Any, Any]:
    """What the collapses start from, for a device mesh without removed faces: the vertices' stars, their classes
    (``devmesh.vertex_classes``), the local origin (``origin``, by default the bounding box's centre) and each
    vertex's quadric (the sum of its faces' area-weighted plane quadrics, float64, about that origin)."""
    import warp as wp

    from engine.decimation.kernels import quadrics as kquad

    inc = Incidence(len(pos)).build(faces, len(faces))
    state = vertex_classes(faces, inc)
    if origin is None:
        origin = bbox_centre(pos)
    quad = wp.empty(len(pos), dtype=kquad.quadric, device=pos.device)
    wp.launch(kquad.vertex_quadrics, dim=len(pos), inputs=[pos, faces, *inc.inputs, origin, quad], device=pos.device)
    return inc, state, origin, quad


def compact_carrying(pos: Any, faces: Any, quad: Any) -> tuple[Any, Any, Any, Any]:
    """``compact_vertices`` that also carries the quadrics and says where each kept vertex was:
    ``(pos, faces, quad, kept)`` with ``kept[i]`` the input index of output vertex ``i`` (``faces`` is remapped in
    place)."""
    import warp as wp

    from engine.decimation.kernels import quadrics as kquad
    from engine.surface.kernels import compaction as kcompact

    with wp.ScopedDevice(pos.device):
        count, slot, n_used = used_slots(pos, faces)
        out = wp.empty(n_used, dtype=wp.vec3)
        kept = wp.empty(n_used, dtype=wp.int32)
        out_quad = wp.empty(n_used, dtype=kquad.quadric)
        wp.launch(kcompact.scatter_vertices, dim=len(pos), inputs=[pos, count, slot, out])
        wp.launch(kquad.scatter_kept, dim=len(pos), inputs=[count, slot, quad, kept, out_quad])
        wp.launch(kcompact.remap_faces, dim=len(faces), inputs=[faces, slot])
    return out, faces, out_quad, kept


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


def _winner_histogram(hist: Any, n: int, listed: tuple[Any, Any], cand: Any, key: Any) -> np.ndarray:
    """The pass's winners counted by cost bin (on the host)."""
    import warp as wp

    from engine.decimation.kernels import claims as kclaim

    hist.zero_()
    wp.launch(kclaim.winner_histogram, dim=n, inputs=[*listed, cand, key, hist])
    return hist.numpy()  # type: ignore[no-any-return]


def start(
    pos: Any, faces: Any, *, locked: Any, quadrics: Any, origin: Any, max_normal_turn_deg: float
) -> tuple[Collapsing, dict[str, int]]:
    """The state a decimation starts from (on the current device): copies of the mesh, its stars and vertex classes,
    the quadrics (each vertex's faces' about ``origin``, or carried in as ``quadrics``), the vertices in ``locked``
    pinned; and the count of each vertex class (a sync point)."""
    import warp as wp

    from engine.decimation.kernels import collapse as kcollapse

    pos = wp.clone(pos)
    faces = wp.clone(faces)
    nv = len(pos)
    if quadrics is None:
        inc, state, origin, quad = vertex_quadrics(pos, faces, origin)
    else:  # carried in: the error stays measured against the surface before the earlier collapses
        inc = Incidence(nv).build(faces, len(faces))
        state = vertex_classes(faces, inc)
        origin = bbox_centre(pos) if origin is None else origin
        quad = wp.clone(quadrics)
    if locked is not None:
        wp.launch(kcollapse.lock_vertices, dim=nv, inputs=[locked, state])
    classes = np.bincount(state.numpy(), minlength=4)  # sync point
    c = Collapsing(
        pos=pos,
        faces=faces,
        inc=inc,
        state=state,
        quad=quad,
        origin=origin,
        cos_max=wp.float64(math.cos(math.radians(max_normal_turn_deg))),
        alive=len(faces),
        hist=wp.zeros(HIST_BINS, dtype=wp.int32),
        counter=wp.zeros(1, dtype=wp.int32),
        removed=wp.zeros(1, dtype=wp.int32),
        n_listed=wp.zeros(1, dtype=wp.int32),
        dirty=wp.ones(nv, dtype=wp.int32),
    )
    return c, {name: int(n) for name, n in zip(CLASS_NAMES, classes, strict=True)}


def update_adjacency(c: Collapsing) -> None:
    """Every vertex's star again, from the faces the last pass left."""
    c.inc.build(c.faces, c.alive)


def price(c: Collapsing) -> None:
    """The cost code and new position of every edge whose ends are dirty (the per-slot arrays grown first where the
    faces array outgrew them)."""
    import warp as wp

    from engine.decimation.kernels import costs as kcost

    slots = 3 * len(c.faces)
    if c.key is None or len(c.key) < slots:
        c.key = wp.empty(slots, dtype=wp.int32)
        c.target_pos = wp.empty(slots, dtype=wp.vec3)
        c.cand = wp.empty(slots, dtype=wp.int32)
        c.checked = wp.empty(slots, dtype=wp.int32)
        c.listing = wp.empty(slots, dtype=wp.int32)
    inputs = [c.pos, c.faces, c.inc.count, c.state, c.quad, c.origin, c.dirty, c.key, c.target_pos, c.checked]
    wp.launch(kcost.edge_costs, dim=slots, inputs=inputs)


def rank(c: Collapsing, needed: int, candidate_fraction: float) -> Cut | None:
    """The pass's cut: about ``candidate_fraction`` of the collapsible edges, cheapest first, but no more than
    ``OVERSHOOT`` (times the boost) per collapse still ``needed``; None where no edge may collapse."""
    import warp as wp

    from engine.decimation.kernels import costs as kcost

    c.hist.zero_()
    wp.launch(kcost.cost_histogram, dim=3 * len(c.faces), inputs=[c.key, c.hist])
    h = c.hist.numpy()  # sync point: 256 KB
    n_valid = int(h.sum())
    if n_valid == 0:
        return None
    m = max(1, min(int(candidate_fraction * n_valid), OVERSHOOT * needed * c.boost))
    return Cut(*_quantile(h, m))


def guard(c: Collapsing, cut: Cut) -> None:
    """List the edges under the cut and run their guards (an edge refused drops out of the pass)."""
    import warp as wp

    from engine.decimation.kernels import costs as kcost
    from engine.decimation.kernels import guards as kguard

    bits = wp.int64(cut.frac_bits)
    c.n_listed.zero_()
    select = [c.key, cut.bin_below, bits, c.cand, c.listing, c.n_listed]
    wp.launch(kcost.select_candidates, dim=3 * len(c.faces), inputs=select)
    inputs = [*c.listed, c.cand, c.pos, c.faces, *c.inc.inputs, c.state, c.quad, c.origin, c.cos_max]
    inputs += [cut.bin_below, bits]
    wp.launch(kguard.check_candidates, dim=cut.most, inputs=inputs, outputs=[c.key, c.target_pos, c.checked])


def claim(c: Collapsing, cut: Cut, claim_rounds: int) -> int:
    """The candidates claim their stars in ``claim_rounds`` rounds; returns how many won (a sync point)."""
    import warp as wp

    from engine.decimation.kernels import claims as kclaim

    claim = wp.full(len(c.faces), kclaim.CLAIM_FREE, dtype=wp.int64)
    c.counter.zero_()
    star = [*c.listed, c.cand, c.key, c.faces, *c.inc.inputs, claim]
    rounds = [  # recorded once, launched every round (packing the arguments cost more than the launch)
        wp.launch(kclaim.claim_stars, dim=cut.most, inputs=star, record_cmd=True),
        wp.launch(kclaim.settle_claims, dim=cut.most, inputs=[*star, c.counter], record_cmd=True),
        wp.launch(
            kclaim.take_stars, dim=cut.most, inputs=[*c.listed, c.cand, c.faces, *c.inc.inputs, claim], record_cmd=True
        ),
        wp.launch(kclaim.release_claims, dim=len(claim), inputs=[claim], record_cmd=True),
    ]
    for r in range(claim_rounds):  # (the last round's claims are made afresh next pass: not released)
        for cmd in rounds if r < claim_rounds - 1 else rounds[:3]:
            cmd.launch()
    return int(c.counter.numpy()[0])  # sync point


def trim(c: Collapsing, cut: Cut, needed: int, won: int) -> int:
    """Keep no more winners than the collapses still ``needed``, cheapest first (up to ``TRIMS`` hashed shares of
    the last cost bin; if every winner went, the cheapest comes back); returns the winners left."""
    import warp as wp

    from engine.decimation.kernels import claims as kclaim

    for salt in range(TRIMS):
        if won <= needed:
            break
        if salt == 0:
            h_won = _winner_histogram(c.hist, cut.most, c.listed, c.cand, c.key)
        kbin, frac_bits, _ = _quantile(h_won, needed)
        inputs = [*c.listed, c.cand, c.key, kbin, wp.int64(frac_bits), salt]
        wp.launch(kclaim.trim_winners, dim=cut.most, inputs=inputs)
        h_won = _winner_histogram(c.hist, cut.most, c.listed, c.cand, c.key)
        won = int(h_won.sum())
        if won == 0:
            best = wp.full(1, kclaim.CLAIM_FREE, dtype=wp.int64)
            wp.launch(kclaim.cheapest_trimmed, dim=cut.most, inputs=[*c.listed, c.cand, c.key, best])
            wp.launch(kclaim.restore_cheapest, dim=cut.most, inputs=[*c.listed, c.cand, c.key, best])
            won = 1
    return won


def perform(c: Collapsing, cut: Cut) -> int:
    """Collapse the winners; returns the faces removed (a sync point) and leaves dirty what they changed."""
    import warp as wp

    from engine.decimation.kernels import collapse as kcollapse

    c.dirty.zero_()
    c.removed.zero_()
    inputs = [*c.listed, c.cand, c.target_pos, c.faces, *c.inc.inputs, c.state, c.quad, c.pos, c.removed, c.dirty]
    wp.launch(kcollapse.apply_collapses, dim=cut.most, inputs=inputs)
    n_removed = int(c.removed.numpy()[0])  # sync point
    c.alive -= n_removed
    return n_removed


def compact(c: Collapsing) -> None:
    """Drop the removed faces once fewer than ``COMPACT_BELOW`` of the slots are alive (new slots: every edge is
    priced and checked again)."""
    if c.alive < len(c.faces) * COMPACT_BELOW:
        c.faces = compact_faces(c.faces, c.alive)
        c.dirty.fill_(1)


def finish(c: Collapsing, carry: bool) -> tuple[Any, Any, Any, Any]:
    """The compact result: ``(pos, faces, quad, kept)``, with the kept vertices' quadrics and input indices where
    ``carry`` (else None)."""
    faces = compact_faces(c.faces, c.alive) if c.alive < len(c.faces) else c.faces
    if carry:
        return compact_carrying(c.pos, faces, c.quad)
    out_pos, out_faces = compact_vertices(c.pos, faces)
    return out_pos, out_faces, None, None
