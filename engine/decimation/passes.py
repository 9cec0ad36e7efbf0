"""Topology-preserving quadric-error decimation on the device (the paper's step 3): the pass loop, Warp kernels in
``engine.decimation.kernels`` (by concern: quadrics, costs, guards, claims, collapse).

Garland-Heckbert edge collapses, many per pass: every pass prices every edge, lets the edges under a cost quantile
compete for vertex-disjoint neighbourhoods (atomic claims of ``(cost, hashed id)`` keys), collapses the winners and
repeats until the face count reaches the target. The guards are those of MeshLab's ``preservetopology``,
``preserveboundary`` and ``preservenormal``:

* link condition (the ends of an edge share exactly the two vertices opposite it), and no opposite vertex left
  with fewer than three faces: a watertight 2-manifold input stays watertight and 2-manifold with the same
  components and Euler characteristic, and no closed piece falls below a tetrahedron;
* open borders keep every vertex, unmoved (a free vertex may collapse onto a border vertex); non-manifold or
  inconsistently wound neighbourhoods are never touched;
* no face turns by more than ``max_normal_turn_deg`` (so none flips or folds) and none becomes degenerate.

A pass runs the named phases of ``engine.decimation.phases`` (update adjacency, price, rank, guard, claim, trim,
perform, compact). Pricing has two of them: every changed edge gets its quadric cost (``price``), and only the edges
under the pass's cost quantile run the guards, which walk the stars (``guard``); an edge refused by a guard drops
out until something it reads changes.

The result depends only on the input and the device: incidence lists are sorted, ties are broken by a hash of the
edge slot, and every floating-point sum runs in a fixed order.

``decimate_device`` works on device arrays of any backend (the pipeline's device-resident path: Warp or OpenCL, the
backend found from the arrays); ``engine.decimation.arrays``' ``decimate_mesh`` takes and returns numpy arrays with
a full report, and is also the entry point of the MeshLab path (``method="meshlab"``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from engine.backend.select import backend_of
from engine.decimation import phases

TOLERANCE = 0.05  # a closed result this far over the target is reported as limited by the guards
STOP_TOLERANCE = 0.0  # passes stop within this fraction over the target
MAX_NORMAL_TURN_DEG = 60.0  # largest turn of a face normal in one collapse (a flip turns 180)
CANDIDATE_FRACTION = 0.15  # share of the collapsible edges (cheapest first) that compete in a pass (0.3: 1.33x
# MeshLab's mean distance on the shrew micro-CT at R 0.5, 0.15: 1.04x; see docs/benchmarks.md)
CLAIM_ROUNDS = 5  # claim rounds per pass (swept on the H100 phantom: 2 doubles the passes, 5 is fastest)
MAX_PASSES = 400
# a decimation whose last STALL_PASSES passes removed less than STALL_SHARE of the faces still to go has stalled: the
# guards refuse nearly every collapse left (a group of slabs pinned on both borders: 99 % of its collapses within 80-150
# passes, the last 250 of its 400 passes winning 16-48 collapses in all)
STALL_PASSES = 16
STALL_SHARE = 0.01


@dataclass
class DecimationStats:
    """What a device decimation did: passes, collapses per pass, why it stopped."""

    input_faces: int = 0
    target_faces: int = 0
    output_faces: int = 0
    passes: int = 0
    collapses: list[int] = field(default_factory=list)
    vertex_classes: dict[str, int] = field(default_factory=dict)
    stopped: str = ""
    seconds: float = 0.0
    profile: dict[str, float] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "input_faces": self.input_faces,
            "target_faces": self.target_faces,
            "output_faces": self.output_faces,
            "passes": self.passes,
            "collapses_per_pass": self.collapses,
            "vertex_classes": self.vertex_classes,
            "stopped": self.stopped,
            "seconds": self.seconds,
            **({"profile_seconds": self.profile} if self.profile is not None else {}),
        }


class _Clock:
    """Per-step wall times for ``profile=True`` (synchronises the device at each tick); does nothing otherwise."""

    def __init__(self, be: Any, stats: DecimationStats | None) -> None:
        self.be, self.stats = be, stats
        if stats is not None:
            stats.profile = {}
        self.t = time.perf_counter()

    def tick(self, name: str) -> None:
        if self.stats is None or self.stats.profile is None:
            return
        self.be.synchronize()
        now = time.perf_counter()
        self.stats.profile[name] = self.stats.profile.get(name, 0.0) + now - self.t
        self.t = now


@dataclass
class Decimated:
    """A decimation's result with what a later decimation of the same surface continues from: the compact mesh,
    each kept vertex's index in the input (``kept``) and its accumulated quadric (about ``origin``)."""

    pos: Any
    faces: Any
    quad: Any
    kept: Any
    origin: Any
    stats: DecimationStats


def _stalled(collapses: list[int], to_go: int) -> bool:
    """Whether the last ``STALL_PASSES`` passes (``collapses`` per pass, two faces each) removed less than
    ``STALL_SHARE`` of the ``to_go`` faces over the target."""
    return len(collapses) >= STALL_PASSES and 2 * sum(collapses[-STALL_PASSES:]) < STALL_SHARE * to_go


def decimate_device(pos: Any, faces: Any, target: int, **options: Any) -> tuple[Any, Any, DecimationStats]:
    """Decimate a device mesh to about ``target`` faces (never fewer).

    Args:
        pos: ``wp.array(dtype=wp.vec3)`` (z, y, x) mm; not modified.
        faces: ``wp.array(dtype=wp.vec3i)``; not modified.
        target: faces to reach; passes stop within ``stop_tolerance`` above it, or when no edge may collapse.
        options: as for ``decimate_carrying``: ``max_normal_turn_deg`` (the largest turn of a face's normal in one
            collapse), ``candidate_fraction`` (share of the collapsible edges, cheapest first, that compete in one
            pass), ``claim_rounds``, ``stop_tolerance``, ``max_passes`` (``stats.stopped`` says when it stopped
            there), ``on_pass`` (called as ``on_pass(faces_now)`` after each pass), ``profile`` (synchronise after
            each step and add its time to ``stats.profile``; for benchmarks).

    Returns:
        ``(pos, faces, stats)``: new compact device arrays (unused vertices dropped, order kept) and the stats.
    """
    out = decimate_carrying(pos, faces, target, carry=False, **options)
    return out.pos, out.faces, out.stats


def decimate_carrying(
    pos: Any,
    faces: Any,
    target: int,
    *,
    locked: Any = None,
    quadrics: Any = None,
    origin: Any = None,
    max_normal_turn_deg: float = MAX_NORMAL_TURN_DEG,
    candidate_fraction: float = CANDIDATE_FRACTION,
    claim_rounds: int = CLAIM_ROUNDS,
    stop_tolerance: float = STOP_TOLERANCE,
    max_passes: int = MAX_PASSES,
    on_pass: Any = None,
    profile: bool = False,
    carry: bool = True,
) -> Decimated:
    """``decimate_device`` for a piece of a larger surface (``engine.decimation.tiles``): vertices flagged in
    ``locked`` (int32 per vertex, nonzero = pinned: never moved, removed or extended by a collapse), quadrics
    carried in from earlier collapses of the same surface (``quadrics`` about ``origin``; by default each vertex's
    faces' quadrics about ``origin`` or the bounding box's centre), and, with ``carry``, the kept vertices' input
    indices and quadrics carried out. Other arguments as for ``decimate_device``."""
    t0 = time.perf_counter()
    stats = DecimationStats(input_faces=len(faces), target_faces=int(target))
    clock = _Clock(backend_of(pos), stats if profile else None)
    c, stats.vertex_classes = phases.start(
        pos, faces, locked=locked, quadrics=quadrics, origin=origin, max_normal_turn_deg=max_normal_turn_deg
    )
    clock.tick("setup")
    stats.stopped = "target reached"
    while True:
        needed = (c.alive - target) // 2
        if needed <= 0 or c.alive <= target * (1 + stop_tolerance):
            break
        if stats.passes >= max_passes:
            stats.stopped = "pass limit"
            break
        if _stalled(stats.collapses, c.alive - target):
            stats.stopped = f"stalled: its last {STALL_PASSES} passes took under {STALL_SHARE:.0%} of the faces to go"
            break
        if stats.passes:
            phases.update_adjacency(c)
            clock.tick("incidence")
        phases.price(c)
        clock.tick("edge_costs")
        cut = phases.rank(c, needed, candidate_fraction)
        clock.tick("histogram")
        if cut is None:
            stats.stopped = "no edge may collapse (guards)"
            break
        phases.guard(c, cut)
        clock.tick("guards")
        won = phases.trim(c, cut, needed, phases.claim(c, cut, claim_rounds))
        clock.tick("claims")
        phases.perform(c, cut)
        stats.passes += 1
        stats.collapses.append(won)
        # near the target, the candidates the guards refuse leave too few winners: offer more next pass
        c.boost = 1 if won >= needed else min(c.boost * (2 if won else 4), 1 << 20)
        clock.tick("apply")
        if on_pass is not None:
            on_pass(c.alive)
        phases.compact(c)
    out_pos, out_faces, out_quad, kept = phases.finish(c, carry)
    clock.tick("compact")
    stats.output_faces = len(out_faces)
    stats.seconds = time.perf_counter() - t0
    return Decimated(out_pos, out_faces, out_quad, kept, c.origin, stats)
