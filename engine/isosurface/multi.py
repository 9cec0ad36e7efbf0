"""One job's streamed volume stages over several devices of a host (``stream_parts``): the volume's z range split into
contiguous parts of whole block layers, one or more per device, each streamed through the Gaussian and MC33 and its
slabs decimated in groups on its own device, in its own thread (``engine.isosurface.stream.stream_surface`` with a
``Part``); then the parts joined into one mesh on the host and finished across all the borders by the budgeted
path's finish (``engine.decimation.groups.finish_groups``, on the job's first device).

A part is pinned where it meets its neighbours exactly as a group of slabs is pinned where it meets the next: the
vertices on its top plane are kept by its last group, and those on its bottom plane (the top plane of the part
below) are computed again by the part itself, from one block layer below it (``Part.slabs``: the same cells, so the
same positions, bit for bit) and pinned in its first group. At the join they become the part below's vertices
(matched edge by edge on the shared plane), and each side's share of their quadrics is added, as between groups.

The groups' finish ("last pass" or "seams", ``GroupDecimator.mode``) is one for all the parts: the lowest part with
a surface chooses it from its first group as one device would (``ModeVote``). The mesh has the same topology as one
device's under the same per-device budget (watertight, the same components and Euler characteristic) and nearly the
same faces; it is not the same bytes, since the parts' borders are group borders that one device's groups need not
have (docs/multi-gpu.md).
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from engine.budget import Budget
from engine.decimation.groups import GroupDecimator
from engine.decimation.tiles import HostMesh
from engine.isosurface.kernel_specs import BLOCK
from engine.isosurface.stats import IsosurfaceStats
from engine.isosurface.stream import StreamResult
from engine.params import GaussianParams
from engine.staging import PinnedBuffer

__all__ = ["ModeVote", "Part", "split_layers", "stream_parts"]

_RINGS: dict[str, PinnedBuffer] = {}  # a pinned plane ring per device beyond the first (kept for the next job)
_RINGS_LOCK = threading.Lock()


VOLUME_SHARE = 0.45  # of a streamed job's time, the volume stages' (by voxels); the rest the groups' (by faces)
SAMPLE_STEP = 4  # the work estimate reads every this many rows and columns of one plane per block layer


def split_layers(work: Sequence[float] | np.ndarray, n: int) -> list[tuple[int, int]]:
    """Block layers (``work``: each one's expected work) split into ``n`` contiguous parts ``[first, end)`` of
    about equal work, each at least one layer; fewer parts where there are fewer layers."""
    n_layers = len(work)
    n = max(min(n, n_layers), 1)
    w = np.maximum(np.asarray(work, np.float64), 0.0)
    total = np.cumsum(w)
    if total[-1] <= 0:
        total = np.arange(1, n_layers + 1, dtype=np.float64)
    goals = total[-1] * np.arange(1, n) / n
    at = np.searchsorted(total, goals)  # the first layer reaching each goal: the cut after it, or before it if nearer
    before = np.where(at > 0, total[np.maximum(at - 1, 0)], 0.0)
    cuts = np.where(total[at] - goals <= goals - before, at + 1, at)
    bounds = [0]
    for i, c in enumerate(cuts):  # each part keeps at least one layer, and leaves one to each part after it
        bounds.append(int(min(max(c, bounds[-1] + 1), n_layers - (n - 1 - i))))
    bounds.append(n_layers)
    return list(itertools.pairwise(bounds))


def layer_work(volume: Any, level: float, n_layers: int) -> np.ndarray:
    """The expected work of each block layer: ``VOLUME_SHARE`` by its planes, the rest by its surface, estimated
    from the level's crossings along rows and columns of one plane per layer (every ``SAMPLE_STEP``-th row and
    column: a 64th of the voxels). Where the volume is read from disk (``engine.io.slabs.SlabSource``), by planes
    only: the estimate would read an eighth of it."""
    from engine.isosurface.kernel_specs import BLOCK

    nz = volume.shape[0]
    planes = np.array([min((b + 1) * BLOCK, nz + 1) - b * BLOCK for b in range(n_layers)], np.float64)
    if not isinstance(volume, np.ndarray) or n_layers < 2:
        return planes
    cross = np.zeros(n_layers)
    for b in range(n_layers):
        plane = volume[min(b * BLOCK + BLOCK // 2, nz - 1), ::SAMPLE_STEP, ::SAMPLE_STEP] >= level
        cross[b] = np.count_nonzero(plane[1:] != plane[:-1]) + np.count_nonzero(plane[:, 1:] != plane[:, :-1])
    if cross.sum() == 0:
        return planes
    work: np.ndarray = (
        VOLUME_SHARE * planes / planes.sum() + (1 - VOLUME_SHARE) * cross * planes / (cross * planes).sum()
    )
    return work


class ModeVote:
    """The groups' finish ("last pass" or "seams") shared by every part of a job: part ``i`` proposes one from its
    first group and waits until every part below it has proposed or finished; the lowest proposal is everyone's
    (part 0's, where it has a surface: what one device would choose from the same first group)."""

    def __init__(self, n: int) -> None:
        self.cond = threading.Condition()
        self.proposals: list[str | None] = [None] * n
        self.finished = [False] * n

    def mode(self, index: int, proposal: str) -> str:
        with self.cond:
            self.proposals[index] = proposal
            self.cond.notify_all()
            below = range(index)
            self.cond.wait_for(lambda: all(self.finished[j] or self.proposals[j] is not None for j in below))
            return next(p for p in self.proposals[: index + 1] if p is not None)

    def finish(self, index: int) -> None:
        """Part ``index`` is done (or failed): the parts above need not wait for its proposal."""
        with self.cond:
            self.finished[index] = True
            self.cond.notify_all()


class PartDecimator(GroupDecimator):
    """A ``GroupDecimator`` for one part: its groups' finish agreed with the other parts (``ModeVote``), and its
    quadric shares of the vertices it shares with the part below (their ids are placeholders, ``-1 - row``) kept
    apart for the join (``Part.foreign``)."""

    def __init__(self, part: Part, *args: Any) -> None:
        super().__init__(*args)
        self.part = part

    def flush(self) -> None:
        if not self.mode and self.pending:
            faces = self.mc33_faces + self.pending_faces
            expected = self.ratio * faces * (self.nz - 1) / max(self.pending[-1].z_top, 1)
            mine = "last pass" if expected * self.per_face <= self.mesh_room else "seams"
            self.mode = self.part.vote.mode(self.part.index, mine)
        super().flush()

    def result(self) -> tuple[HostMesh | None, tuple[Any, Any, Any] | None]:
        self.flush()
        own, foreign = [], []
        for ids, shares in self.deferred:
            below = ids < 0
            own.append((ids[~below], shares[~below]))
            foreign.append((ids[below], shares[below]))
        self.deferred = own
        if foreign:
            self.part.foreign = (np.concatenate([f[0] for f in foreign]), np.concatenate([f[1] for f in foreign]))
        return super().result()


@dataclasses.dataclass
class Part:
    """One z part of a job over several devices: its block layers ``[first, end)`` and what the join needs of it.

    Attributes:
        bottom: the vertex ids (this part's MC33 numbering, ``(2, ny + 1, nx + 1)``, -1 where none) on its bottom
            plane, computed again from the block layer below (None for the first part, or where that layer has no
            surface).
        top: the ids on its top plane (of its last slab), None where it has none.
        foreign: its share of the quadrics of the vertices on its bottom plane (placeholder ids ``-1 - row`` of
            ``bottom``'s sorted ids, and the shares).
    """

    index: int
    layers: tuple[int, int]
    n_layers: int
    vote: ModeVote
    ring: PinnedBuffer | None = None
    groups: PartDecimator | None = None
    bottom: np.ndarray | None = None
    top: np.ndarray | None = None
    foreign: tuple[np.ndarray, np.ndarray] | None = None

    def decimator(self, *args: Any) -> PartDecimator:
        """The part's ``GroupDecimator`` (``stream_surface`` makes it with the one device's arguments)."""
        self.groups = PartDecimator(self, *args)
        return self.groups

    def slabs(self, run: Callable[..., Iterator[Any]], stats: IsosurfaceStats) -> Iterator[Any]:
        """The part's slab meshes (``run``: ``engine.isosurface.slabs.run_slabs`` bound to the volume); first the
        vertices of its bottom plane, from one block layer below it (its own ids, before the part's), pinned in its
        first group as those shared with a group below are; its top plane's ids kept at the end."""
        from engine.backend.select import backend_of

        first, end = self.layers
        plane, vstart = None, 0
        if first > 0:
            for below in run(IsosurfaceStats(), layers=(first - 1, first)):
                be = backend_of(below.verts)
                plane, vstart = below.plane_above, below.nv
                self.bottom = np.asarray(be.to_host(plane)).reshape(2, -1)
                ids = np.unique(self.bottom[self.bottom >= 0]).astype(np.int64)
                assert self.groups is not None
                pos = np.asarray(be.to_host(below.verts), np.float32).reshape(-1, 3)
                self.groups.top_ids, self.groups.top_pos = ids, pos[ids]
                self.groups.top_out = -1 - np.arange(len(ids), dtype=np.int64)
        last = None
        for slab in run(stats, layers=(first, end), plane_prev=plane, vstart=vstart):
            last = slab.plane_above
            yield slab
        if last is not None and end < self.n_layers:
            self.top = np.asarray(backend_of(last).to_host(last)).reshape(2, -1)


def _ring(be: Any, first: bool) -> PinnedBuffer | None:
    """The pinned plane ring of a part on ``be``: the process's own on the job's first device, else one per device."""
    if first:
        return None
    with _RINGS_LOCK:
        return _RINGS.setdefault(be.spec, PinnedBuffer())


def stream_parts(
    volume: Any,
    level: float,
    spacing: tuple[float, float, float],
    *,
    closed: bool,
    gaussian: GaussianParams | None,
    budget: Budget,
    ratio: float | None,
    devices: Sequence[Any],
    stats: IsosurfaceStats,
) -> StreamResult:
    """The streamed volume stages and the groups' decimation of ``volume`` split over ``devices`` (backends of one
    kind, each with ``budget``; a device named twice takes two parts in turn), joined on the host: a
    ``StreamResult`` whose ``host`` mesh ``finish_groups`` finishes across ``borders``. ``stats`` gets the parts'
    sums.

    Raises:
        BudgetError, ValueError: as ``stream_surface`` (the lowest part's error where several fail).
    """
    n_layers = -(-(volume.shape[0] + 1) // BLOCK)
    layers = split_layers(layer_work(volume, level, n_layers), len(devices))
    n = len(layers)
    if budget.host_bytes is not None:  # the parts' reads share the host bound's read share
        budget = dataclasses.replace(budget, host_read_share=budget.host_read_share / n)
    vote = ModeVote(n)
    parts = [Part(i, layers[i], n_layers, vote) for i in range(n)]
    for p, be in zip(parts, devices, strict=False):
        p.ring = _ring(be, be is devices[0])
    part_stats = [IsosurfaceStats(profile=stats.profile) for _ in parts]
    results: list[StreamResult | None] = [None] * n
    errors: list[BaseException | None] = [None] * n
    seconds = [0.0] * n
    peaks: list[int | None] = [None] * n

    def run(indices: list[int], be: Any) -> None:
        import warp as wp

        from engine.device import resolve_device
        from engine.isosurface.stream import stream_surface

        # the job's memory report measures its first device; another GPU's peak is measured here, per part
        tracker = be.peak_tracker() if be is not devices[0] and not be.is_host else None
        with wp.ScopedDevice(resolve_device(be)):
            for i in indices:
                t0 = time.perf_counter()
                if tracker is not None:
                    tracker.start()
                try:
                    results[i] = stream_surface(
                        volume, level, spacing, closed=closed, gaussian=gaussian, budget=budget, ratio=ratio,
                        decimate=True, dev=be, stats=part_stats[i], zpart=parts[i],
                    )  # fmt: skip
                except BaseException as exc:  # handed to the caller, the lowest part's first
                    errors[i] = exc
                finally:
                    vote.finish(i)
                    seconds[i] = time.perf_counter() - t0
                    if tracker is not None:
                        peaks[i] = tracker.peak()
                        tracker.stop()

    by_device: dict[int, tuple[Any, list[int]]] = {}  # a device named twice runs its parts in turn, in one thread
    for i, be in enumerate(devices[:n]):
        by_device.setdefault(id(be), (be, []))[1].append(i)
    threads = [
        threading.Thread(target=run, args=(idx, be), name=f"bonemesh-part-{be.spec}", daemon=True)
        for be, idx in by_device.values()
    ]
    import warp as wp

    scope = wp.get_device()  # Warp's default device is the process's: each thread's scope sets it, this restores it
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wp.set_device(scope)
    streamed = time.perf_counter() - t0
    for exc in errors:
        if exc is not None:
            raise exc
    done = [r for r in results if r is not None]
    assert len(done) == n
    t1 = time.perf_counter()
    out = _join(parts, done, volume.shape)
    _sum_stats(stats, part_stats)
    out.info = {
        "devices": [be.spec for be in devices[:n]],
        "parts": [_part_info(*args) for args in zip(parts, done, devices, seconds, peaks, strict=False)],
        "streamed_seconds": streamed,
        "join_seconds": time.perf_counter() - t1,
        "slabs": stats.slabs,
        "groups": sum(r.info.get("groups", 0) for r in done),
        "group_mode": next((r.info.get("group_mode") for r in done if r.info.get("group_mode")), None),
        "seconds": time.perf_counter() - t0,
    }
    return out


def _part_info(part: Part, r: StreamResult, be: Any, seconds: float, peak: int | None) -> dict[str, Any]:
    """A part's line of the report: its device, block layers (the cell layers ``8 * first - 1`` ..), time, groups
    and, on a GPU other than the job's first, its peak device memory."""
    info = {"device": be.spec, "layers": list(part.layers), "seconds": seconds, "mc33_faces": r.mc33_faces}
    if peak is not None:
        info["peak_bytes"] = peak
    return info | {k: r.info.get(k) for k in ("slabs", "groups", "group_mode", "group_seconds", "feed")}


def _host_mesh(r: StreamResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A part's decimated groups on the host: positions, faces (its own numbering, placeholders below 0) and
    quadrics (``(0, 10)`` where not carried)."""
    from engine.backend.select import backend_of

    if r.host is not None:
        return r.host.pos.reshape(-1, 3), r.host.faces.reshape(-1, 3), r.host.quad.reshape(-1, 10)
    assert r.pieces is not None
    pos, faces, quad = r.pieces
    be = backend_of(pos)
    q = np.asarray(be.to_host(quad)).reshape(-1, 10) if quad is not None and len(quad) else np.zeros((0, 10))
    pos_h = np.asarray(be.to_host(pos), np.float32).reshape(-1, 3) if len(pos) else np.zeros((0, 3), np.float32)
    faces_h = np.asarray(be.to_host(faces), np.int32).reshape(-1, 3) if len(faces) else np.zeros((0, 3), np.int32)
    return pos_h, faces_h, q


def _seam_map(below: Part, part: Part, offset_below: int) -> np.ndarray:
    """The output ids (the joined numbering) of ``part``'s bottom-plane vertices, in the order of its placeholders:
    the part below's vertices on the same edges of the shared plane.

    Raises:
        RuntimeError: the two parts do not see the same vertices on the plane they share.
    """
    bottom = part.bottom
    if bottom is None:
        return np.zeros(0, np.int64)
    top = below.top if below.top is not None else np.full_like(bottom, -1)
    if not np.array_equal(bottom >= 0, top >= 0):
        raise RuntimeError(f"the parts {below.index} and {part.index} of the volume do not meet on the same vertices")
    g = below.groups
    assert g is not None and part.groups is not None
    ids = np.unique(bottom[bottom >= 0])  # the placeholders' order (Part.slabs)
    at = bottom >= 0
    rows = np.searchsorted(ids, bottom[at])
    out = np.empty(len(ids), np.int64)
    out[rows] = g.top_out[np.searchsorted(g.top_ids, top[at])] + offset_below
    return out


def _join(parts: list[Part], results: list[StreamResult], shape: tuple[int, ...]) -> StreamResult:
    """The parts' decimated groups as one host mesh: each part's vertices after the parts' below, its faces on the
    vertices it shares with the part below renumbered to that part's, and its share of their quadrics added."""
    meshes = [_host_mesh(r) for r in results]
    carried = all(len(q) == len(p) for p, _, q in meshes) and any(len(p) for p, _, _ in meshes)
    offsets = np.cumsum([0] + [len(p) for p, _, _ in meshes])
    faces_out, shares_ids, shares = [], [], []
    for i, (part, (_, faces, _)) in enumerate(zip(parts, meshes, strict=True)):
        seam = _seam_map(parts[i - 1], part, int(offsets[i - 1])) if i else np.zeros(0, np.int64)
        f = faces.astype(np.int64) + offsets[i]
        below = faces < 0
        if below.any():
            f[below] = seam[-1 - faces[below]]
        faces_out.append(f)
        if part.foreign is not None and len(part.foreign[0]):
            shares_ids.append(seam[-1 - part.foreign[0]])
            shares.append(part.foreign[1])
    pos = np.concatenate([p for p, _, _ in meshes]) if meshes else np.zeros((0, 3), np.float32)
    faces_all = np.concatenate(faces_out).astype(np.int32) if faces_out else np.zeros((0, 3), np.int32)
    quad = np.concatenate([q for _, _, q in meshes]) if carried else np.zeros((0, 10))
    if carried and shares_ids:
        np.add.at(quad, np.concatenate(shares_ids), np.concatenate(shares))
    origin = results[0].origin
    out = StreamResult(origin=origin)
    out.mc33_faces = sum(r.mc33_faces for r in results)
    out.mc33_vertices = sum(r.mc33_vertices for r in results)
    out.borders = sorted(b for r in results for b in r.borders)
    if len(faces_all):
        out.host = HostMesh(pos, faces_all, quad, origin)
    return out


def _sum_stats(stats: IsosurfaceStats, parts: list[IsosurfaceStats]) -> None:
    """The parts' isosurface stats added into ``stats`` (the level is in range where both signs were seen in any
    part: a part wholly inside or outside the bone is no sign of a level out of range)."""
    for s in parts:
        stats.slabs += s.slabs
        stats.blocks += s.blocks
        stats.active_blocks += s.active_blocks
        stats.table_misses += s.table_misses
        stats.retries += s.retries
        stats.slab_layers += s.slab_layers
        stats.peak_slab_bytes = max(stats.peak_slab_bytes, s.peak_slab_bytes)
        for name, t in s.timings.items():
            stats.timings[name] = stats.timings.get(name, 0.0) + t
    stats.level_in_range = any(s.level_in_range for s in parts)
