"""Warp kernels of a decimation pass's claims (host side: ``engine.decimation.phases``).

Each competing edge does an atomic min of its key ``(cost code << 32) | mix32(edge slot)`` onto every face of its
two stars and wins only where it holds all of them (a few rounds; winners take their faces for the rest of the
pass). Winners' stars are face-disjoint, so their collapses and guards are independent. A pass with more winners
than collapses left to do trims the surplus, cheapest kept.
"""

from __future__ import annotations

import warp as wp

from engine.decimation.kernels.costs import HIST_SHIFT, edge_ends, listed, mix32

CLAIM_FREE = wp.constant(wp.int64(0x7FFFFFFFFFFFFFFF))
CLAIM_TAKEN = wp.constant(wp.int64(-1))
TRIMMED = wp.constant(5)  # ``cand`` of a winner trimmed off (the pass has more winners than collapses left to do)


@wp.func
def priority(code: int, h: int) -> wp.int64:
    """An edge's claim priority, lower wins: its cost code, ties broken by the hashed slot."""
    return (wp.int64(code) << wp.int64(32)) | mix32(h)


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
