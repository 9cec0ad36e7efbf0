"""Device operations of the defect template on any backend (``engine.backend``; kernels in
``engine.defect.kernels``, named in ``engine.defect.kernel_specs``): the exact Euclidean distance transform and the mask
selections. Device volumes are flat arrays of ``n = nz * ny * nx`` elements in (z, y, x) order; the shape travels
beside them."""

from __future__ import annotations

from typing import Any

import numpy as np

from engine.backend.base import Backend

BIG_MM = 1.0e30  # "no feature": the distance where a transform found nothing
# threads per point of the nearest-feature query (a warp's worth: each looks at every 32nd row of the point's box)
NEAREST_PARTS = 32


def distance(
    be: Backend, mask: Any, shape: tuple[int, ...], spacing_zyx: tuple[float, float, float], *, inside: bool = False
) -> Any:
    """Exact Euclidean distance (mm, flat float32 device array) from every voxel to the nearest set voxel of
    ``mask`` (flat uint8, of ``shape``), or with ``inside`` to the nearest clear voxel; ``BIG_MM`` where there is
    none (the same bits on every backend).

    Felzenszwalb and Huttenlocher's separable transform: one pass per axis, one thread per grid line.
    """
    from engine.defect.kernel_specs import EDT_PASS, EDT_SQRT, FEATURES

    nz, ny, nx = (int(s) for s in shape)
    n = nz * ny * nx
    f = be.empty(n, np.float32)
    g = be.empty(n, np.float32)
    be.launch(FEATURES, n, [mask, int(inside), f])
    scratch = n + n // max(min(nz, ny, nx), 1) + 1  # (length + 1) entries per line, on the axis with the most lines
    v = be.empty(scratch, np.int32)
    zb = be.empty(scratch, np.float32)
    for axis in (2, 1, 0):
        be.launch(EDT_PASS, n // (nz, ny, nx)[axis], [f, g, nz, ny, nx, axis, float(spacing_zyx[axis]), v, zb])
        f, g = g, f
    be.launch(EDT_SQRT, n, [f, g])
    return g


def select(be: Backend, src: Any, value: int) -> Any:
    """Flat uint8 mask: src == value."""
    from engine.defect.kernel_specs import SELECT

    out = be.empty(len(src), np.uint8)
    be.launch(SELECT, len(src), [src, int(value), out])
    return out


def bits(be: Backend, src: Any, which: int) -> Any:
    """Flat uint8 mask: any of the bits ``which`` set in src."""
    from engine.defect.kernel_specs import BITS

    out = be.empty(len(src), np.uint8)
    be.launch(BITS, len(src), [src, int(which), out])
    return out


def upload_mask(be: Backend, mask: Any) -> Any:
    """A host bool (or uint8) volume as a flat uint8 device array."""
    return be.from_host(np.ascontiguousarray(mask).view(np.uint8).reshape(-1))


def closest_feature(be: Backend, features: Any, shape: tuple[int, ...], spacing_zyx: tuple[float, float, float]) -> Any:
    """The closest-feature transform: for every voxel, the rank (in ``features``: a flat int32 device array of
    distinct flat voxel indices) of a feature voxel nearest to it in mm (flat int32 device array of ``shape``; -1
    only where there is no feature). ``distance``'s exact separable transform, carrying the feature's rank."""
    from engine.defect.kernel_specs import CFT_PASS, CFT_SEED

    nz, ny, nx = (int(s) for s in shape)
    n = nz * ny * nx
    f = be.full(n, BIG_MM, np.float32)
    g = be.empty(n, np.float32)
    fr = be.full(n, -1, np.int32)
    gr = be.empty(n, np.int32)
    if len(features):
        be.launch(CFT_SEED, len(features), [features, f, fr])
    scratch = n + n // max(min(nz, ny, nx), 1) + 1  # as in distance
    v = be.empty(scratch, np.int32)
    zb = be.empty(scratch, np.float32)
    for axis in (2, 1, 0):
        lines = n // (nz, ny, nx)[axis]
        be.launch(CFT_PASS, lines, [f, g, fr, gr, nz, ny, nx, axis, float(spacing_zyx[axis]), v, zb])
        f, g, fr, gr = g, f, gr, fr
    return fr


def nearest_feature(
    be: Backend,
    points: Any,
    count: int,
    rank: Any,
    features: Any,
    box: Any,
    out: Any,
    *,
    max_scan: int,
    parts: int | None = None,
    scratch: tuple[Any, Any] | None = None,
) -> None:
    """``out[i]`` (int32 device array): the rank of the feature nearest to point ``i`` (grid x, y, z mm, three
    float32 each in ``points``) for the first ``count`` points (ties to the lower rank), from ``closest_feature``'s
    ``rank`` field of the grid ``box`` (``kernel_specs.BOX``). The closest feature of the voxel nearest to the point
    bounds the distance; the voxels within that bound are then looked at (exact: a feature is its own closest
    feature) where they are at most ``max_scan``, else the bound's feature is kept (a point far from every
    feature). Each point's look is shared by ``parts`` threads (by default ``NEAREST_PARTS`` on a GPU, one on
    the host's CPU), each taking every ``parts``-th row of the box, then joined: the same answer (the nearest, ties
    to the lower rank, whatever the order of the looks), where one thread's look of up to ``max_scan`` voxels set
    the query's time on a GPU. ``scratch``: the parts' float32 and int32 device arrays (at least ``count * parts``
    each) kept by a caller that queries again (allocated here when not given)."""
    from engine.defect.kernel_specs import NEAREST_JOIN, NEAREST_PART

    if count:
        parts = parts or nearest_parts(be)
        n = count * parts
        part_d2, part_rank = scratch or (be.empty(n, np.float32), be.empty(n, np.int32))
        be.launch(NEAREST_PART, n, [points, rank, features, box, int(max_scan), parts, part_d2, part_rank])
        be.launch(NEAREST_JOIN, count, [part_d2, part_rank, parts, out])


def nearest_parts(be: Backend) -> int:
    """Threads per point of ``nearest_feature`` on ``be``: ``NEAREST_PARTS`` on a GPU, one on the host's CPU (its
    cores are busy with one thread per point)."""
    return 1 if be.is_host else NEAREST_PARTS


def set_voxels(be: Backend, mask: Any, shape: tuple[int, ...], *, surface: bool = False) -> np.ndarray:
    """Flat indices (int64, ascending: ``np.flatnonzero``'s) of the set voxels of ``mask`` (flat uint8 device array
    of ``shape``), or with ``surface`` of those with a face neighbour clear or outside the grid (a sync point: the
    indices come back to the host)."""
    from engine.defect.kernel_specs import FLAGS

    nz, ny, nx = (int(s) for s in shape)
    flags = be.empty(nz * ny * nx, np.int32)
    be.launch(FLAGS, nz * ny * nx, [mask, nz, ny, nx, int(surface), flags])
    indices, _, count = be.compact(flags)
    return be.to_host(indices, count=count).astype(np.int64)


def sobel(be: Backend, mask: Any, shape: tuple[int, ...], at: Any, count: int) -> np.ndarray:
    """The 3x3x3 Sobel gradient (integer x, y, z components, (count, 3) int32 on the host; the grid outside clear)
    of ``mask`` (flat uint8 device array of ``shape``) at the flat voxels ``at`` (int32 device array)."""
    from engine.defect.kernel_specs import SOBEL

    nz, ny, nx = (int(s) for s in shape)
    out = be.empty(3 * max(count, 1), np.int32)
    if count:
        be.launch(SOBEL, count, [mask, nz, ny, nx, at, out])
    return be.to_host(out, count=3 * count).reshape(count, 3)


def largest_piece(be: Backend, bone: Any, shape: tuple[int, ...]) -> tuple[Any, int]:
    """The largest 26-connected piece of ``bone`` (flat uint8 device array of ``shape``) as a flat uint8 device
    mask, and the number of pieces; of pieces the same size, the one whose first voxel comes first in the flat
    order (``scipy.ndimage.label``'s numbering, as ``grid.bone_and_skull`` picks). Min-label hooking with pointer
    jumping: a sync point per round (a few rounds), one for the pieces' sizes."""
    from engine.defect.kernel_specs import PIECE_GATHER, PIECE_HOOK, PIECE_INIT, PIECE_MASK, PIECE_ROOTS
    from engine.surface.kernel_specs import JUMP_LABELS  # the meshes' pointer jumping (unlabelled voxels left)

    nz, ny, nx = (int(s) for s in shape)
    n = nz * ny * nx
    label = be.empty(n, np.int32)
    be.launch(PIECE_INIT, n, [bone, label])
    changed = be.zeros(1, np.int32)
    while True:
        be.fill(changed, 0)
        be.launch(PIECE_HOOK, n, [nz, ny, nx, label, changed])
        be.launch(JUMP_LABELS, n, [label])
        if int(be.to_host(changed)[0]) == 0:  # sync point
            break
    size = be.zeros(n, np.int32)
    flags = be.empty(n, np.int32)
    be.launch(PIECE_ROOTS, n, [label, size, flags])
    roots, _, count = be.compact(flags)
    out = be.empty(n, np.uint8)
    if count == 0:
        be.fill(out, 0)
        return out, 0
    sizes = be.empty(count, np.int32)
    be.launch(PIECE_GATHER, count, [size, roots, sizes])
    root = int(be.to_host(roots, count=count)[int(np.argmax(be.to_host(sizes)))])  # the first of the largest
    be.launch(PIECE_MASK, n, [label, root, out])
    return out, count


def bone_and_skull(be: Backend, data: Any, level: float) -> tuple[Any, Any]:
    """``engine.defect.grid.bone_and_skull`` with the skull's pieces found on the backend: the bone (every sample at
    or above the level, on the host) and the skull, its largest 26-connected piece (``largest_piece``), as host
    bool volumes; the same masks.

    Raises:
        EmptySurfaceError: nothing is at or above the level.
    """
    from engine.defect.grid import bone_at

    bone = bone_at(data, level)
    shape = tuple(int(s) for s in bone.shape)
    skull, pieces = largest_piece(be, upload_mask(be, bone), shape)
    if pieces == 1:
        return bone, bone.copy()
    return bone, be.to_host(skull).reshape(shape).view(np.bool_)
