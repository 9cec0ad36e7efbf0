"""Stage: the volume stages within a device memory budget, and the first decimation round slab by slab.

``stream_surface`` runs the Gaussian and MC33 over z slabs of the host volume (each slab uploaded with a one-plane
halo, smoothed, and handed to MC33, so the field is the whole-volume Gaussian's, bit for bit), and keeps the slabs'
meshes on the device. When the mesh built so far and its decimation would no longer fit the budget, the slabs
gathered so far are decimated as one group (``GroupDecimator``) with the vertices they share with the slabs below
and above pinned, so the pieces still join into one watertight surface; the decimated group goes to the host with
its quadrics, and the next group starts. If no group had to go, the whole MC33 mesh is still on the device and the
pipeline goes on as without a budget; otherwise the decimated groups are finished across their borders by
``engine.decimation.tiles``.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.budget import Budget, mib
from engine.decimation.groups import GROUP_SLACK, GroupDecimator
from engine.decimation.tiles import HostMesh
from engine.params import GaussianParams

GROUP_SLABS = 4  # slabs are sized for this share of a group's faces (a group then fills at least 3/4 of its cap)


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


def plane_bytes(volume: Any, gaussian: GaussianParams | None) -> int:
    """Device bytes of one z plane in a slab: the samples, and the Gaussian's two float32 planes where it runs."""
    return int(volume.shape[1] * volume.shape[2] * (volume.itemsize + (8 if gaussian is not None else 0)))


def slab_getter(volume: Any, gaussian: GaussianParams | None, upload: Any) -> tuple[Any, int, int]:
    """``(get_slab, plane_bytes, halo_planes)`` for ``run_slabs`` over ``volume`` (a host array, or a scan read slab
    by slab: ``engine.io.slabs.SlabSource``): planes zlo..zhi uploaded by ``upload(lo, hi)``
    (``engine.isosurface.feed.plane_feed``) and smoothed, with a plane of halo on each side so the result equals the
    whole volume's Gaussian."""
    from engine.backend.select import backend_of
    from engine.volume.gaussian import smooth_volume

    nz = volume.shape[0]
    if gaussian is None:
        return upload, plane_bytes(volume, gaussian), 0

    def smoothed(zlo: int, zhi: int) -> Any:
        lo, hi = max(zlo - 1, 0), min(zhi + 1, nz - 1)
        field_ = smooth_volume(upload(lo, hi), gaussian)
        return backend_of(field_).view(field_, zlo - lo, zhi - lo + 1)

    return smoothed, plane_bytes(volume, gaussian), 2


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
    volume: Any,
    level: float,
    spacing: tuple[float, float, float],
    *,
    closed: bool,
    gaussian: GaussianParams | None,
    budget: Budget,
    ratio: float | None,
    decimate: bool,
    dev: Any,
    stats: Any,
    zpart: Any = None,
) -> StreamResult:
    """Gaussian and MC33 over z slabs of ``volume`` (a host array, or a scan read slab by slab from disk:
    ``engine.io.slabs.SlabSource``, whose planes are read as the slabs need them, within the budget's host bound)
    within a device memory ``budget`` (limited), decimating groups of slabs (to ``ratio`` of their faces, or by half
    when the target is a face count) whenever the mesh would not fit.

    ``zpart``: one z part of a job over several devices (``engine.isosurface.multi.Part``): only its block layers
    are streamed, after the vertices it shares with the part below, and its slabs always end in decimated groups
    (pinned where they meet the parts below and above), to be joined with the other parts'.

    Raises:
        BudgetError: one slab (one block layer and its halo) or, without decimation, the mesh needs more.
        ValueError: as ``engine.isosurface.mc33`` (NaN in the data).
    """
    from engine.errors import BudgetError
    from engine.isosurface.feed import plane_feed
    from engine.isosurface.slabs import SlabPlan, join_parts, run_slabs

    share = budget.stream_slab_share if decimate else budget.slab_share  # of the budget, for a slab
    plane = volume.shape[1] * volume.shape[2] * volume.itemsize
    slab_bytes = (budget.share(share) // plane_bytes(volume, gaussian) + 3) * plane  # the most uploaded
    host = budget.host_read_bytes  # under a host bound: the ring (or a direct read) takes at most this
    ring = None if zpart is None else zpart.ring  # a part of a job over several devices: its own pinned ring
    with plane_feed(volume, dev, slab_bytes, ring_bytes=budget.feed_ring_bytes, host_bytes=host, pinned=ring) as feed:
        get_slab, per_plane, halo = slab_getter(volume, gaussian, feed.upload)
        # a group is decimated between slabs, when the slab's working set is freed: it may use the whole budget but
        # for what stays on the device meanwhile (the halo planes of the streamed Gaussian, the shared-plane ids)
        resident = halo * per_plane + 16 * (volume.shape[1] + 1) * (volume.shape[2] + 1)
        spill = budget.share(budget.spill_share)
        if decimate:  # a slab runs beside the groups decimated so far (up to ``spill``) and the pending slabs
            room = budget.share(1) - resident
            cap = (room - spill) // budget.costs.decimate  # a slab's faces must fit a group however many are held
            target: int | None = max(cap // GROUP_SLABS, 1)
        else:  # undecimated, the mesh stays whole beside the slab (checked below)
            room = 1 << 62
            cap, target = budget.share(1 - share) // budget.costs.mesh, None
        plan = SlabPlan(budget.share(share), per_plane, halo, max_faces=max(cap, 1), target_faces=target, strict=True)
        origin = 0.5 * (np.array(volume.shape, np.float64) - 1) * np.asarray(spacing, np.float64)
        # the groups stop short of the target (GROUP_SLACK), leaving the last collapses to a pass across borders
        group_ratio = ratio if ratio is not None else 0.5
        group_room = room if budget.group_room_share == 1 else int(room * budget.group_room_share)
        make = GroupDecimator if zpart is None else zpart.decimator
        groups = make(group_ratio, GROUP_SLACK, group_room, spill, origin, volume.shape[0], dev, budget)
        out = StreamResult(origin=origin)
        t0 = time.perf_counter()
        is_float = gaussian is not None or volume.dtype == np.float32
        run = functools.partial(run_slabs, get_slab, volume.shape, plan, is_float, level, spacing, closed, dev)
        slabs = run(stats) if zpart is None else zpart.slabs(run, stats)
        for part in _slabs_within(slabs, share):
            out.mc33_faces += part.nt
            out.mc33_vertices += part.nv
            if not decimate and out.mc33_faces > cap:
                needed = int(out.mc33_faces * budget.costs.mesh / (1 - share))
                raise BudgetError(
                    f"the undecimated model does not fit the device memory budget of {mib(budget.share(1))} "
                    f"(more than {out.mc33_faces:,} faces); decimate it or give at least {mib(needed)}",
                    needed=needed,
                )
            groups.add(part)
        out.info = {"slabs": stats.slabs, "slab_retries": stats.retries, "group_cap_faces": cap}
        if not groups.groups and zpart is None:  # it all fitted: the undecimated mesh stays on the device
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
        if feed.stats is not None:  # the uploads through the pinned ring (engine.isosurface.feed.PlaneFeed)
            out.info["feed"] = dict(feed.stats)
    return out
