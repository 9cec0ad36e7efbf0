"""Stage: the volume stages within a device memory budget, and the first decimation round slab by slab.

``stream_surface`` runs the Gaussian and MC33 over z slabs of the host volume (each slab uploaded with a one-plane
halo, smoothed, and handed to MC33, so the field is the whole-volume Gaussian's, bit for bit), and keeps the slabs'
meshes on the device. When the mesh built so far and its decimation would no longer fit the budget, the slabs
gathered so far are decimated as one group (``GroupDecimator``) with the vertices they share with the slabs below
and above pinned, so the pieces still join into one watertight surface; the decimated group goes to the host with
its quadrics, and the next group starts. If no group had to go, the whole MC33 mesh is still on the device and the
pipeline goes on as without a budget; otherwise the decimated groups are finished across their borders by
``engine.stages.tiled``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.memory import DECIMATE_BYTES_PER_FACE, MESH_BYTES_PER_FACE, SLAB_SHARE, STREAM_SLAB_SHARE, mib
from engine.params import GaussianParams

PIECE_TOLERANCE = 0.01  # a group or tile stops this close to its share (the last pass across them is exact)
GROUP_SLACK = 1.15  # groups of slabs keep this many times their share of the target
SEAM_SLACK = 1.03  # or this many, when only the faces near their borders get a last pass (the seams)
SPILL_SHARE = 0.25  # of the budget: decimated groups held on the device beyond this go to the host
GROUP_SLABS = 4  # slabs are sized for this share of a group's faces (a group then fills at least 3/4 of its cap)


@dataclass
class HostMesh:
    """A mesh being decimated piece by piece, on the host: float32 (z, y, x) positions, int32 faces, and each
    vertex's accumulated quadric (float64, 10 coefficients, about ``origin``)."""

    pos: np.ndarray
    faces: np.ndarray
    quad: np.ndarray
    origin: np.ndarray


@dataclass
class StreamResult:
    """``device`` (pos, faces) when the whole MC33 mesh fitted, else the decimated groups (``pieces`` on the device
    or ``host``)."""

    @property
    def grouped(self) -> bool:
        return self.pieces is not None or self.host is not None

    device: tuple[Any, Any] | None = None
    pieces: tuple[Any, Any, Any] | None = None  # decimated groups on the device: pos, faces, quadrics
    host: HostMesh | None = None  # or on the host
    mc33_faces: int = 0
    mc33_vertices: int = 0
    origin: Any = None  # the quadrics' origin (z, y, x) mm
    borders: list[float] = field(default_factory=list)  # z (mm) where the groups meet
    info: dict[str, Any] = field(default_factory=dict)


def plane_bytes(volume: np.ndarray, gaussian: GaussianParams | None) -> int:
    """Device bytes of one z plane in a slab: the samples, and the Gaussian's two float32 planes where it runs."""
    return volume.shape[1] * volume.shape[2] * (volume.itemsize + (8 if gaussian is not None else 0))


def slab_getter(volume: np.ndarray, gaussian: GaussianParams | None, upload: Any) -> tuple[Any, int, int]:
    """``(get_slab, plane_bytes, halo_planes)`` for ``_run_slabs``: planes zlo..zhi uploaded by ``upload(lo, hi)``
    (``engine.staging.plane_feed``) and smoothed, with a plane of halo on each side so the result equals the whole
    volume's Gaussian."""
    from engine.stages.gaussian import smooth_volume

    nz = volume.shape[0]
    if gaussian is None:
        return upload, plane_bytes(volume, gaussian), 0

    def smoothed(zlo: int, zhi: int) -> Any:
        lo, hi = max(zlo - 1, 0), min(zhi + 1, nz - 1)
        field_ = smooth_volume(upload(lo, hi), gaussian)
        return field_[zlo - lo : zhi - lo + 1]

    return smoothed, plane_bytes(volume, gaussian), 2


class GroupDecimator:
    """Collects slab meshes and decimates them in groups whose decimation fits the budget.

    The decimated groups stay on the device, numbered as one mesh (``pieces``), until they hold ``spill_bytes``;
    then they go to the host (``host``). The vertices a group shares with the group below keep that group's ids;
    each side's share of their quadrics is added at the end (``deferred``).
    """

    def __init__(
        self, ratio: float, slack: float, mesh_room: int, spill_bytes: int, origin: np.ndarray, nz: int, dev: Any
    ) -> None:
        self.ratio, self.slack, self.mesh_room, self.spill_bytes = ratio, slack, mesh_room, spill_bytes
        self.origin, self.nz, self.dev = origin, nz, dev
        self.mode = ""  # "last pass" (groups keep ``slack`` more) or "seams" (groups go to the ratio)
        self.borders: list[float] = []  # z (mm) where groups meet
        self.mc33_faces = 0
        self.pending: list[Any] = []
        self.pending_faces = 0
        self.pieces: list[tuple[Any, Any, Any]] = []  # device (pos, faces in output ids, quad)
        self.host: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.held = 0  # bytes of ``pieces``
        self.deferred: list[tuple[np.ndarray, np.ndarray]] = []  # (output ids, quadric shares) of shared vertices
        self.n_out = 0
        self.top_ids = np.zeros(0, np.int64)  # MC33 ids of the last group's pinned top vertices, sorted
        self.top_out = np.zeros(0, np.int64)  # their output ids
        self.top_pos = np.zeros((0, 3), np.float32)  # and positions
        self.groups: list[dict[str, Any]] = []
        self.seconds = 0.0
        self.timings = {"prepare": 0.0, "decimate": 0.0, "number": 0.0, "spill": 0.0}

    @property
    def cap(self) -> int:
        """Faces a group may have now (its decimation beside the groups held on the device)."""
        return max((self.mesh_room - self.held) // DECIMATE_BYTES_PER_FACE, 1)

    @property
    def carries_quadrics(self) -> bool:
        """Whether the groups' quadrics go on to a last pass (in "seams" mode the seams are decimated with quadrics
        of their current faces)."""
        return self.mode == "last pass"

    def add(self, part: Any) -> None:
        if self.pending and self.pending_faces + part.nt > self.cap:
            self.flush()
        for p in self.pending:  # a group reads only its top slab's shared plane: the others' are freed
            p.plane_above = None
        part.plane_below = None
        self.pending.append(part)
        self.pending_faces += part.nt

    def flush(self) -> None:
        """Decimate the pending slabs as one group, pinned where they meet the slabs below and above."""
        import warp as wp

        from engine.kernels import tiles as kt
        from engine.stages.decimate import decimate_carrying

        if not self.pending:
            return
        t0 = time.perf_counter()
        parts, self.pending, n_faces = self.pending, [], self.pending_faces
        self.pending_faces = 0
        self.mc33_faces += n_faces
        if not self.mode:  # will the decimated groups fit for one last pass? (extrapolated from the first group)
            expected = self.ratio * self.mc33_faces * (self.nz - 1) / max(parts[-1].z_top, 1)
            self.mode = "last pass" if expected * DECIMATE_BYTES_PER_FACE <= self.mesh_room else "seams"
        v0 = parts[0].vstart
        fid = self.top_ids  # the shared vertices below are the last group's top ones
        nf, n_own = len(fid), sum(p.nv for p in parts)
        above = parts[-1].plane_above.numpy()  # sync point: 8 bytes per plane edge
        shared = np.zeros(n_own, bool)  # (a mark per vertex: np.unique sorted the plane, 5 ms a group on the H100)
        shared[above[above >= v0] - v0] = True
        tid = np.flatnonzero(shared) + v0
        with wp.ScopedDevice(self.dev):
            pos = wp.empty(nf + n_own, dtype=wp.vec3)
            faces = wp.empty(n_faces, dtype=wp.vec3i)
            if nf:
                wp.copy(pos, wp.array(self.top_pos, dtype=wp.vec3), count=nf)
            ov, of = nf, 0
            for p in parts:
                wp.copy(pos, p.verts, dest_offset=ov, count=p.nv)
                wp.copy(faces, p.faces, dest_offset=of, count=p.nt)
                ov, of = ov + p.nv, of + p.nt
            del parts
            fmin = int(fid[0]) if nf else v0
            fmap = np.full(max(v0 - fmin, 1), -1, np.int32)
            fmap[fid - fmin] = np.arange(nf, dtype=np.int32)
            wp.launch(kt.localize_faces, dim=n_faces, inputs=[faces, v0, nf, fmin, wp.array(fmap, dtype=wp.int32)])
            lock_np = np.zeros(nf + n_own, np.int32)
            lock_np[:nf] = 1
            lock_np[tid - v0 + nf] = 1
            t1 = self._lap("prepare", t0)
            ratio = min(1.0, self.ratio * (self.slack if self.mode == "last pass" else SEAM_SLACK))
            res = decimate_carrying(
                pos,
                faces,
                max(round(ratio * n_faces), 1),
                locked=wp.array(lock_np, dtype=wp.int32),
                origin=wp.vec3d(*self.origin),
                stop_tolerance=PIECE_TOLERANCE,
            )
            del pos, faces
            t1 = self._lap("decimate", t1)
            self._number(res, nf, tid, v0)
        self._lap("number", t1)
        self.groups.append(
            {"faces_in": n_faces, "faces_out": len(res.faces), "passes": res.stats.passes, "pinned": nf + len(tid)}
        )
        if self.held > self.spill_bytes:
            t1 = time.perf_counter()
            self.spill()
            self._lap("spill", t1)
        self.seconds += time.perf_counter() - t0

    def _number(self, res: Any, nf: int, tid: np.ndarray, v0: int) -> None:
        """Number the group's output after the groups before it. Its first ``nf`` vertices are the shared ones below
        (pinned, so all kept, in order); its own vertices get new ids."""
        import warp as wp

        from engine.kernels import tiles as kt

        kept = res.kept.numpy()  # sync point: 4 bytes per vertex
        if nf and not np.array_equal(kept[:nf], np.arange(nf)):
            raise RuntimeError("a pinned vertex was removed by the decimation of a group of slabs")
        carry = self.carries_quadrics
        if nf and carry:
            self.deferred.append((self.top_out, res.quad[:nf].numpy().reshape(-1, 10)))
        foreign_out = wp.array(self.top_out.astype(np.int32) if nf else np.zeros(1, np.int32), dtype=wp.int32)
        base = self.n_out - nf
        wp.launch(kt.globalize_faces, dim=len(res.faces), inputs=[res.faces, nf, foreign_out, base])
        top_res = np.searchsorted(kept, tid - v0 + nf)  # the pinned top vertices' rows in the output
        self.top_ids, self.top_out = tid, top_res + base
        self.top_pos = res.pos.numpy()[top_res] if len(top_res) else np.zeros((0, 3), np.float32)
        if len(top_res):
            self.borders.append(float(np.median(self.top_pos[:, 0])))
        n_new = len(kept) - nf
        self.pieces.append((res.pos[nf:], res.faces, res.quad[nf:] if carry else None))
        self.held += n_new * (12 + (80 if carry else 0)) + len(res.faces) * 12
        self.n_out += n_new

    def spill(self) -> None:
        """The decimated groups held on the device go to the host."""
        for pos, faces, quad in self.pieces:
            q = quad.numpy().reshape(-1, 10) if quad is not None else np.zeros((0, 10))
            self.host.append((pos.numpy().reshape(-1, 3), faces.numpy().reshape(-1, 3), q))
        self.pieces, self.held = [], 0

    def result(self) -> tuple[HostMesh | None, tuple[Any, Any, Any] | None]:
        """``(host mesh, None)`` when groups were spilled, else ``(None, (pos, faces, quad))`` on the device."""
        import warp as wp

        from engine.kernels import tiles as kt
        from engine.kernels.decimate import quadric

        self.flush()
        ids = np.concatenate([d[0] for d in self.deferred]) if self.deferred else np.zeros(0, np.int64)
        shares = np.concatenate([d[1] for d in self.deferred]) if self.deferred else np.zeros((0, 10))
        if self.host:
            self.spill()
            quad = np.concatenate([h[2] for h in self.host])
            if len(quad):
                quad[ids] += shares  # each side's faces' share of a shared vertex's quadric
            pos = np.concatenate([h[0] for h in self.host])
            faces = np.concatenate([h[1] for h in self.host])
            return HostMesh(pos, faces, quad, self.origin), None
        with wp.ScopedDevice(self.dev):
            carried = self.carries_quadrics
            pos = wp.empty(self.n_out, dtype=wp.vec3)
            quad = wp.empty(self.n_out, dtype=quadric) if carried else None
            faces = wp.empty(sum(len(p[1]) for p in self.pieces), dtype=wp.vec3i)
            ov = of = 0
            for p, f, q in self.pieces:
                wp.copy(pos, p, dest_offset=ov, count=len(p))
                if quad is not None:
                    wp.copy(quad, q, dest_offset=ov, count=len(q))
                wp.copy(faces, f, dest_offset=of, count=len(f))
                ov, of = ov + len(p), of + len(f)
            self.pieces = []
            if len(ids) and quad is not None:
                add = [wp.array(ids.astype(np.int32), dtype=wp.int32), wp.array(shares, dtype=quadric), quad]
                wp.launch(kt.add_quadrics, dim=len(ids), inputs=add)
        return None, (pos, faces, quad)

    def _lap(self, name: str, t: float) -> float:
        now = time.perf_counter()
        self.timings[name] += now - t
        return now


def _slabs_within(slabs: Any, share: float) -> Any:
    """The slab generator, its budget errors restated for the whole budget (slabs get ``share`` of it)."""
    from engine.errors import BudgetError

    try:
        yield from slabs
    except BudgetError as exc:
        needed = (int(exc.needed / share) // 2**20 + 1) * 2**20  # whole MiB, rounded up
        msg = f"{exc}: give at least {mib(needed)}"
        raise BudgetError(msg, needed) from None


def stream_surface(
    volume: np.ndarray,
    level: float,
    spacing: tuple[float, float, float],
    *,
    closed: bool,
    gaussian: GaussianParams | None,
    budget: int,
    ratio: float | None,
    decimate: bool,
    dev: Any,
    stats: Any,
) -> StreamResult:
    """Gaussian and MC33 over z slabs within ``budget`` bytes of device memory, decimating groups of slabs
    (to ``ratio`` of their faces, or by half when the target is a face count) whenever the mesh would not fit.

    Raises:
        BudgetError: one slab (one block layer and its halo) or, without decimation, the mesh needs more.
        ValueError: as ``engine.stages.isosurface`` (NaN in the data).
    """
    from engine.errors import BudgetError
    from engine.stages.slabs import SlabPlan, _run_slabs, join_parts
    from engine.staging import plane_feed

    share = STREAM_SLAB_SHARE if decimate else SLAB_SHARE  # of the budget, for a slab
    slab_bytes = (int(budget * share) // plane_bytes(volume, gaussian) + 3) * volume[0].nbytes  # the most uploaded
    with plane_feed(volume, dev, slab_bytes) as feed:
        get_slab, per_plane, halo = slab_getter(volume, gaussian, feed.upload)
        # a group is decimated between slabs, when the slab's working set is freed: it may use the whole budget but
        # for what stays on the device meanwhile (the halo planes of the streamed Gaussian, the shared-plane ids)
        resident = halo * per_plane + 16 * (volume.shape[1] + 1) * (volume.shape[2] + 1)
        spill = int(budget * SPILL_SHARE)
        if decimate:  # a slab runs beside the groups decimated so far (up to ``spill``) and the pending slabs
            room = budget - resident
            cap = (room - spill) // DECIMATE_BYTES_PER_FACE  # a slab's faces must fit a group however many are held
            target: int | None = max(cap // GROUP_SLABS, 1)
        else:  # undecimated, the mesh stays whole beside the slab (checked below)
            room = 1 << 62
            cap, target = int(budget * (1 - share)) // MESH_BYTES_PER_FACE, None
        plan = SlabPlan(int(budget * share), per_plane, halo, max_faces=max(cap, 1), target_faces=target, strict=True)
        origin = 0.5 * (np.array(volume.shape, np.float64) - 1) * np.asarray(spacing, np.float64)
        # the groups stop short of the target (GROUP_SLACK), leaving the last collapses to a pass across borders
        group_ratio = ratio if ratio is not None else 0.5
        groups = GroupDecimator(group_ratio, GROUP_SLACK, room, spill, origin, volume.shape[0], dev)
        out = StreamResult(origin=origin)
        t0 = time.perf_counter()
        is_float = gaussian is not None or volume.dtype == np.float32
        slabs = _run_slabs(get_slab, volume.shape, plan, is_float, level, spacing, closed, dev, stats)
        for part in _slabs_within(slabs, share):
            out.mc33_faces += part.nt
            out.mc33_vertices += part.nv
            if not decimate and out.mc33_faces > cap:
                needed = int(out.mc33_faces * MESH_BYTES_PER_FACE / (1 - share))
                raise BudgetError(
                    f"the undecimated model does not fit the device memory budget of {mib(budget)} "
                    f"(more than {out.mc33_faces:,} faces); decimate it or give at least {mib(needed)}",
                    needed=needed,
                )
            groups.add(part)
        out.info = {"slabs": stats.slabs, "slab_retries": stats.retries, "group_cap_faces": cap}
        if not groups.groups:  # it all fitted: the undecimated mesh stays on the device
            if groups.pending and stats.level_in_range:
                out.device = join_parts(groups.pending)
            out.info["groups"] = 0
        else:
            out.host, out.pieces = groups.result()
            out.info |= {"groups": len(groups.groups), "group_rounds": groups.groups}
            out.info |= {"group_seconds": groups.seconds, "group_timings": groups.timings}
            out.info["group_mode"] = groups.mode
            out.borders = groups.borders
        out.info["seconds"] = time.perf_counter() - t0
        if feed.stats is not None:  # the uploads through the pinned ring (engine.staging.PlaneFeed)
            out.info["feed"] = dict(feed.stats)
    return out
