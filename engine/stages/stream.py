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

from engine.memory import DECIMATE_BYTES_PER_FACE, MESH_BYTES_PER_FACE, SLAB_SHARE, mib
from engine.params import GaussianParams

PIECE_TOLERANCE = 0.01  # a group or tile stops this close to its share (the last pass across them is exact)
GROUP_SLACK = 1.15  # groups of slabs keep this many times their share of the target


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
    """``device`` (pos, faces) when the whole MC33 mesh fitted, else ``host`` (the decimated groups)."""

    device: tuple[Any, Any] | None = None
    host: HostMesh | None = None
    mc33_faces: int = 0
    mc33_vertices: int = 0
    info: dict[str, Any] = field(default_factory=dict)


def slab_getter(volume: np.ndarray, gaussian: GaussianParams | None, dev: Any) -> tuple[Any, int, int]:
    """``(get_slab, plane_bytes, halo_planes)`` for ``_run_slabs``: planes zlo..zhi uploaded (and smoothed, with a
    plane of halo on each side so the result equals the whole volume's Gaussian)."""
    import warp as wp

    from engine.stages.gaussian import smooth_volume

    nz, ny, nx = volume.shape
    if gaussian is None:

        def raw(zlo: int, zhi: int) -> Any:
            return wp.array(np.ascontiguousarray(volume[zlo : zhi + 1]), device=dev)

        return raw, ny * nx * volume.itemsize, 0

    def smoothed(zlo: int, zhi: int) -> Any:
        lo, hi = max(zlo - 1, 0), min(zhi + 1, nz - 1)
        field_ = smooth_volume(wp.array(np.ascontiguousarray(volume[lo : hi + 1]), device=dev), gaussian)
        return field_[zlo - lo : zhi - lo + 1]

    return smoothed, ny * nx * (volume.itemsize + 8), 2


class GroupDecimator:
    """Collects slab meshes and decimates them in groups whose decimation fits ``cap_faces``."""

    def __init__(self, ratio: float | None, cap_faces: int, origin: np.ndarray, dev: Any) -> None:
        self.ratio, self.cap, self.origin, self.dev = ratio, cap_faces, origin, dev
        self.pending: list[Any] = []
        self.pending_faces = 0
        self.pos: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.quad: list[np.ndarray] = []
        self.n_out = 0
        self.top_ids = np.zeros(0, np.int64)  # MC33 ids of the last group's pinned top vertices, sorted
        self.top_out = np.zeros(0, np.int64)  # and their ids in the output
        self.groups: list[dict[str, Any]] = []
        self.seconds = 0.0
        self.timings = {"prepare": 0.0, "decimate": 0.0, "download": 0.0, "assemble": 0.0}

    def add(self, part: Any) -> None:
        if self.pending and self.pending_faces + part.nt > self.cap:
            self.flush()
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
        v0 = parts[0].vstart
        below = parts[0].plane_below.numpy()  # sync point: 8 bytes per plane edge
        fid = np.unique(below[below >= 0]).astype(np.int64)
        nf, n_own = len(fid), sum(p.nv for p in parts)
        with wp.ScopedDevice(self.dev):
            pos = wp.empty(nf + n_own, dtype=wp.vec3)
            faces = wp.empty(n_faces, dtype=wp.vec3i)
            if nf:
                out_ids = self.top_out[np.searchsorted(self.top_ids, fid)]
                wp.copy(pos, wp.array(self._host_pos(out_ids), dtype=wp.vec3), count=nf)
            ov, of = nf, 0
            for p in parts:
                wp.copy(pos, p.verts, dest_offset=ov, count=p.nv)
                wp.copy(faces, p.faces, dest_offset=of, count=p.nt)
                ov, of = ov + p.nv, of + p.nt
            fmin = int(fid[0]) if nf else v0
            fmap = np.full(max(v0 - fmin, 1), -1, np.int32)
            fmap[fid - fmin] = np.arange(nf, dtype=np.int32)
            wp.launch(kt.localize_faces, dim=n_faces, inputs=[faces, v0, nf, fmin, wp.array(fmap, dtype=wp.int32)])
            lock = wp.zeros(nf + n_own, dtype=wp.int32)
            if nf:
                lock[:nf].fill_(1)
            top = parts[-1].plane_above
            wp.launch(kt.lock_plane, dim=top.shape, inputs=[top, v0, nf, lock])
            del parts, top
            t1 = self._lap("prepare", t0)
            target = n_faces if self.ratio is None else max(round(self.ratio * n_faces), 1)
            res = decimate_carrying(
                pos, faces, target, locked=lock, origin=wp.vec3d(*self.origin), stop_tolerance=PIECE_TOLERANCE
            )
            t1 = self._lap("decimate", t1)
            out_pos, out_faces = res.pos.numpy(), res.faces.numpy().reshape(-1, 3)  # sync point
            out_quad, kept = res.quad.numpy().reshape(-1, 10), res.kept.numpy().astype(np.int64)
            pinned = lock.numpy()[kept] != 0
        t1 = self._lap("download", t1)
        self._assemble(out_pos, out_faces, out_quad, kept, pinned, fid, v0)
        self._lap("assemble", t1)
        self.groups.append(
            {"faces_in": n_faces, "faces_out": len(out_faces), "passes": res.stats.passes, "pinned": int(pinned.sum())}
        )
        self.seconds += time.perf_counter() - t0

    def _lap(self, name: str, t: float) -> float:
        now = time.perf_counter()
        self.timings[name] += now - t
        return now

    def _host_pos(self, out_ids: np.ndarray) -> np.ndarray:
        start = self.n_out - len(self.pos[-1])
        return self.pos[-1][out_ids - start]

    def _assemble(
        self,
        pos: np.ndarray,
        faces: np.ndarray,
        quad: np.ndarray,
        kept: np.ndarray,
        pinned: np.ndarray,
        fid: np.ndarray,
        v0: int,
    ) -> None:
        """Number the group's output after the groups before it: the vertices it shares with the group below keep
        that group's ids (and add their quadrics to it); its own vertices get new ids."""
        nf = len(fid)
        foreign = kept < nf
        lut = np.empty(len(kept), np.int64)
        if foreign.any():
            shared = self.top_out[np.searchsorted(self.top_ids, fid[kept[foreign]])]
            lut[foreign] = shared
            start = self.n_out - len(self.pos[-1])
            self.quad[-1][shared - start] += quad[foreign]  # each side's faces' share of the pinned quadric
        own = ~foreign
        n_new = int(own.sum())
        lut[own] = self.n_out + np.arange(n_new)
        mc33_id = v0 + kept - nf
        top = own & pinned
        self.top_ids, self.top_out = mc33_id[top], lut[top]  # increasing, as ``kept`` is
        self.pos.append(pos.reshape(-1, 3)[own])
        self.quad.append(quad[own])
        self.faces.append(lut[faces].astype(np.int32))
        self.n_out += n_new

    def result(self) -> HostMesh:
        self.flush()
        return HostMesh(np.concatenate(self.pos), np.concatenate(self.faces), np.concatenate(self.quad), self.origin)


def _slabs_within(slabs: Any) -> Any:
    """The slab generator, its budget errors restated for the whole budget (slabs get ``SLAB_SHARE`` of it)."""
    from engine.errors import BudgetError

    try:
        yield from slabs
    except BudgetError as exc:
        needed = (int(exc.needed / SLAB_SHARE) // 2**20 + 1) * 2**20  # whole MiB, rounded up
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
    from engine.stages.isosurface import SlabPlan, _run_slabs, join_parts

    get_slab, plane_bytes, halo = slab_getter(volume, gaussian, dev)
    mesh_room = int(budget * (1 - SLAB_SHARE))
    cap = mesh_room // DECIMATE_BYTES_PER_FACE if decimate else mesh_room // MESH_BYTES_PER_FACE
    plan = SlabPlan(int(budget * SLAB_SHARE), plane_bytes, halo, max_faces=max(cap, 1), strict=True)
    origin = 0.5 * (np.array(volume.shape, np.float64) - 1) * np.asarray(spacing, np.float64)
    # the groups stop short of the target (GROUP_SLACK), leaving the last collapses to a pass across their borders
    groups = GroupDecimator(min(1.0, ratio * GROUP_SLACK) if ratio is not None else 0.5, cap, origin, dev)
    out = StreamResult()
    t0 = time.perf_counter()
    is_float = gaussian is not None or volume.dtype == np.float32
    for part in _slabs_within(_run_slabs(get_slab, volume.shape, plan, is_float, level, spacing, closed, dev, stats)):
        out.mc33_faces += part.nt
        out.mc33_vertices += part.nv
        if not decimate and out.mc33_faces > cap:
            needed = int(out.mc33_faces * MESH_BYTES_PER_FACE / (1 - SLAB_SHARE))
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
        out.host = groups.result()
        out.info |= {"groups": len(groups.groups), "group_rounds": groups.groups, "group_seconds": groups.seconds}
        out.info["group_timings"] = groups.timings
    out.info["seconds"] = time.perf_counter() - t0
    return out
