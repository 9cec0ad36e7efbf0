"""Stage: bone of the body only, for HU data. Drops the couch, head holders and anything else above the bone level
that lies outside the patient's body outline, before meshing (host, scipy.ndimage).

The outline is the tissue at or above ``outline_hu`` and below the bone level, its holes filled slice by slice: a
bone covered by soft tissue (skull under the scalp, a pelvis in the abdomen) becomes part of it, while a couch or
a head holder, which touches the air outside, does not (even where a phantom rests on the couch without an air
gap). The partial-volume rim around a thin holder plate also closes in a slice, so parts of a slice's outline
thinner than 6 mm beside a thicker part are not body (``body_outline``). Each connected bone piece (26-connected
voxels at or above the level) is kept when enough of it lies inside the outline; the voxels of the others are set
to the volume's minimum (air).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from engine.errors import NoBoneInBodyError
from engine.params import BodyMaskParams
from engine.types import Volume

# a part of a slice's body outline thinner than this (twice this radius) beside a thicker part is not body
THIN_PART_RADIUS_MM = 3.0


def body_outline(
    data: np.ndarray,
    level: float,
    outline: float,
    spacing_zyx_mm: tuple[float, float, float],
    dilate_mm: float,
    thin_radius_mm: float | None = THIN_PART_RADIUS_MM,
) -> np.ndarray:
    """The filled body outline (bool, same shape): tissue >= ``outline`` and < ``level``, holes filled per slice,
    without the thin parts (see below), grown in-plane by ``dilate_mm``.

    The partial-volume rim around a thin holder plate passes through the tissue range and closes around it in a
    slice, so that hole filling puts the plate "inside" an outline of its own (the head-holder plates of the
    gantry-tilt series, 18 mm beside the skull). A connected part of a slice's outline that does not hold a disc of
    ``thin_radius_mm`` (6 mm across; a finger, a toe or a wrist holds one) is dropped when the slice has a thicker
    part (the body); a slice whose parts are all thin keeps them. None: keep every part.

    Every step is in-plane (slice by slice), run on ``CHUNK_PLANES`` slices at a time with an in-plane structure
    (one scipy call per chunk, not per slice), the chunks side by side on threads (scipy releases the GIL).
    """
    body = np.empty(data.shape, bool)
    pixel_mm = min(spacing_zyx_mm[1:])

    def chunk(z0: int, z1: int) -> None:
        d = data[z0:z1]
        part = fill_holes_in_plane((d >= outline) & (d < level))
        if thin_radius_mm is not None and part.any():
            part = _without_thin_parts(part, thin_radius_mm, pixel_mm)
        if dilate_mm > 0:
            from scipy import ndimage as ndi

            for z in range(part.shape[0]):
                part[z] = ndi.distance_transform_edt(~part[z], sampling=spacing_zyx_mm[1:]) <= dilate_mm
        body[z0:z1] = part

    _by_chunks(chunk, data.shape[0])
    return body


CHUNK_PLANES = 16  # slices outlined at once: the chunk's labels (int32) are what it holds in memory
_PLANE_CROSS = np.zeros((3, 3, 3), bool)  # in-plane 4-connectivity: no step across slices
_PLANE_CROSS[1] = [[0, 1, 0], [1, 1, 1], [0, 1, 0]]


def _by_chunks(fn: Any, nz: int) -> None:
    """``fn(z0, z1)`` over the slices in chunks of ``CHUNK_PLANES``, on the host's threads (each chunk writes its
    own slices)."""
    spans = _spans(nz)
    threads = min(len(spans), os.cpu_count() or 1, MAX_THREADS)
    if threads <= 1:
        for z0, z1 in spans:
            fn(z0, z1)
        return
    with ThreadPoolExecutor(threads, thread_name_prefix="bonemesh-body") as pool:
        for done in [pool.submit(fn, z0, z1) for z0, z1 in spans]:
            done.result()


MAX_THREADS = 16


def _spans(nz: int) -> list[tuple[int, int]]:
    """The chunks of ``CHUNK_PLANES`` slices, in order."""
    return [(z, min(z + CHUNK_PLANES, nz)) for z in range(0, nz, CHUNK_PLANES)]


def bone_pieces(data: np.ndarray, level: float) -> tuple[np.ndarray, int]:
    """The 26-connected pieces of the voxels at or above ``level``: ``(labels, n)`` as ``scipy.ndimage.label``
    gives them for the whole volume (the same pieces, numbered in another order), labelled in chunks of slices on
    the host's threads and joined across the chunks' borders (a voxel touches the 9 beside it in the next slice)."""
    from scipy import ndimage as ndi
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    labels = np.empty(data.shape, np.int32)
    nz = data.shape[0]
    spans = _spans(nz)
    counts = dict.fromkeys((z0 for z0, _ in spans), 0)

    def label(z0: int, z1: int) -> None:
        counts[z0] = ndi.label(data[z0:z1] >= level, structure=np.ones((3, 3, 3), bool), output=labels[z0:z1])

    _by_chunks(label, nz)
    first, total = {}, 0  # each chunk's labels follow the chunks' before it
    for z0, _ in spans:
        first[z0], total = total, total + counts[z0]
    if len(spans) == 1 or total == 0:
        return labels, total
    pairs = []  # in the chunks' own numbering, moved to the volume's
    for (z0, _), (z, _) in itertools.pairwise(spans):
        a, b = _touching(labels[z - 1], labels[z])
        pairs.append((a + first[z0], b + first[z]))
    a, b = np.concatenate([p[0] for p in pairs]), np.concatenate([p[1] for p in pairs])
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(total + 1, total + 1))
    _, comp = connected_components(graph, directed=False)
    _, joined = np.unique(comp[1:], return_inverse=True)
    remap = joined.astype(np.int32) + 1  # a chunk's label k is the volume's label first + k, here at first + k - 1

    def renumber(z0: int, z1: int) -> None:
        lut = np.concatenate([[0], remap[first[z0] : first[z0] + counts[z0]]]).astype(np.int32)
        labels[z0:z1] = lut[labels[z0:z1]]

    _by_chunks(renumber, nz)
    return labels, int(joined.max()) + 1


def _touching(below: np.ndarray, above: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs of labels (both set) of two adjacent slices that touch, 26-connected: each voxel and the 9 beside
    it in the other slice."""
    ny, nx = below.shape
    out_a, out_b = [], []
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            a = below[max(0, -dy) : ny - max(0, dy), max(0, -dx) : nx - max(0, dx)]
            b = above[max(0, dy) : ny - max(0, -dy), max(0, dx) : nx - max(0, -dx)]
            both = (a > 0) & (b > 0)
            out_a.append(a[both])
            out_b.append(b[both])
    return np.concatenate(out_a), np.concatenate(out_b)


def fill_holes_in_plane(tissue: np.ndarray) -> np.ndarray:
    """Each slice's holes filled, as ``scipy.ndimage.binary_fill_holes`` fills one slice: the background (4-connected
    in the slice) that reaches the slice's edge is outside; everything else is body."""
    from scipy import ndimage as ndi

    back, _ = ndi.label(~tissue, structure=_PLANE_CROSS)
    outside = np.zeros(int(back.max()) + 1, bool)
    for edge in (back[:, 0, :], back[:, -1, :], back[:, :, 0], back[:, :, -1]):
        outside[edge] = True
    outside[0] = False  # the tissue itself
    filled: np.ndarray = ~outside[back]
    return filled


def _without_thin_parts(body: np.ndarray, radius_mm: float, pixel_mm: float) -> np.ndarray:
    """``body`` without its thin in-plane parts (``body_outline``): a part is thick when something of it survives
    an in-plane erosion by the radius (city-block steps of a pixel, so a disc of that radius survives); a slice
    with no thick part keeps all of its parts."""
    from scipy import ndimage as ndi

    steps = max(1, round(radius_mm / pixel_mm))
    thick = ndi.binary_erosion(body, structure=_PLANE_CROSS, iterations=steps)
    parts, n = ndi.label(body, structure=_PLANE_CROSS)
    keep = np.zeros(n + 1, bool)
    keep[parts[thick]] = True  # label 0 (not body) is never thick
    kept: np.ndarray = np.where(thick.any(axis=(1, 2))[:, None, None], keep[parts], body)
    return kept


def isolate_bone(
    volume: Volume, level: float, params: BodyMaskParams, hu_offset: float | None
) -> tuple[Volume, dict[str, Any]]:
    """Remove the bone pieces outside the body outline (see the module docstring).

    Args:
        volume: the scan.
        level: the bone iso level in the volume's units.
        params: the outline threshold, dilation and the share of a piece that must lie inside.
        hu_offset: stored value = HU + this (0 for HU data); None: the data are not HU, nothing is done.

    Returns:
        The volume (the same object when nothing was removed) and the report entry: ``applied``, the outline's
        threshold, ``pieces``, ``pieces_removed``, ``voxels_removed``, ``volume_removed_mm3``,
        ``largest_removed_mm3`` and ``seconds``; or ``applied`` False with the reason.

    Raises:
        NoBoneInBodyError: there is bone-level material, but none of it inside the body.
    """
    if hu_offset is None:
        return volume, {
            "applied": False,
            "reason": "the volume is not in HU (for stacks of HU + offset give iso.hu_offset, CLI --hu-offset)",
        }
    outline = params.outline_hu + hu_offset
    if level <= outline:  # a skin surface (or lower): there is no tissue below the level to outline a body with
        return volume, {
            "applied": False,
            "reason": f"the level is at or below the body outline's threshold ({params.outline_hu:g} HU)",
        }
    t0 = time.perf_counter()
    data = volume.data
    voxel_mm3 = float(np.prod(volume.spacing_zyx_mm))
    labels, n = bone_pieces(data, level)
    info: dict[str, Any] = {
        "applied": True,
        "outline_hu": params.outline_hu,
        "outline_stored": outline,
        "min_inside_fraction": params.min_inside_fraction,
        "dilate_mm": params.dilate_mm,
        "pieces": int(n),
    }
    if n == 0:  # no bone at all: the isosurface stage reports the empty surface with the data's range
        info.update(pieces_removed=0, voxels_removed=0, volume_removed_mm3=0.0, largest_removed_mm3=0.0)
        return volume, {**info, "seconds": time.perf_counter() - t0}
    body = body_outline(data, level, outline, volume.spacing_zyx_mm, params.dilate_mm)
    size, inside = _piece_counts(labels, body, n)
    drop = inside < params.min_inside_fraction * size
    drop[0] = False
    removed = size[drop]
    info.update(
        pieces_removed=int(drop.sum()),
        voxels_removed=int(removed.sum()),
        volume_removed_mm3=float(removed.sum()) * voxel_mm3,
        largest_removed_mm3=float(removed.max()) * voxel_mm3 if removed.size else 0.0,
        body_voxels=int(body.sum()),
    )
    kept_mm3 = float(size[1:][~drop[1:]].sum()) * voxel_mm3
    info["kept_mm3"] = kept_mm3
    if drop.any() and kept_mm3 < params.min_bone_mm3:
        units = "HU" if hu_offset == 0 else f"stored (HU + {hu_offset:g})"
        raise NoBoneInBodyError(
            f"no bone inside the body: {info['pieces_removed']} of the {n} piece(s) at or above the level "
            f"{level:g} {units} ({info['volume_removed_mm3']:,.0f} mm3) lie outside the body outline (a couch, a "
            f"head holder), and only {kept_mm3:,.0f} mm3 lie inside (less than {params.min_bone_mm3:g} mm3); choose "
            "another level, or switch the body mask off (CLI --keep-outside-body, job params body: null)"
        )
    if not drop.any():
        return volume, {**info, "seconds": time.perf_counter() - t0}
    out = data.copy()
    air = data.min()

    def clear(z0: int, z1: int) -> None:
        part = out[z0:z1]
        part[drop[labels[z0:z1]]] = air

    _by_chunks(clear, data.shape[0])
    return dataclasses.replace(volume, data=out), {**info, "seconds": time.perf_counter() - t0}


def _piece_counts(labels: np.ndarray, body: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each piece's voxels, and those inside the outline (index = label), counted chunk by chunk on threads."""
    size, inside = np.zeros(n + 1, np.int64), np.zeros(n + 1, np.int64)
    lock = threading.Lock()

    def count(z0: int, z1: int) -> None:
        lab = labels[z0:z1]
        here = np.bincount(lab.ravel(), minlength=n + 1), np.bincount(lab[body[z0:z1]], minlength=n + 1)
        with lock:
            size[:] += here[0]
            inside[:] += here[1]

    _by_chunks(count, labels.shape[0])
    return size, inside
