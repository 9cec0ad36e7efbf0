"""A model per label, batched: every label of a map meshed together on the device (not one pipeline run per label),
on any backend: each kernel is written in Warp (``kernels/labels.py``) and in OpenCL C (``kernels/labels.cl``),
launched by this one host code through ``engine.backend``.

1. **Boxes**, one pass over the map (``mark_extent``): the planes, rows and columns each label occupies.
2. **Atlases**: each label's box, padded by ``PAD`` voxels, becomes a crop of its indicator; crops of similar
   (y, x) size are stacked along z into a few atlases (``_groups``), so one Gaussian and one MC33 run per atlas
   mesh many labels at once. The indicator is 1 on the label, ``OTHER_LABEL`` (-1) on any other label and 0 on
   background; the surface is its level ``LEVEL`` = 0.5 after the pipeline's 3x3x3 Gaussian. For two labels A
   and B the indicators add up to at most 0 everywhere (1 - 1 on A and on B, -2 on a third, 0 elsewhere), and so
   do their smoothed and trilinearly interpolated fields (both linear, weights >= 0): no point is at or above 0.5
   in both, so their level sets are a whole unit apart; where two labels touch, each surface retreats about 0.32
   voxel from the shared face (a 0.64-voxel gap at the default sigma), while against background it sits where a
   plain 0/1 indicator puts it. (-0.5 still separates the level sets, but MC33's flat triangles of two labels
   interleaved in one cell then crossed on the headsq test map: -1 is the margin that kept them apart.) The
   padding keeps every surface inside its own crop (a pad plane is below 0.11 after smoothing), so the crops of
   an atlas never join.
3. **One mesh**: each atlas' vertices move back to the grid with their label slot (place_vertices);
   the atlases' meshes are joined and decimated as one (``engine.decimation.passes.decimate_carrying``: every
   guard, the slots carried through ``kept``; vertices of a cell that another label touches are pinned, since a
   collapse there could carry a face across the neighbour's), with the triangle budget shared by area: label i may keep
   ``T * area_i / sum(area)`` faces (``share_by_area``), and labels still above their share after a round are
   decimated again with the others pinned (``locked``). Then the surface-preserving smoothing of the pipeline.
4. **Parts**: the mesh comes back once and is split by slot on the host, each part in the patient frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.backend.base import VEC3F, VEC3I, Backend
from engine.errors import EmptyLabelError
from engine.labels import kernel_specs as ks
from engine.params import MIN_TRIANGLES, GaussianParams, ReconParams

__all__ = ["LEVEL", "PAD", "LabelMesh", "mesh_labels", "share_by_area"]

LEVEL = 0.5
OTHER_LABEL = -1.0  # the indicator on other labels' voxels (<= -1: disjoint meshes; see the module docstring)
PAD = 2  # voxels around each label's box: one for the Gaussian's reach, one more below the level
MAX_ROUNDS = 3  # decimation rounds that bring labels above their area share down to it
SHARE_TOLERANCE = 0.05
MIN_LABEL_FACES = 200  # a label's share is never below this (or its own face count): tiny labels stay solid
MAX_PASSES = 20  # per round (5x at 31M faces takes 19 on the H100); pinned vertices leave little to more passes


@dataclass
class LabelMesh:
    """The labels' joined mesh on the host: vertices (z, y, x) mm in the grid, faces, each vertex's label slot."""

    vertices: np.ndarray
    faces: np.ndarray
    slot: np.ndarray
    values: list[int]
    info: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Map:
    """The label map on the device: its backend, array, integer type (the generic kernels' variant) and shape, and
    the fixed-point scale of the area sums."""

    be: Backend
    dev: Any
    dtype: np.dtype[Any]
    shape: tuple[int, int, int]
    area_scale: float


@dataclass
class _Crop:
    slot: int
    lo: np.ndarray  # grid (z, y, x) of the crop's first voxel (may be outside the map)
    dims: np.ndarray  # (dz, dy, dx)


def share_by_area(areas: np.ndarray, total: int, least: int = MIN_TRIANGLES) -> np.ndarray:
    """Each label's share of a ``total`` face budget, by its area (at least ``least`` each)."""
    a = np.maximum(np.asarray(areas, dtype=np.float64), 0)
    if a.sum() <= 0:
        return np.full(len(a), max(total // max(len(a), 1), least), dtype=np.int64)
    out: np.ndarray = np.maximum(np.floor(total * a / a.sum()).astype(np.int64), least)
    return out


def _boxes(m: _Map, values: list[int]) -> list[_Crop]:
    """Each label's padded box from one pass over the device map (``EmptyLabelError`` for a label not in it)."""
    be, (nz, ny, nx) = m.be, m.shape
    lut = np.full(max(values) + 1, -1, dtype=np.int32)
    lut[values] = np.arange(len(values), dtype=np.int32)
    fz, fy, fx = (be.zeros((len(values), n), np.int32) for n in (nz, ny, nx))
    args = [m.dev, be.from_host(lut), len(lut), fz, fy, fx, nz, ny, nx]
    be.launch(ks.MARK_EXTENT, m.shape, args, dtype=m.dtype)
    flags = [be.to_host(f).astype(bool) for f in (fz, fy, fx)]  # sync point
    crops, empty = [], []
    for s, v in enumerate(values):
        if not flags[0][s].any():
            empty.append(v)
            continue
        lo = np.array([np.argmax(f[s]) for f in flags]) - PAD
        hi = np.array([len(f[s]) - np.argmax(f[s][::-1]) for f in flags]) + PAD
        crops.append(_Crop(s, lo, hi - lo))
    if empty:
        raise EmptyLabelError(f"label value(s) {empty} have no voxels in the map")
    return crops


def _groups(crops: list[_Crop], max_waste: float = 0.5) -> list[list[_Crop]]:
    """Crops grouped into atlases of a common (y, x) size, each atlas at most ``max_waste`` empty padding."""
    order = sorted(crops, key=lambda c: -int(c.dims[1] * c.dims[2]))
    groups: list[list[_Crop]] = []
    for c in order:
        if groups:
            g = groups[-1]
            y = max(max(m.dims[1] for m in g), c.dims[1])
            x = max(max(m.dims[2] for m in g), c.dims[2])
            used = sum(int(np.prod(m.dims)) for m in g) + int(np.prod(c.dims))
            if used >= (1 - max_waste) * y * x * (sum(int(m.dims[0]) for m in g) + c.dims[0]):
                g.append(c)
                continue
        groups.append([c])
    return groups


def _atlas_mesh(m: _Map, group: list[_Crop], values: list[int], params: ReconParams, sp: Any) -> Any:
    """One atlas: fill, smooth, MC33; returns (verts in atlas mm, faces, plane_crop, crops table) on the device."""
    from engine.isosurface import extract_isosurface
    from engine.volume import smooth_volume

    z0 = np.cumsum([0] + [int(c.dims[0]) for c in group])
    table = np.array(
        [[z0[i], *c.lo, c.dims[1], c.dims[2], values[c.slot]] for i, c in enumerate(group)], dtype=np.int32
    )
    plane_crop = np.repeat(np.arange(len(group), dtype=np.int32), [int(c.dims[0]) for c in group])
    shape = (int(z0[-1]), max(int(c.dims[1]) for c in group), max(int(c.dims[2]) for c in group))
    pc, tab = m.be.from_host(plane_crop), m.be.from_host(table)
    field = m.be.empty(shape, np.float32)
    m.be.launch(ks.FILL_ATLAS, shape, [m.dev, pc, tab, OTHER_LABEL, field, *m.shape], dtype=m.dtype)
    field = smooth_volume(field, params.gaussian or GaussianParams())
    verts, faces = extract_isosurface(field, LEVEL, spacing=sp, closed=True)
    return verts, faces, pc, tab


def _join(
    m: _Map, parts: list[tuple[Any, Any, Any, Any, np.ndarray]], sp: tuple[float, float, float]
) -> tuple[Any, ...]:
    """The atlases' meshes as one device mesh in grid mm, with each vertex's label slot and near flag."""
    be = m.be
    nv, nf = sum(len(p[0]) for p in parts), sum(len(p[1]) for p in parts)
    pos, faces = be.empty(nv, VEC3F), be.empty(nf, VEC3I)
    slot, near = be.empty(nv, np.int32), be.empty(nv, np.int32)
    v0 = f0 = 0
    for verts, fcs, pc, tab, crop_slot in parts:
        if len(verts):
            args = [verts, pc, len(pc), tab, be.from_host(crop_slot), m.dev, *sp, v0, pos, slot, near, *m.shape]
            be.launch(ks.PLACE_VERTICES, len(verts), args, dtype=m.dtype)
            be.launch(ks.OFFSET_FACES, len(fcs), [fcs, v0, f0, faces])
        v0, f0 = v0 + len(verts), f0 + len(fcs)
    return pos, faces, slot, near


def _per_slot(be: Backend, pos: Any, faces: Any, slot: Any, n: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Faces and area (mm^2) per label slot (device sums in fixed point, ``scale`` units per mm^2; one sync)."""
    count, area = be.zeros(n, np.int32), be.zeros(n, np.int64)
    if len(faces):
        be.launch(ks.FACE_SUMS, len(faces), [pos, faces, slot, scale, count, area])
    return be.to_host(count).astype(np.int64), be.to_host(area) / scale  # sync point


def area_scale(spacing_zyx_mm: tuple[float, float, float]) -> float:
    """Fixed-point units per mm^2 of the per-label area sums: 2^20 per face of the smallest voxel side (a face's
    rounding is below 1e-6 of a voxel face; a sum of 10^9 voxel faces still fits an int64)."""
    return float(np.float32(2.0**20 / min(spacing_zyx_mm) ** 2))


def _decimate(
    m: _Map, mesh: tuple[Any, Any, Any, Any], n: int, params: ReconParams, info: dict[str, Any]
) -> tuple[Any, ...]:
    """Decimation of the joined mesh to the budget shared by area (rounds with the labels in budget pinned), the
    vertices near another label pinned throughout (a collapse there could carry a face across the neighbour's)."""
    from engine.decimation import decimate_carrying

    be, (pos, faces, slot, near) = m.be, mesh
    if params.decimate is None or len(faces) == 0:
        return pos, faces, slot
    count, area = _per_slot(be, pos, faces, slot, n, m.area_scale)
    total = params.decimate.target_faces(len(faces))
    share = np.minimum(share_by_area(area, total, MIN_LABEL_FACES), np.maximum(count, 1))
    info.update(input_faces=len(faces), target_faces=int(share.sum()), share_faces=share.tolist(), rounds=0)
    locked, quad, origin = near, None, None
    info["pinned_near_other_labels"] = int(be.to_host(near).sum()) if len(near) else 0  # sync point
    for _ in range(MAX_ROUNDS):
        over = count > share * (1 + SHARE_TOLERANCE)
        if not over.any():
            break
        target = int(np.where(over, share, count).sum())
        before = len(faces)
        out = decimate_carrying(
            pos, faces, target, locked=locked, quadrics=quad, origin=origin, carry=True, max_passes=MAX_PASSES
        )
        new_slot, new_near = be.empty(len(out.pos), np.int32), be.empty(len(out.pos), np.int32)
        be.launch(ks.GATHER_SLOTS, len(out.pos), [slot, out.kept, new_slot])
        be.launch(ks.GATHER_SLOTS, len(out.pos), [near, out.kept, new_near])
        pos, faces, slot, near, quad, origin = out.pos, out.faces, new_slot, new_near, out.quad, out.origin
        count, _ = _per_slot(be, pos, faces, slot, n, m.area_scale)
        info["rounds"] += 1
        info.setdefault("passes", []).append(out.stats.passes)
        info.setdefault("stopped", []).append(out.stats.stopped)
        locked = be.empty(len(pos), np.int32)
        still = be.from_host((count > share * (1 + SHARE_TOLERANCE)).astype(np.int32))
        be.launch(ks.LOCK_SLOTS, len(pos), [slot, still, near, locked])
        if len(faces) >= before:
            break  # the guards allow no more
    info["output_faces"] = len(faces)
    info["limited_by_guards"] = bool((count > share * (1 + SHARE_TOLERANCE)).any())
    return pos, faces, slot


def _closed_check(pos: Any, faces: Any) -> dict[str, Any]:
    """The joined mesh's edge census on the device: watertight and manifold (then so is every label)."""
    from engine.surface import mesh_stats_device

    if len(faces) == 0:
        return {"watertight": False}
    stats = mesh_stats_device(pos, faces)
    keys = ("watertight", "manifold", "boundary_edges", "nonmanifold_edges", "inconsistent_edges", "components")
    return {k: stats[k] for k in keys}  # type: ignore[literal-required]


def mesh_labels(
    labels: np.ndarray,
    values: list[int],
    spacing_zyx_mm: tuple[float, float, float],
    params: ReconParams | None = None,
    *,
    device: Any = "auto",
) -> LabelMesh:
    """Mesh every label of ``values`` in the (z, y, x) integer map ``labels``; one joined mesh comes back.

    Args:
        labels: the map (uint8, uint16, int32 or uint32; other integer types are converted).
        values: the label values to mesh (> 0), each present in the map.
        spacing_zyx_mm: voxel size.
        params: the pipeline's ``gaussian`` (sigma), ``decimate`` (the budget, shared by area) and ``smooth``;
            the level is fixed (``LEVEL`` of the indicator) and the islands stage does not run.
        device: a backend (``engine.backend``) or a device spec for ``get_backend``: every backend gives the
            same mesh.

    Raises:
        EmptyLabelError: a value has no voxels.
    """
    from engine.backend.select import get_backend
    from engine.surface import smooth_device

    params = params or ReconParams()
    values = [int(v) for v in values]
    if not values or min(values) <= 0:
        raise EmptyLabelError(f"no label values to mesh (got {values}; 0 is background)")
    if labels.dtype not in (np.uint8, np.uint16, np.int32, np.uint32):
        labels = labels.astype(np.int32 if int(labels.max()) < 2**31 else np.uint32)
    be = get_backend(device)
    sp = (float(spacing_zyx_mm[0]), float(spacing_zyx_mm[1]), float(spacing_zyx_mm[2]))
    info: dict[str, Any] = {"seconds": {}, "backend": be.label}
    t = time.perf_counter()
    m = _Map(be, be.from_host(np.ascontiguousarray(labels)), labels.dtype, labels.shape, area_scale(sp))
    crops = _boxes(m, values)
    info["seconds"]["boxes"] = time.perf_counter() - t
    parts = []
    groups = _groups(crops)
    for g in groups:
        verts, faces, pc, tab = _atlas_mesh(m, g, values, params, sp)
        parts.append((verts, faces, pc, tab, np.array([c.slot for c in g], dtype=np.int32)))
    pos, faces, slot, near = _join(m, parts, sp)
    info["atlases"] = [
        [int(sum(c.dims[0] for c in g)), int(max(c.dims[1] for c in g)), int(max(c.dims[2] for c in g))] for g in groups
    ]
    info["mc33_faces"] = len(faces)
    info["seconds"]["isosurface"] = time.perf_counter() - t - info["seconds"]["boxes"]
    t1 = time.perf_counter()
    info["decimate"] = {}
    pos, faces, slot = _decimate(m, (pos, faces, slot, near), len(values), params, info["decimate"])
    info["seconds"]["decimate"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    if params.smooth is not None and len(faces):
        pos, info["smooth"] = smooth_device(pos, faces, params.smooth)
    info["seconds"]["smooth"] = time.perf_counter() - t1
    info.update(_closed_check(pos, faces))
    out = LabelMesh(
        be.to_host(pos).reshape(-1, 3), be.to_host(faces).reshape(-1, 3).astype(np.int32), be.to_host(slot), values
    )
    info["seconds"]["total"] = time.perf_counter() - t
    out.info = info
    return out
