"""What a label job keeps: a region of interest cropped before anything runs (``crop_roi``), the segments asked for
(``select_segments``: by number or name), and, from a CT alone, the N largest bone pieces as a label map of
separately named parts (``bone_pieces``: fragments of a fracture, the two femurs of a pelvis scan; specks below the
model's island size are not pieces), each with the region of the scan its model is made from (``piece_boxes``: the
job meshes the smoothed scan inside it through the model's stages, ``engine.job.run``, so that a piece's surface is
the model's surface, not that of a 0/1 mask)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from engine.errors import EmptySurfaceError, InputError
from engine.io.labelmaps import LabelVolume, Segment, palette
from engine.params import OrientParams, PiecesParams, ReconParams, RoiParams
from engine.types import Volume

__all__ = ["PieceBox", "bone_pieces", "crop_roi", "fewer_pieces_note", "piece_boxes", "roi_slices", "select_segments"]

Grid = TypeVar("Grid", Volume, LabelVolume)


def _as_volume(grid: Volume | LabelVolume) -> Volume:
    return grid.as_volume() if isinstance(grid, LabelVolume) else grid


def roi_slices(grid: Volume | LabelVolume, roi: RoiParams, orient: OrientParams | None = None) -> tuple[slice, ...]:
    """The (z, y, x) index slices of ``roi`` in the grid (an mm box through ``engine.orient.patient_frame``).

    Raises:
        InputError: the box leaves fewer than 2 samples along an axis (outside the grid, or too thin).
    """
    from engine.orient import patient_frame

    vol = _as_volume(grid)
    shape = vol.data.shape
    if roi.units == "voxels":
        bounds = [(int(lo), int(hi)) for lo, hi in roi.box]
    else:
        frame = patient_frame(vol, orient)
        corners = np.array([[x, y, z] for x in roi.box[0] for y in roi.box[1] for z in roi.box[2]], dtype=np.float64)
        grid_xyz = (corners - frame.offset_mm) @ np.linalg.inv(frame.matrix).T  # grid mm (x, y, z)
        idx = grid_xyz[:, ::-1] / np.asarray(vol.spacing_zyx_mm)
        bounds = [
            (math.ceil(lo - 1e-6), math.floor(hi + 1e-6) + 1) for lo, hi in zip(idx.min(0), idx.max(0), strict=True)
        ]
    slices = []
    for axis, (lo, hi) in enumerate(bounds):
        i0, i1 = max(0, lo), min(shape[axis], hi)
        if i1 - i0 < 2:
            raise InputError(
                f"the region of interest leaves {max(i1 - i0, 0)} sample(s) along {'zyx'[axis]} of the {shape} grid "
                f"(indices {lo}..{hi}); it must overlap the scan by at least 2"
            )
        slices.append(slice(i0, i1))
    return tuple(slices)


def crop_roi(grid: Grid, roi: RoiParams, orient: OrientParams | None = None) -> Grid:
    """The scan or label map cropped to ``roi``, its origin moved so that every kept voxel stays where it was."""
    vol = _as_volume(grid)
    sl = roi_slices(grid, roi, orient)
    offset_xyz = np.array([s.start * d for s, d in zip(sl[::-1], vol.spacing_zyx_mm[::-1], strict=True)])
    shift = np.asarray(vol.direction, dtype=np.float64) @ offset_xyz
    origin = (
        float(vol.origin_mm[0] + shift[0]),
        float(vol.origin_mm[1] + shift[1]),
        float(vol.origin_mm[2] + shift[2]),
    )
    source = {
        **grid.source,
        "roi": {"units": roi.units, "box": [list(r) for r in roi.box], "slices_zyx": [[s.start, s.stop] for s in sl]},
    }
    if isinstance(grid, LabelVolume):
        labels = np.ascontiguousarray(grid.labels[sl])
        masks = {v: np.ascontiguousarray(m[sl]) for v, m in grid.masks.items()}  # overlapping segments' own masks
        masks = {v: m for v, m in masks.items() if m.any()}
        present = set(np.unique(labels).tolist()) | set(masks)
        segments = tuple(s for s in grid.segments if s.value in present)
        if not segments:
            from engine.errors import EmptyLabelError

            raise EmptyLabelError("no label lies inside the region of interest")
        out: Grid = dataclasses.replace(  # type: ignore[call-arg]
            grid, labels=labels, origin_mm=origin, segments=segments, source=source, masks=masks
        )
        return out
    data = grid.data[sl]  # a scan read slab by slab (engine.io.slabs) gives the box's reader
    if isinstance(data, np.ndarray):
        data = np.ascontiguousarray(data)
    return dataclasses.replace(grid, data=data, origin_mm=origin, source=source)


def select_segments(lv: LabelVolume, wanted: Sequence[int | str]) -> LabelVolume:
    """Only the segments ``wanted`` (a segment number, or its name, case-insensitive), the others' voxels cleared.

    Raises:
        InputError: a wanted segment is not in the map (the message lists those it has).
    """
    by_value = {s.value: s for s in lv.segments}
    by_name = {s.name.casefold(): s for s in lv.segments}
    chosen: dict[int, Segment] = {}
    missing = []
    for want in wanted:
        seg = by_value.get(want) if isinstance(want, int) else by_name.get(str(want).casefold())
        if seg is None and isinstance(want, str) and want.strip().isdigit():
            seg = by_value.get(int(want))
        if seg is None:
            missing.append(want)
        else:
            chosen[seg.value] = seg
    if missing:
        have = ", ".join(f"{s.value} {s.name!r}" for s in lv.segments[:20]) + (", ..." if len(lv.segments) > 20 else "")
        raise InputError(f"the label map has no segment {', '.join(map(repr, missing))}; it has {have}")
    values = np.array(sorted(chosen), dtype=lv.labels.dtype)
    labels = np.where(np.isin(lv.labels, values), lv.labels, 0).astype(lv.labels.dtype, copy=False)
    segments = tuple(s for s in lv.segments if s.value in chosen)
    source = {**lv.source, "segments_selected": [int(v) for v in values]}
    return dataclasses.replace(lv, labels=labels, segments=segments, source=source)


def _structure(connectivity: int) -> np.ndarray:
    from scipy import ndimage

    out: np.ndarray = ndimage.generate_binary_structure(3, {6: 1, 18: 2, 26: 3}[connectivity])
    return out


def bone_pieces(
    volume: Volume,
    params: ReconParams | None = None,
    pieces: PiecesParams | None = None,
    *,
    level: float | None = None,
) -> LabelVolume:
    """The ``pieces.count`` largest connected pieces of the bone (voxels at or above the pipeline's level, inside
    the body for HU data as the pipeline keeps them) as a label map: value 1 the largest, named ``piece_1``...

    Specks are not pieces: a piece whose voxels' volume is below the model's island size (``params.islands``, the
    islands stage's rule: ``engine.params.islands_of``; 4 voxels by default) is never kept, and ``source`` says how
    many were left out (``specks_excluded``) and, when fewer pieces than asked exist, why (``note``).

    Args:
        level: the level of a scan prepared already (``engine.job.plans.prepare_volume``: preprocessed, the bone
            outside the body dropped); None: the level is resolved and the body mask applied here.

    Raises:
        EmptySurfaceError: no bone voxel at the level (or none in a piece of ``min_voxels`` and the island size).
    """
    from scipy import ndimage

    params = params or ReconParams()
    pieces = pieces or PiecesParams()
    if level is None:
        from engine.level import resolve_level

        choice = resolve_level(volume, params)
        level = choice.value
        if params.body is not None:
            from engine.volume.bodymask import isolate_bone

            volume, _ = isolate_bone(volume, level, params.body, choice.hu_offset)
    comp, n = ndimage.label(volume.data >= level, structure=_structure(pieces.connectivity))
    sizes = np.bincount(comp.reshape(-1))[1:] if n else np.zeros(0, np.int64)
    speck_mm3 = _speck_mm3(params, volume.spacing_zyx_mm)
    least = max(pieces.min_voxels, math.ceil(speck_mm3 / float(np.prod(volume.spacing_zyx_mm)) - 1e-9))
    real = [int(i) + 1 for i in np.argsort(-sizes, kind="stable") if sizes[i] >= least]
    order = real[: pieces.count]
    if not order:
        raise EmptySurfaceError(
            f"no bone piece of at least {least} voxels ({speck_mm3:g} mm3, the island size) at level {level:g} "
            f"{volume.units}"
        )
    lut = np.zeros(n + 1, dtype=np.uint16 if len(order) > 255 else np.uint8)
    lut[order] = np.arange(1, len(order) + 1)
    labels = lut[comp]
    segments = tuple(Segment(i, f"piece_{i}", palette(i - 1)) for i in range(1, len(order) + 1))
    source = {
        **volume.source,
        "format": "pieces",
        "level": level,
        "pieces_found": int(n),
        "pieces_asked": pieces.count,
        "pieces_kept": len(order),
        "piece_voxels": [int(sizes[i - 1]) for i in order],
        "specks_excluded": int(n) - len(real),
        "speck_limit_mm3": speck_mm3,
    }
    if len(order) < pieces.count:
        source["note"] = fewer_pieces_note(pieces.count, len(order), int(n) - len(real), speck_mm3)
    return LabelVolume(
        labels, volume.spacing_zyx_mm, volume.origin_mm, volume.direction, segments, source, volume.patient_frame
    )


def fewer_pieces_note(asked: int, kept: int, specks: int, speck_mm3: float) -> str:
    """Why a pieces job has fewer pieces than asked for, in one sentence."""
    if specks == 0:
        return f"{asked} pieces asked for, {kept} found: the scan has no other bone piece at the level"
    return (
        f"{asked} pieces asked for, {kept} found: the other {specks} bone piece(s) are specks below the island size "
        f"({speck_mm3:g} mm3), which the model drops too"
    )


def _speck_mm3(params: ReconParams, spacing_zyx_mm: tuple[float, float, float]) -> float:
    """The island size of the model (``IslandParams.min_volume_for``): 0 when it keeps specks."""
    limit = params.islands.min_volume_for(spacing_zyx_mm) if params.islands is not None else None
    return float(limit or 0.0)


# a piece's smoothed values are its own within this many voxels of it: the 3x3x3 Gaussian reaches 1, and the voxels
# next to the last one above the level place the surface on their edges
REACH = 2


@dataclass(frozen=True)
class PieceBox:
    """Where one piece's model comes from: ``box`` (z, y, x slices of the scan: the piece, ``REACH`` voxels around
    it and one more for the Gaussian) and ``region`` (bool, the box's shape): the voxels whose smoothed values are
    the piece's (within ``REACH`` of it, and nearer to it than to any other bone)."""

    value: int
    box: tuple[slice, slice, slice]
    region: np.ndarray

    def masked(self, smoothed: np.ndarray, low: float) -> np.ndarray:
        """The box's smoothed scan inside the region, ``low`` (below the level) outside: its surface at the level
        is the model's surface around this piece, closed where the region ends."""
        return np.where(self.region, smoothed, np.float32(low)).astype(np.float32, copy=False)


def piece_boxes(lv: LabelVolume, bone: np.ndarray) -> list[PieceBox]:
    """Each segment of a pieces map (``bone_pieces``) with its box and region (``PieceBox``); ``bone``: the scan's
    voxels at or above the level (bool, the map's shape), every piece and speck, so that a region stops half way to
    the next one."""
    from scipy import ndimage

    cube = np.ones((3, 3, 3), bool)
    found = ndimage.find_objects(lv.labels)
    shape = lv.labels.shape
    out = []
    for seg in lv.segments:
        where = found[seg.value - 1] if seg.value - 1 < len(found) else None
        if where is None:
            continue
        box = tuple(
            slice(max(0, s.start - REACH - 1), min(n, s.stop + REACH + 1)) for s, n in zip(where, shape, strict=True)
        )
        own = lv.labels[box] == seg.value
        region = ndimage.binary_dilation(own, structure=cube, iterations=REACH)
        other = bone[box] & ~own
        if other.any() and (ndimage.binary_dilation(other, cube, REACH) & region).any():
            region &= _nearer(own, other, lv.labels[box], seg.value, lv.spacing_zyx_mm)
        out.append(PieceBox(seg.value, box, region))  # type: ignore[arg-type]
    return out


def _nearer(own: np.ndarray, other: np.ndarray, labels: np.ndarray, value: int, spacing: Any) -> np.ndarray:
    """The voxels nearer to ``own`` than to ``other`` bone (mm); half way between two pieces, the larger one's
    (the lower value: ``bone_pieces`` numbers them largest first), half way to a speck or a piece not kept, ours."""
    from scipy import ndimage

    near_own = ndimage.distance_transform_edt(~own, sampling=spacing)
    near_other, where = ndimage.distance_transform_edt(~other, sampling=spacing, return_indices=True)
    theirs = labels[tuple(where)].astype(np.int64)
    theirs[theirs == 0] = np.iinfo(np.int64).max
    out: np.ndarray = (near_own < near_other) | ((near_own == near_other) & (value < theirs))
    return out
