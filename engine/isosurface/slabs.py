"""Marching Cubes 33 over z slabs of a volume (``run_slabs``): per slab, classify blocks -> count -> scan -> emit,
with slabs sized to a device memory budget and stitched so the mesh is the same as one pass's
(``engine.isosurface.mc33`` wraps it; ``engine.isosurface.stream`` feeds it smoothed slabs under a budget).

The volume is processed in slabs of whole block layers along z with a one-plane overlap; vertex ids continue across
slabs (the ids of the slab's first plane come from the previous slab).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, Backend
from engine.isosurface.kernel_specs import BLOCK, BLOCK_CELLS, BLOCKS, COUNT, EMIT, GRID, NAN, PLANE
from engine.isosurface.stats import IsosurfaceStats, Timer

TIE_TAU = 1.0 / 1024.0  # an edge point is never closer than this (in edges) to a sample (engine.isosurface.mc33)
_INT32_MAX = 2**31 - 1


@functools.cache
def _tables(be: Backend) -> dict[str, Any]:
    """Lookup tables uploaded once per backend, from the one generated source (``mc33_tables`` and its generator's
    face cycles) for every backend."""
    from engine.isosurface import _make_mc33_tables as gen
    from engine.isosurface import mc33_tables as t

    key_map = np.full(t.N_KEYS_DENSE, -1, dtype=np.int32)
    key_map[np.asarray(t.KEYS, dtype=np.int64)] = np.asarray(t.TRI_ID, dtype=np.int32)
    face_cyc = np.asarray([c for cyc, _ in gen.FACES for c in cyc], dtype=np.int32)

    def up(values: Any, dtype: Any) -> Any:
        return be.from_host(np.asarray(values, dtype=dtype))

    return {
        "key_map": up(key_map, np.int32),
        "face_cyc": up(face_cyc, np.int32),
        "tri_offset": up(t.TRI_OFFSET, np.int32),
        "tri_count": up(t.TRI_COUNT, np.int32),
        "tri_local": up(t.TRIANGLES, np.int32),
        "ivert_offset": up(t.IVERT_OFFSET, np.int32),
        "ivert_count": up(t.IVERT_COUNT, np.int32),
        "ivert_weights": up(t.IVERT_WEIGHTS, np.float32),
    }


def _per_active_block() -> int:
    """Working-set bytes per active block: 5 int32 per cell slot, plus room for ~1 vertex and ~2 triangles per
    cell of output (a worst case; the real output is known after the count)."""
    return BLOCK_CELLS * (20 + 36)


def _per_layer(shape: tuple[int, int, int], plane_bytes: int) -> int:
    """Fixed bytes per block layer: its volume planes (``plane_bytes`` each) and the per-block arrays."""
    _, ny, nx = shape
    nby, nbx = -(-(ny + 1) // BLOCK), -(-(nx + 1) // BLOCK)
    return BLOCK * plane_bytes + nby * nbx * 16


def _layers_per_slab(shape: tuple[int, int, int], plane_bytes: int, budget: int, active_share: float = 1.0) -> int:
    """Block layers per slab within ``budget`` when ``active_share`` of the blocks are active (1: the worst case)."""
    _, ny, nx = shape
    nby, nbx = -(-(ny + 1) // BLOCK), -(-(nx + 1) // BLOCK)
    per_layer = _per_layer(shape, plane_bytes) + int(nby * nbx * active_share * _per_active_block())
    layers = max(1, budget // max(per_layer, 1))
    layers = min(layers, max(1, (_INT32_MAX // 2) // (nby * nbx * BLOCK_CELLS)))
    return int(layers)


@dataclass
class SlabMesh:
    """One slab's share of the mesh, on the device: its new vertices (ids ``vstart`` ..) and faces, and the vertex
    ids on its bottom and top planes (``(2, ny + 1, nx + 1)`` int32, -1 where none), which it shares with the
    slabs below and above (the faces of a slab use its own vertices and those of ``plane_below``)."""

    verts: Any
    faces: Any
    nv: int
    nt: int
    vstart: int
    plane_below: Any
    plane_above: Any
    z_top: int = 0  # index of the top plane


@dataclass
class SlabPlan:
    """How ``run_slabs`` sizes its slabs: ``budget`` bytes for a slab's working set, of which a z plane of the
    source costs ``plane_bytes`` (the slab getter's own working set per plane, e.g. the streamed Gaussian's);
    ``max_faces`` caps a slab's output (a slab over it is redone smaller) and ``target_faces`` is what slabs are
    sized for (at the last slab's faces per layer; fewer, larger slabs cost less than many thin ones); ``strict``
    raises ``BudgetError`` where one block layer does not fit (otherwise one layer is used anyway, as MC33 alone
    always did)."""

    budget: int
    plane_bytes: int
    halo_planes: int = 0
    max_faces: int | None = None
    target_faces: int | None = None
    strict: bool = False


class _SlabPass:
    """What every slab of a pass shares: the backend, the volume's block grid, the lookup tables on the device, the
    sizes the slabs are planned with (``SlabPlan``), the flags the kernels raise (level below/above seen, NaN, table
    misses), the stats and the timer; and the phases of one slab, each over explicit arrays (classify and compact
    the blocks, count, emit). Kernels are launched by name (``engine.isosurface.kernel_specs``) on any backend."""

    def __init__(self, shape: tuple[int, int, int], plan: SlabPlan, be: Backend, st: IsosurfaceStats) -> None:
        self.be, self.shape, self.plan, self.st = be, shape, plan, st
        self.tables = _tables(be)
        nz, ny, nx = shape
        self.nbz_total = -(-(nz + 1) // BLOCK)
        self.nby, self.nbx = -(-(ny + 1) // BLOCK), -(-(nx + 1) // BLOCK)
        self.fixed = _per_layer(shape, plan.plane_bytes)
        self.halo = plan.halo_planes * plan.plane_bytes
        self.per_block = BLOCK_CELLS * 20  # the per-cell slot arrays; the output is counted once known
        self.layers = _layers_per_slab(shape, plan.plane_bytes, max(plan.budget - self.halo, 1))
        self.flags = be.zeros(4, np.int32)
        self.timer = Timer(st, be)
        self.dtype: Any = None  # the slabs' sample type (the OpenCL programs are built per type)

    def grid(self, zlo: int, bz0: int, n_layers: int, level: float, spacing: Any, closed: bool) -> Any:
        """The slab's ``Grid`` (planes from ``zlo``, block layers ``bz0`` .. ``bz0 + n_layers``)."""
        nz, ny, nx = self.shape
        sz, sy, sx = spacing
        return self.be.struct(
            GRID, nz=nz, ny=ny, nx=nx, zoff=zlo, bz0=bz0, nbz=n_layers, nby=self.nby, nbx=self.nbx,
            cz_first=bz0 * BLOCK - 1, level=level, pad=-1.0,  # only the pad's sign is used (engine.isosurface.mc33)
            closed=int(bool(closed)), tau=TIE_TAU, sz=sz, sy=sy, sx=sx,
        )  # fmt: skip

    def classify(self, sub: Any, g: Any, nblocks: int, is_float: bool) -> tuple[Any, Any, int]:
        """The blocks whose samples straddle the level, compacted: ``(active list, every block's place in it or -1,
        how many)`` (a sync point); NaN in a float slab raises a flag."""
        from engine.volume.gaussian import sample_dtype

        be = self.be
        self.dtype = sample_dtype(sub)
        if is_float:
            be.launch(NAN, tuple(sub.shape), [sub, self.flags], dtype=self.dtype)
        active = be.empty(nblocks, np.int32)
        be.launch(BLOCKS, nblocks, [sub, g, active, self.flags], dtype=self.dtype)
        return be.compact(active)

    def count(self, sub: Any, g: Any, alist: Any, nslots: int) -> tuple[Any, Any, Any, int, int]:
        """Each active cell's vertices and triangles, scanned: ``(voff, toff, code, nv, nt)`` (a sync point)."""
        be, t = self.be, self.tables
        vcount = be.empty(nslots, np.int32)
        tcount = be.empty(nslots, np.int32)
        code = be.empty(nslots, np.int32)
        inputs = [sub, g, alist, t["face_cyc"], t["key_map"], t["tri_count"], t["ivert_count"], vcount, tcount, code]
        be.launch(COUNT, nslots, [*inputs, self.flags], dtype=self.dtype)
        self.timer.lap("count")
        voff = be.empty(nslots, np.int32)
        toff = be.empty(nslots, np.int32)
        nv = be.exclusive_scan(vcount, voff)  # sync point
        nt = be.exclusive_scan(tcount, toff)  # sync point
        return voff, toff, code, nv, nt

    def emit(
        self,
        sub: Any,
        g: Any,
        blocks: tuple[Any, Any],
        counted: tuple[Any, Any, Any, int, int],
        plane_prev: Any,
        vstart: int,
        cz_last: int,
    ) -> tuple[Any, Any, Any]:
        """The slab's vertices (ids from ``vstart``) and faces, and the vertex ids on its top planes."""
        be, t = self.be, self.tables
        alist, bmap = blocks
        voff, toff, code, nv, nt = counted
        _, ny, nx = self.shape
        verts = be.empty(max(nv, 1), VEC3F)
        faces = be.empty(max(nt, 1), VEC3I)
        inputs = [sub, g, alist, bmap, voff, toff, code, plane_prev, vstart, t["tri_offset"], t["tri_count"]]
        inputs += [t["tri_local"], t["ivert_offset"], t["ivert_count"], t["ivert_weights"], verts, faces]
        be.launch(EMIT, len(code), inputs, dtype=self.dtype)
        plane_next = be.empty((2, ny + 1, nx + 1), np.int32)
        be.launch(PLANE, (ny + 1, nx + 1), [g, bmap, voff, code, vstart, cz_last, plane_next])
        return verts, faces, plane_next

    def smaller(self, n_layers: int) -> None:
        """Redo this slab with half the layers."""
        self.layers = max(1, n_layers // 2)
        self.st.retries += 1

    def finish(self) -> None:
        """The flags of the whole pass: NaN raises; the level's range and the table misses go to the stats."""
        fl = self.be.to_host(self.flags)  # sync point
        if fl[2]:
            raise ValueError("Expected a volume without NaN, got NaN values in the float volume")
        self.st.table_misses = int(fl[3])
        self.st.level_in_range = bool(fl[0] and fl[1])


def run_slabs(
    get_slab: Callable[[int, int], Any],
    shape: tuple[int, int, int],
    plan: SlabPlan,
    is_float: bool,
    level: float,
    spacing: tuple[float, float, float],
    closed: bool,
    dev: Any,
    st: IsosurfaceStats,
    *,
    layers: tuple[int, int] | None = None,
    plane_prev: Any = None,
    vstart: int = 0,
) -> Iterator[SlabMesh]:
    """Yield each slab's mesh (``SlabMesh``); check NaN and the level's range at the end.

    ``dev`` is the backend (``engine.backend.Backend``, or a Warp device for Warp's);
    ``get_slab(zlo, zhi)`` returns the (zhi - zlo + 1, ny, nx) samples of planes zlo..zhi on it. Slabs start
    at the worst-case size for ``plan.budget`` and adapt to the active blocks and faces of the slab before; a slab
    found over the budget (or over ``plan.max_faces``) after its blocks are classified or counted is redone with
    half the layers, so the result never depends on the slabbing. Per slab, the phases of ``_SlabPass``: classify
    the blocks, compact the active ones, count, emit.

    ``layers``: only block layers ``[first, end)`` (a z part of the volume, ``engine.isosurface.multi``), after the
    vertices of the part below: ``plane_prev``, the ids on the part's bottom plane (a ``SlabMesh.plane_above`` of
    layer ``first - 1``; None: none), and ``vstart``, the first id of the part's own vertices.
    """
    from engine.backend.select import get_backend

    be = get_backend(dev)
    p = _SlabPass(shape, plan, be, st)
    nz, ny, nx = shape
    B = BLOCK
    if plane_prev is None:
        plane_prev = be.full((2, ny + 1, nx + 1), -1, np.int32)
    bz0, bz_end = (0, p.nbz_total) if layers is None else layers
    active_per_layer = faces_per_layer = 0.0  # the last slab's (with any), for sizing the next slab
    while bz0 < bz_end:
        bz1 = min(bz0 + p.layers, bz_end)
        n_layers = bz1 - bz0
        cz_first = bz0 * B - 1
        cz_last = min(bz1 * B - 1, nz) - 1  # last cell layer (origin)
        zlo, zhi = max(cz_first, 0), min(cz_last + 1, nz - 1)
        sub = get_slab(zlo, zhi)
        p.timer.lap("upload")
        g = p.grid(zlo, bz0, n_layers, level, spacing, closed)
        nblocks = n_layers * p.nby * p.nbx
        alist, bmap, n_active = p.classify(sub, g, nblocks, is_float)
        need = p.fixed * n_layers + p.halo + n_active * p.per_block
        if need > plan.budget and n_layers > 1:
            p.smaller(n_layers)
            continue
        # (one layer over a strict budget goes on to the count, so the error can name the whole need)
        blocks = (alist, bmap)
        del alist, bmap
        p.timer.lap("classify blocks")
        nslots = n_active * BLOCK_CELLS
        slab_bytes = be.nbytes(sub) + nblocks * 12 + nslots * 20
        if nslots == 0:
            _accept(st, nblocks, n_active, cz_last - cz_first + 1, slab_bytes)
            be.fill(plane_prev, -1)
            bz0 = bz1
            p.layers = _next_layers(plan, p, active_per_layer, faces_per_layer, p.layers)
            continue
        counted = p.count(sub, g, blocks[0], nslots)
        nv, nt = counted[3:]
        p.timer.lap("scan")
        if plan.max_faces is not None and nt > plan.max_faces:
            if n_layers > 1:
                p.smaller(n_layers)
                continue
            if plan.strict:
                raise _too_small(
                    need + nt * plan.budget // max(plan.max_faces, 1),
                    "the faces of one block layer of the volume (8 z planes)",
                )
        need += nv * 12 + nt * 12 + (ny + 1) * (nx + 1) * 8
        if need > plan.budget and n_layers > 1:
            p.smaller(n_layers)
            continue
        if need > plan.budget and plan.strict:
            raise _too_small(need, "one block layer of the volume (8 z planes) and its surface")
        if vstart + nv > _INT32_MAX:
            raise ValueError(f"Expected at most {_INT32_MAX} vertices (int32 faces), got more than {vstart + nv}")
        verts, faces, plane_next = p.emit(sub, g, blocks, counted, plane_prev, vstart, cz_last)
        p.timer.lap("emit")
        del sub, blocks, counted  # the consumer may use the memory while this generator waits
        _accept(st, nblocks, n_active, cz_last - cz_first + 1, slab_bytes + nslots * 8 + nv * 12 + nt * 12)
        # the density of this slab, not the densest seen: a dense end of a scan does not keep the rest in thin
        # slabs (a slab found denser than this is redone with fewer layers)
        active_per_layer, faces_per_layer = n_active / n_layers, nt / n_layers
        yield SlabMesh(verts, faces, nv, nt, vstart, plane_prev, plane_next, cz_last + 1)
        plane_prev = plane_next
        vstart += nv
        bz0 = bz1
        p.layers = _next_layers(plan, p, active_per_layer, faces_per_layer, p.layers)
    p.finish()


def _accept(st: IsosurfaceStats, nblocks: int, n_active: int, cell_layers: int, slab_bytes: int) -> None:
    st.slabs += 1
    st.blocks += nblocks
    st.active_blocks += n_active
    st.slab_layers.append(cell_layers)
    st.peak_slab_bytes = max(st.peak_slab_bytes, slab_bytes)


def _next_layers(plan: SlabPlan, p: _SlabPass, active_per_layer: float, faces_per_layer: float, layers: int) -> int:
    """The next slab's block layers: what the budget allows at twice the last slab's active blocks (and faces) per
    layer, and no more than ``plan.target_faces`` (or half ``plan.max_faces``) at its faces per layer; growing at
    most fourfold per slab (a slab found too large is redone smaller)."""
    per_layer = p.fixed + 2.0 * (active_per_layer * p.per_block + faces_per_layer * 18)
    n = int((plan.budget - p.halo) // max(per_layer, 1.0))
    if faces_per_layer > 0:
        if plan.target_faces is not None:
            n = min(n, int(plan.target_faces // faces_per_layer))
        if plan.max_faces is not None:
            n = min(n, int(plan.max_faces // (2.0 * faces_per_layer)))
    return int(min(max(n, 1), 4 * layers, p.nbz_total))


def _too_small(need: int, what: str) -> Exception:
    from engine.errors import BudgetError

    return BudgetError(f"the device memory budget is too small for {what}", needed=int(need))


def join_parts(parts: list[SlabMesh], be: Backend | None = None) -> tuple[Any, Any]:
    """The slabs' meshes as one device mesh (vertex ids already run on across slabs), on their backend."""
    from engine.backend.select import backend_of

    be = be if be is not None else backend_of(parts[0].verts)
    if len(parts) == 1:
        return be.view(parts[0].verts, 0, parts[0].nv), be.view(parts[0].faces, 0, parts[0].nt)
    verts = be.empty(sum(p.nv for p in parts), VEC3F)
    faces = be.empty(sum(p.nt for p in parts), VEC3I)
    ov = of = 0
    for p in parts:
        be.copy(verts, p.verts, dst_offset=ov, count=p.nv)
        be.copy(faces, p.faces, dst_offset=of, count=p.nt)
        ov, of = ov + p.nv, of + p.nt
    return verts, faces
