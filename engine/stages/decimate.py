"""Stage: topology-preserving quadric-error decimation on the device (the paper's step 3), Warp kernels in
``engine.kernels.decimate``.

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

Pricing has two phases: every changed edge gets its quadric cost (``edge_costs``), and only the edges under the
pass's cost quantile run the guards, which walk the stars (``check_candidates``); an edge refused by a guard drops
out until something it reads changes.

The result depends only on the input and the device: incidence lists are sorted, ties are broken by a hash of the
edge slot, and every floating-point sum runs in a fixed order.

``decimate_device`` works on Warp arrays (the pipeline's device-resident path); ``decimate_mesh`` takes and returns
numpy arrays with a full report, and is also the entry point of the MeshLab path (``method="meshlab"``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.stages.devmesh import (
    CLASS_NAMES,
    Incidence,
    bbox_centre,
    compact_carrying,
    compact_faces,
    compact_vertices,
    vertex_classes,
)
from engine.stages.meshcheck import boundary_kept, component_labels, edge_report, folds, signed_volume, validate_mesh

TOLERANCE = 0.05  # a closed result this far over the target is reported as limited by the guards
STOP_TOLERANCE = 0.0  # passes stop within this fraction over the target
OVERSHOOT = 4  # near the target, this many candidates per collapse still needed (the surplus winners are trimmed)
MAX_NORMAL_TURN_DEG = 60.0  # largest turn of a face normal in one collapse (a flip turns 180)
CANDIDATE_FRACTION = 0.15  # share of the collapsible edges (cheapest first) that compete in a pass (0.3: 1.33x
# MeshLab's mean distance on the shrew micro-CT at R 0.5, 0.15: 1.04x; see docs/benchmarks.md)
CLAIM_ROUNDS = 5  # claim rounds per pass (swept on the H100 phantom: 2 doubles the passes, 5 is fastest)
MAX_PASSES = 400
TRIMS = 4  # at most this many trims of a pass's surplus winners (each a hashed share of the last cost bin)
HIST_BINS = 1 << 16
COMPACT_BELOW = 0.85  # the faces array is compacted when its live share falls below this (swept: 0.5 -> 0.85, -8 %)


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


def target_faces(n_faces: int, reduction: float | None, max_triangles: int | None) -> int:
    """The face count asked for: ``reduction`` (fraction kept, in (0, 1]) or ``max_triangles`` (>= 1)."""
    if (reduction is None) == (max_triangles is None):
        raise ValueError("Give exactly one of reduction (fraction of faces kept) or max_triangles")
    if reduction is not None:
        if isinstance(reduction, bool) or not np.isfinite(reduction) or not 0 < reduction <= 1:
            raise ValueError(f"reduction is the fraction of faces kept and must be in (0, 1], got {reduction}")
        return max(round(reduction * n_faces), 1)
    if isinstance(max_triangles, bool) or int(max_triangles) != max_triangles or max_triangles < 1:
        raise ValueError(f"max_triangles must be an integer >= 1, got {max_triangles}")
    return int(max_triangles)


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

    from engine.kernels import decimate as kd

    hist.zero_()
    wp.launch(kd.winner_histogram, dim=n, inputs=[*listed, cand, key, hist])
    return hist.numpy()  # type: ignore[no-any-return]


class _Clock:
    """Per-step wall times for ``profile=True`` (synchronises the device at each tick); does nothing otherwise."""

    def __init__(self, device: Any, stats: DecimationStats | None) -> None:
        self.device, self.stats = device, stats
        if stats is not None:
            stats.profile = {}
        self.t = time.perf_counter()

    def tick(self, name: str) -> None:
        if self.stats is None or self.stats.profile is None:
            return
        import warp as wp

        wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.stats.profile[name] = self.stats.profile.get(name, 0.0) + now - self.t
        self.t = now


def vertex_quadrics(pos: Any, faces: Any, origin: Any = None) -> tuple[Incidence, Any, Any, Any]:
    """What the collapses start from, for a device mesh without removed faces: the vertices' stars, their classes
    (``devmesh.vertex_classes``), the local origin (``origin``, by default the bounding box's centre) and each
    vertex's quadric (the sum of its faces' area-weighted plane quadrics, float64, about that origin)."""
    import warp as wp

    from engine.kernels import decimate as kd

    inc = Incidence(len(pos)).build(faces, len(faces))
    state = vertex_classes(faces, inc)
    if origin is None:
        origin = bbox_centre(pos)
    quad = wp.empty(len(pos), dtype=kd.quadric, device=pos.device)
    wp.launch(kd.vertex_quadrics, dim=len(pos), inputs=[pos, faces, *inc.inputs, origin, quad], device=pos.device)
    return inc, state, origin, quad


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
    """``decimate_device`` for a piece of a larger surface (``engine.stages.tiled``): vertices flagged in
    ``locked`` (int32 per vertex, nonzero = pinned: never moved, removed or extended by a collapse), quadrics
    carried in from earlier collapses of the same surface (``quadrics`` about ``origin``; by default each vertex's
    faces' quadrics about ``origin`` or the bounding box's centre), and, with ``carry``, the kept vertices' input
    indices and quadrics carried out. Other arguments as for ``decimate_device``."""
    import warp as wp

    from engine.kernels import decimate as kd

    t0 = time.perf_counter()
    dev = pos.device
    stats = DecimationStats(input_faces=len(faces), target_faces=int(target))
    clock = _Clock(dev, stats if profile else None)
    with wp.ScopedDevice(dev):
        pos = wp.clone(pos)
        faces = wp.clone(faces)
        nv = len(pos)
        alive = len(faces)
        if quadrics is None:
            inc, state, origin, quad = vertex_quadrics(pos, faces, origin)
        else:  # carried in: the error stays measured against the surface before the earlier collapses
            inc = Incidence(nv).build(faces, len(faces))
            state = vertex_classes(faces, inc)
            origin = bbox_centre(pos) if origin is None else origin
            quad = wp.clone(quadrics)
        if locked is not None:
            wp.launch(kd.lock_vertices, dim=nv, inputs=[locked, state])
        classes = np.bincount(state.numpy(), minlength=4)  # sync point
        clock.tick("setup")
        stats.vertex_classes = {name: int(c) for name, c in zip(CLASS_NAMES, classes, strict=True)}
        cos_max = wp.float64(math.cos(math.radians(max_normal_turn_deg)))
        hist = wp.zeros(HIST_BINS, dtype=wp.int32)
        counter = wp.zeros(1, dtype=wp.int32)
        removed = wp.zeros(1, dtype=wp.int32)
        key = target_pos = cand = checked = listing = None
        n_listed = wp.zeros(1, dtype=wp.int32)
        dirty = wp.ones(nv, dtype=wp.int32)
        boost = 1  # grows while passes fall short of what is needed (candidates refused by the guards)
        stats.stopped = "target reached"
        while True:
            needed = (alive - target) // 2
            if needed <= 0 or alive <= target * (1 + stop_tolerance):
                break
            if stats.passes >= max_passes:
                stats.stopped = "pass limit"
                break
            if stats.passes:
                inc.build(faces, alive)
                clock.tick("incidence")
            slots = 3 * len(faces)
            if key is None or len(key) < slots:
                key = wp.empty(slots, dtype=wp.int32)
                target_pos = wp.empty(slots, dtype=wp.vec3)
                cand = wp.empty(slots, dtype=wp.int32)
                checked = wp.empty(slots, dtype=wp.int32)
                listing = wp.empty(slots, dtype=wp.int32)
            wp.launch(
                kd.edge_costs,
                dim=slots,
                inputs=[pos, faces, inc.count, state, quad, origin, dirty, key, target_pos, checked],
            )
            clock.tick("edge_costs")
            hist.zero_()
            wp.launch(kd.cost_histogram, dim=slots, inputs=[key, hist])
            h = hist.numpy()  # sync point: 256 KB
            clock.tick("histogram")
            n_valid = int(h.sum())
            if n_valid == 0:
                stats.stopped = "no edge may collapse (guards)"
                break
            m = max(1, min(int(candidate_fraction * n_valid), OVERSHOOT * needed * boost))
            kbin, frac_bits, most = _quantile(h, m)  # most: at least the candidates listed (the kernels below
            # run over this many)
            n_listed.zero_()
            wp.launch(kd.select_candidates, dim=slots, inputs=[key, kbin, wp.int64(frac_bits), cand, listing, n_listed])
            listed = (listing, n_listed)
            wp.launch(
                kd.check_candidates,
                dim=most,
                inputs=[
                    *listed,
                    cand,
                    pos,
                    faces,
                    *inc.inputs,
                    state,
                    quad,
                    origin,
                    cos_max,
                    kbin,
                    wp.int64(frac_bits),
                ],
                outputs=[key, target_pos, checked],
            )
            clock.tick("guards")
            claim = wp.full(len(faces), kd.CLAIM_FREE, dtype=wp.int64)
            counter.zero_()
            star = [*listed, cand, key, faces, *inc.inputs, claim]
            rounds = [  # recorded once, launched every round (packing the arguments cost more than the launch)
                wp.launch(kd.claim_stars, dim=most, inputs=star, record_cmd=True),
                wp.launch(kd.settle_claims, dim=most, inputs=[*star, counter], record_cmd=True),
                wp.launch(kd.take_stars, dim=most, inputs=[*listed, cand, faces, *inc.inputs, claim], record_cmd=True),
                wp.launch(kd.release_claims, dim=len(claim), inputs=[claim], record_cmd=True),
            ]
            for r in range(claim_rounds):  # (the last round's claims are made afresh next pass: not released)
                for cmd in rounds if r < claim_rounds - 1 else rounds[:3]:
                    cmd.launch()
            won = int(counter.numpy()[0])  # sync point
            for salt in range(TRIMS):  # keep no more than the collapses still needed, cheapest first
                if won <= needed:
                    break
                if salt == 0:
                    h_won = _winner_histogram(hist, most, listed, cand, key)
                kbin, frac_bits, _ = _quantile(h_won, needed)
                wp.launch(kd.trim_winners, dim=most, inputs=[*listed, cand, key, kbin, wp.int64(frac_bits), salt])
                h_won = _winner_histogram(hist, most, listed, cand, key)
                won = int(h_won.sum())
                if won == 0:
                    best = wp.full(1, kd.CLAIM_FREE, dtype=wp.int64)
                    wp.launch(kd.cheapest_trimmed, dim=most, inputs=[*listed, cand, key, best])
                    wp.launch(kd.restore_cheapest, dim=most, inputs=[*listed, cand, key, best])
                    won = 1
            clock.tick("claims")
            dirty.zero_()
            removed.zero_()
            wp.launch(
                kd.apply_collapses,
                dim=most,
                inputs=[*listed, cand, target_pos, faces, *inc.inputs, state, quad, pos, removed, dirty],
            )
            n_removed = int(removed.numpy()[0])  # sync point
            stats.passes += 1
            stats.collapses.append(won)
            # near the target, the candidates the guards refuse leave too few winners: offer more next pass
            boost = 1 if won >= needed else min(boost * (2 if won else 4), 1 << 20)
            alive -= n_removed
            clock.tick("apply")
            if on_pass is not None:
                on_pass(alive)
            if alive < len(faces) * COMPACT_BELOW:
                faces = compact_faces(faces, alive)
                dirty.fill_(1)  # new slots: every edge is priced and checked again
        if alive < len(faces):
            faces = compact_faces(faces, alive)
        if carry:
            out_pos, out_faces, out_quad, kept = compact_carrying(pos, faces, quad)
        else:
            (out_pos, out_faces), out_quad, kept = compact_vertices(pos, faces), None, None
        clock.tick("compact")
    stats.output_faces = len(out_faces)
    stats.seconds = time.perf_counter() - t0
    return Decimated(out_pos, out_faces, out_quad, kept, origin, stats)


# ------------------------------------------------------------------------------------------------ numpy entry point
def decimate_mesh(
    verts: npt.NDArray[Any],
    faces: npt.NDArray[Any],
    *,
    reduction: float | None = None,
    max_triangles: int | None = None,
    device: Any = "auto",
    method: str = "auto",
    workers: int | None = None,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32], dict[str, Any]]:
    """Reduce the face count by topology-preserving quadric-error edge collapses.

    Args:
        verts: (V, 3) vertices in (z, y, x) order, mm.
        faces: (F, 3) integer vertex indices, outward normals with vertices in (x, y, z) order.
        reduction: fraction of the faces to keep, in (0, 1] (0.2 keeps about 20 %).
        max_triangles: or the number of faces to reduce to (>= 1); at or above F the mesh is returned as is.
        device: Warp device (or spec) for the Warp kernels.
        method: ``"warp"`` (the Warp kernels), ``"meshlab"`` (MeshLab's collapse in CPU processes) or ``"auto"``
            (Warp: the faster on every device measured, see ``docs/benchmarks.md``).
        workers: MeshLab processes (``method="meshlab"`` only).

    Returns:
        ``(verts, faces, info)``: float32 (z, y, x) vertices, int32 faces, and ``info`` with ``method``,
        ``target_faces``, ``input_faces``, ``output_faces``, ``achieved_ratio``, ``limited_by_watertightness``
        (closed input whose result keeps more than 5 % over the target), ``closed_input``, ``closed_output``,
        ``boundary_preserved``, ``folds_before`` / ``folds_after`` (edges whose faces turn by more than 90
        degrees), ``components_before``, ``components_after``, ``volume_change`` (relative), ``seconds``, and for
        the Warp path ``passes`` and ``stopped``.

    Raises:
        ValueError: bad arrays or arguments.
    """
    from engine.stages.islands import compact_mesh

    t0 = time.perf_counter()
    verts, faces = validate_mesh(verts, faces)
    if len(faces) == 0:
        raise ValueError("Cannot decimate an empty mesh")
    if not np.isfinite(verts).all():
        raise ValueError("Vertices must be finite")
    if method not in ("auto", "warp", "meshlab"):
        raise ValueError(f"method must be auto, warp or meshlab, got {method!r}")
    target = target_faces(len(faces), reduction, max_triangles)
    verts, faces = compact_mesh(verts, faces)
    pts = verts[:, ::-1].astype(np.float64)
    before = edge_report(faces, len(pts))
    closed = before["boundary_edges"] == 0 and before["nonmanifold_edges"] == 0
    info: dict[str, Any] = {
        "target_faces": target,
        "input_faces": len(faces),
        "closed_input": bool(closed),
        "components_before": component_labels(faces, len(pts))[0],
    }
    if target >= len(faces):
        out_v, out_faces = verts, faces
        info["method"] = "none (at or under the target)"
    elif method == "meshlab":
        from engine.stages.decimate_meshlab import collapse_meshlab

        out_v, out_faces, extra = collapse_meshlab(pts, faces, target, closed, workers)
        info.update(extra)
    else:
        import warp as wp

        from engine.device import resolve_device

        dev = resolve_device(device)
        with wp.ScopedDevice(dev):
            p, f, st = decimate_device(wp.array(verts, dtype=wp.vec3), wp.array(faces, dtype=wp.vec3i), target)
            out_v, out_faces = p.numpy(), f.numpy().astype(np.int32)  # sync point
        info.update(method="warp quadric edge collapse", device=str(dev), passes=st.passes, stopped=st.stopped)
        info["vertex_classes"] = st.vertex_classes
    out_pts = out_v[:, ::-1].astype(np.float64)
    after = edge_report(out_faces, len(out_pts))
    closed_out = after["boundary_edges"] == 0 and after["nonmanifold_edges"] == 0
    vol_in = signed_volume(pts, faces)
    vol_out = signed_volume(out_pts, out_faces)
    info.update(
        output_faces=len(out_faces),
        achieved_ratio=len(out_faces) / len(faces),
        limited_by_watertightness=bool(closed and len(out_faces) > target * (1 + TOLERANCE)),
        closed_output=bool(closed_out),
        boundary_preserved=bool(before["boundary_edges"] == 0 or boundary_kept(pts, faces, out_pts)),
        folds_before=folds(pts, faces),
        folds_after=folds(out_pts, out_faces),
        components_after=component_labels(out_faces, len(out_pts))[0],
        volume_change=(vol_out - vol_in) / vol_in if vol_in else 0.0,
        seconds=time.perf_counter() - t0,
    )
    return np.ascontiguousarray(out_v, dtype=np.float32), out_faces, info
