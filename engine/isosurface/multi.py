"""One job's streamed volume stages over several devices of a host (``stream_parts``): the volume's z range split into
contiguous parts of whole block layers, one or more per device, each streamed through the Gaussian and MC33 and its
slabs decimated in groups on its own device, in its own thread (``engine.isosurface.stream.stream_surface`` with a
``Part``); then the parts joined into one mesh (on the job's first device where the finish would work on it there,
else on the host, from where the finish takes it up as it does one device's spilled groups) and finished across all
the borders by the budgeted path's finish (``engine.decimation.groups.finish_groups``, on the job's first device).

A part is pinned where it meets its neighbours exactly as a group of slabs is pinned where it meets the next: the
vertices on its top plane are kept by its last group, and those on its bottom plane (the top plane of the part
below) are computed again by the part itself, from one block layer below it (``Part.slabs``: the same cells, so the
same positions, bit for bit), numbered first in its output and pinned in its first group. At the join they become
the part below's vertices (matched edge by edge on the shared plane), and each side's share of their quadrics is
added, as between groups.

The groups' finish ("last pass" or "seams", ``GroupDecimator.mode``) is one for all the parts: the lowest part with
a surface chooses it from its first group as one device would (``ModeVote``). The mesh has the same topology as one
device's under the same per-device budget (watertight, the same components and Euler characteristic) and nearly the
same faces; it is not the same bytes, since the parts' borders are group borders that one device's groups need not
have (docs/multi-gpu.md).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
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
SAMPLE_STEP = 8  # the work estimate reads every this many rows and columns of one plane per block layer,
WORK_RUN = 16  # this many layers at a time, in up to this many threads (every 4th row and column in one thread
WORK_THREADS = 8  # took 0.13 s for the 8 G voxels on the host of two H200s, before any part could start)


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
    column: the rows read are a 64th of the volume's bytes). Where the volume is read from disk
    (``engine.io.slabs.SlabSource``), by planes only: the estimate would read an eighth of it."""
    from engine.isosurface.kernel_specs import BLOCK

    nz = volume.shape[0]
    planes = np.array([min((b + 1) * BLOCK, nz + 1) - b * BLOCK for b in range(n_layers)], np.float64)
    if not isinstance(volume, np.ndarray) or n_layers < 2:
        return planes
    cross = np.zeros(n_layers)

    def count(first: int) -> None:  # a run of layers (NumPy's comparisons and counts release the GIL)
        for b in range(first, min(first + WORK_RUN, n_layers)):
            plane = volume[min(b * BLOCK + BLOCK // 2, nz - 1), ::SAMPLE_STEP, ::SAMPLE_STEP] >= level
            cross[b] = np.count_nonzero(plane[1:] != plane[:-1]) + np.count_nonzero(plane[:, 1:] != plane[:, :-1])

    runs = range(0, n_layers, WORK_RUN)
    with ThreadPoolExecutor(max(1, min(WORK_THREADS, os.cpu_count() or 1, len(runs)))) as pool:
        list(pool.map(count, runs))
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
    output numbered after the vertices it shares with the part below (``Part.seam``: rows ``0 .. nf``, copies of the
    part below's, pinned; the part's share of their quadrics is added to them as between groups), so that the join
    maps rows below ``nf`` to the part below's and moves the rest (``GLOBALIZE_FACES``)."""

    def __init__(self, part: Part, *args: Any) -> None:
        super().__init__(*args)
        self.part = part
        self.seeded = False

    def flush(self) -> None:
        if not self.mode and self.pending:
            mine = self.first_group_mode(self.mc33_faces + self.pending_faces, self.pending[-1].z_top)
            self.mode = self.part.vote.mode(self.part.index, mine)
        if self.pending:
            self.seed()
        super().flush()

    def seed(self) -> None:
        """The shared vertices below as the output's first rows (a piece without faces; zero quadrics where the
        groups carry theirs), once, when the groups' finish is known."""
        if self.seeded or self.part.seam is None:
            return
        from engine.backend.base import VEC3F, VEC3I, VEC10D
        from engine.backend.select import get_backend

        self.seeded = True
        be = get_backend(self.dev)
        nf = len(self.part.seam)
        quad = be.zeros(nf, VEC10D) if self.carries_quadrics else None
        self.pieces.insert(0, (be.from_host(self.part.seam, VEC3F), be.empty(0, VEC3I), quad))
        self.held += nf * (12 + (80 if quad is not None else 0))

    def result(self) -> tuple[HostMesh | None, tuple[Any, Any, Any] | None]:
        self.flush()
        self.seed()
        return super().result()


@dataclasses.dataclass
class Part:
    """One z part of a job over several devices: its block layers ``[first, end)`` and what the join needs of it.

    Attributes:
        bottom: the vertex ids (this part's MC33 numbering, ``(2, ny + 1, nx + 1)``, -1 where none) on its bottom
            plane, computed again from the block layer below (None for the first part, or where that layer has no
            surface).
        seam: the positions of those vertices (in the order of their ids): the first rows of the part's output.
        top: the ids on its top plane (of its last slab), None where it has none.
    """

    index: int
    layers: tuple[int, int]
    n_layers: int
    vote: ModeVote
    ring: PinnedBuffer | None = None
    groups: PartDecimator | None = None
    bottom: np.ndarray | None = None
    seam: np.ndarray | None = None
    top: np.ndarray | None = None

    @property
    def nf(self) -> int:
        """Rows of the part's output that are the part below's vertices."""
        return 0 if self.seam is None else len(self.seam)

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
                if len(ids):
                    pos = np.asarray(be.to_host(below.verts), np.float32).reshape(-1, 3)
                    self.seam = np.ascontiguousarray(pos[ids])
                    g = self.groups
                    assert g is not None
                    g.top_ids, g.top_pos, g.top_out, g.n_out = ids, self.seam, np.arange(len(ids)), len(ids)
                del below  # its mesh: only the plane's ids stay on the device
        last = None
        for slab in run(stats, layers=(first, end), plane_prev=plane, vstart=vstart):
            last = slab.plane_above
            yield slab
        if last is not None and end < self.n_layers:
            self.top = np.asarray(backend_of(last).to_host(last)).reshape(2, -1)


class _OneReader:
    """A scan read slab by slab (``engine.io.slabs.SlabSource``) shared by the parts' threads: one read at a time (a
    source is read from one thread elsewhere: a TIFF's file handle, a Zarr's row of chunks kept for the next read),
    everything else as the source's."""

    def __init__(self, source: Any) -> None:
        self.source = source
        self.lock = threading.Lock()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.source, name)

    def read(self, z0: int, z1: int) -> np.ndarray:
        with self.lock:
            planes: np.ndarray = self.source.read(z0, z1)
            return planes

    def read_into(self, z0: int, z1: int, out: np.ndarray) -> None:
        with self.lock:
            self.source.read_into(z0, z1, out)


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
    kind, each with ``budget``; a device named twice takes two parts in turn), joined: a ``StreamResult`` whose
    ``pieces`` (on the first device) or ``host`` mesh ``finish_groups`` finishes across ``borders``. ``stats`` gets
    the parts' sums.

    Raises:
        BudgetError, ValueError: as ``stream_surface`` (the lowest part's error where several fail).
    """
    t_split = time.perf_counter()
    n_layers = -(-(volume.shape[0] + 1) // BLOCK)
    layers = split_layers(layer_work(volume, level, n_layers), len(devices))
    if not isinstance(volume, np.ndarray):  # a scan read slab by slab: the parts take turns to read it
        volume = _OneReader(volume)
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
        from engine.device import resolve_device
        from engine.isosurface.stream import stream_surface

        # the job's memory report measures its first device; another GPU's peak is measured here, per part
        tracker = be.peak_tracker() if be is not devices[0] and not be.is_host else None
        # the device's CUDA context made current on this thread only (CUDA's current context is per thread); not
        # wp.ScopedDevice, which sets Warp's default device for the whole process: the parts' threads would race on
        # it. Every call of the stages names its device (tests/engine/job/test_multi_device.py checks it)
        with resolve_device(be).context_guard:
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
    t0 = time.perf_counter()
    split = t0 - t_split  # the work estimate, the split and the parts' rings
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    streamed = time.perf_counter() - t0
    for exc in errors:
        if exc is not None:
            raise exc
    done = [r for r in results if r is not None]
    assert len(done) == n
    t1 = time.perf_counter()
    out = _join(parts, done, devices[0], budget)
    _sum_stats(stats, part_stats)
    out.info = {
        "devices": [be.spec for be in devices[:n]],
        "parts": [_part_info(*args) for args in zip(parts, done, devices, seconds, peaks, strict=False)],
        "split_seconds": split,
        "streamed_seconds": streamed,
        "join_seconds": time.perf_counter() - t1,
        "joined_on": "device" if out.pieces is not None else "host",
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


def _seam_map(below: Part, part: Part, offset_below: int) -> np.ndarray:
    """The joined mesh's ids of ``part``'s first rows (its bottom plane's vertices, ``Part.seam``): the part below's
    vertices on the same edges of the plane they share (``offset_below``: where the part below's own rows start).

    Raises:
        RuntimeError: the two parts do not see the same vertices on the plane they share.
    """
    bottom = part.bottom
    if part.nf == 0 or bottom is None:
        return np.zeros(0, np.int64)
    top = below.top if below.top is not None else np.full_like(bottom, -1)
    if not np.array_equal(bottom >= 0, top >= 0):
        raise RuntimeError(f"the parts {below.index} and {part.index} of the volume do not meet on the same vertices")
    g = below.groups
    assert g is not None
    at = bottom >= 0
    rows = np.searchsorted(np.unique(bottom[at]), bottom[at])  # the order of the seam's rows (Part.slabs)
    out = np.empty(part.nf, np.int64)
    out[rows] = g.top_out[np.searchsorted(g.top_ids, top[at])] - below.nf + offset_below
    return out


def _join(parts: list[Part], results: list[StreamResult], be: Any, budget: Budget) -> StreamResult:
    """The parts' decimated groups as one mesh: each part's own rows after the parts' below, its faces on its first
    rows (the part below's vertices) renumbered to the part below's, and its share of their quadrics added.

    On the job's first device ``be`` where every part's groups are still on their devices and the joined mesh is
    one the finish would work on there (``_on_device``); else on the host, from where the finish takes it up again
    where it can (``finish_groups``), as it does one device's groups spilled to the host."""
    out = StreamResult(origin=results[0].origin)
    out.mc33_faces = sum(r.mc33_faces for r in results)
    out.mc33_vertices = sum(r.mc33_vertices for r in results)
    out.borders = sorted(b for r in results for b in r.borders)
    pieces = [r.pieces for r in results if r.pieces is not None]
    if len(pieces) == len(results):
        carried = {p[2] is not None for p in pieces if len(p[0])}  # the parts carry quadrics, or none does
        n_verts = sum(len(p[0]) - part.nf for p, part in zip(pieces, parts, strict=True))
        n_faces = sum(len(p[1]) for p in pieces)
        carry = carried == {True} and budget.last_pass_fits(n_faces)  # the quadrics only for one last pass
        first = sum(_nbytes(x) for x in pieces[0] if x is not None) if results[0].pieces is not None else 0
        if len(carried) <= 1 and _on_device(n_verts, n_faces, carry, bool(out.borders), budget.beside(first)):
            out.pieces = _join_on_device(parts, results, be, carry)
            return out
    out.host = _join_on_host(parts, results, out.origin)
    return out


def _nbytes(arr: Any) -> int:
    from engine.backend.select import backend_of

    return int(backend_of(arr).nbytes(arr)) if len(arr) else 0


def _on_device(n_verts: int, n_faces: int, carry: bool, borders: bool, room: Budget) -> bool:
    """Whether the joined mesh is made on the first device: it fits ``room`` (beside the first part's groups, which
    it is copied from) and the finish would work on it there (one last pass, or a seam pass beside it)."""
    from engine.decimation.seams import seams_fit_beside

    if not room.fits(n_verts * (12 + 80 * carry) + n_faces * 12):
        return False
    return room.last_pass_fits(n_faces) or (borders and seams_fit_beside(n_verts, n_faces, room))


def _offsets(parts: list[Part], n_rows: list[int]) -> list[int]:
    """Where each part's own rows (after its ``nf`` first) start in the joined mesh."""
    own = [n - p.nf for p, n in zip(parts, n_rows, strict=True)]
    return [int(x) for x in np.cumsum([0, *own[:-1]])]


def _join_on_host(parts: list[Part], results: list[StreamResult], origin: np.ndarray) -> HostMesh | None:
    meshes = [_host_mesh(r) for r in results]
    offsets = _offsets(parts, [len(m[0]) for m in meshes])
    carried = all(len(q) == len(pos) for pos, _, q in meshes) and any(len(pos) for pos, _, _ in meshes)
    pos_out, faces_out, quad_out, share_ids, shares = [], [], [], [], []
    for i, (part, (pos, faces, quad)) in enumerate(zip(parts, meshes, strict=True)):
        nf = part.nf
        seam = _seam_map(parts[i - 1], part, offsets[i - 1]) if i and nf else np.zeros(0, np.int64)
        f = faces.astype(np.int64)
        below = f < nf
        f[~below] += offsets[i] - nf
        f[below] = seam[f[below]]
        faces_out.append(f)
        pos_out.append(pos[nf:])
        if carried:
            quad_out.append(quad[nf:])
            share_ids.append(seam)
            shares.append(quad[:nf])
    faces_all = np.concatenate(faces_out).astype(np.int32)
    if not len(faces_all):
        return None
    quad_all = np.concatenate(quad_out) if carried else np.zeros((0, 10))
    if carried:
        np.add.at(quad_all, np.concatenate(share_ids), np.concatenate(shares))
    return HostMesh(np.concatenate(pos_out), faces_all, quad_all, origin)


def _host_mesh(r: StreamResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A part's decimated groups on the host: positions, faces (the part's numbering) and quadrics (``(0, 10)``
    where not carried)."""
    from engine.backend.select import backend_of

    if r.host is not None:
        return r.host.pos.reshape(-1, 3), r.host.faces.reshape(-1, 3), r.host.quad.reshape(-1, 10)
    if r.pieces is None:  # a part without a surface
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 10))
    pos, faces, quad = r.pieces
    be = backend_of(pos)

    def host(arr: Any, cols: int, dtype: Any) -> np.ndarray:
        return np.asarray(be.to_host(arr), dtype).reshape(-1, cols) if len(arr) else np.zeros((0, cols), dtype)

    q = host(quad, 10, np.float64) if quad is not None else np.zeros((0, 10))
    return host(pos, 3, np.float32), host(faces, 3, np.int32), q


def _join_on_device(parts: list[Part], results: list[StreamResult], be: Any, carry: bool) -> tuple[Any, Any, Any]:
    """``_join_on_host``'s mesh made on ``be`` from the parts' groups on their devices (copied device to device
    where the devices allow: Warp's, any CUDA devices; through the host between OpenCL devices), with the quadrics
    where ``carry``."""
    from engine.backend.base import VEC3F, VEC3I, VEC10D
    from engine.backend.select import backend_of
    from engine.decimation import kernel_specs as K

    pieces: list[tuple[Any, Any, Any]] = []
    for r in results:
        assert r.pieces is not None
        pieces.append(r.pieces)
    offsets = _offsets(parts, [len(p[0]) for p in pieces])
    carried = carry and any(p[2] is not None for p in pieces if len(p[0]) > 0)
    n_rows = int(sum(len(p[0]) - part.nf for p, part in zip(pieces, parts, strict=True)))
    pos = be.empty(max(n_rows, 1), VEC3F)
    faces = be.empty(max(int(sum(len(p[1]) for p in pieces)), 1), VEC3I)
    quad = be.zeros(max(n_rows, 1), VEC10D) if carried else None
    seams: list[np.ndarray] = []
    of = 0
    for i, (part, piece) in enumerate(zip(parts, pieces, strict=True)):
        p, f, q = piece
        src = backend_of(p)
        nf = part.nf
        seam = _seam_map(parts[i - 1], part, offsets[i - 1]) if i and nf else np.zeros(0, np.int64)
        seams.append(seam)
        if len(f):  # the faces renumbered where they are, then copied
            table = src.from_host(seam.astype(np.int32) if nf else np.zeros(1, np.int32))
            src.launch(K.GLOBALIZE_FACES, len(f), [f, int(nf), table, int(offsets[i] - nf)])
            _copy(be, faces, of, src, f, 0, len(f))
            of += len(f)
        if len(p) > nf:
            _copy(be, pos, offsets[i], src, p, nf, len(p) - nf)
            if quad is not None:
                _copy(be, quad, offsets[i], src, q, nf, len(p) - nf)
    if quad is not None:
        for part, piece, seam in zip(parts, pieces, seams, strict=True):
            if part.nf:  # each side's share of the vertices the parts share
                src = backend_of(piece[2])
                share = np.asarray(src.to_host(piece[2], part.nf)).reshape(-1, 10)
                add = [be.from_host(seam.astype(np.int32)), be.from_host(share, VEC10D), quad]
                be.launch(K.ADD_QUADRICS, part.nf, add)
    for r in results:
        r.pieces = None
    n_faces = of
    return be.view(pos, 0, n_rows), be.view(faces, 0, n_faces), None if quad is None else be.view(quad, 0, n_rows)


def _copy(be: Any, dst: Any, dst_offset: int, src_be: Any, src: Any, src_offset: int, count: int) -> None:
    """``count`` rows of ``src`` (on ``src_be``) from ``src_offset`` into ``dst`` (on ``be``) at ``dst_offset``:
    device to device where both are Warp's (CUDA devices copy peer to peer), else through the host."""
    if src_be is be or (src_be.kind == "warp" and be.kind == "warp"):
        be.copy(dst, src, dst_offset=dst_offset, src_offset=src_offset, count=count)
        return
    rows = np.asarray(src_be.to_host(src_be.view(src, src_offset, src_offset + count)))
    be.upload(dst, rows, dst_offset=dst_offset)


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
