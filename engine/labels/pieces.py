"""What a label job keeps: a region of interest cropped before anything runs (``crop_roi``), the segments asked for
(``select_segments``: by number or name), and, from a CT alone, the N largest bone pieces as a label map of
separately named parts (``bone_pieces``: fragments of a fracture, the two femurs of a pelvis scan), meshed like any
label map (``engine.labels.parts.label_models``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import TypeVar

import numpy as np

from engine.errors import EmptySurfaceError, InputError
from engine.io.labelmaps import LabelVolume, Segment, palette
from engine.params import OrientParams, PiecesParams, ReconParams, RoiParams
from engine.types import Volume

__all__ = ["bone_pieces", "crop_roi", "roi_slices", "select_segments"]

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
    return dataclasses.replace(grid, data=np.ascontiguousarray(grid.data[sl]), origin_mm=origin, source=source)


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


def bone_pieces(volume: Volume, params: ReconParams | None = None, pieces: PiecesParams | None = None) -> LabelVolume:
    """The ``pieces.count`` largest connected pieces of the bone (voxels at or above the pipeline's level, inside
    the body for HU data as the pipeline keeps them) as a label map: value 1 the largest, named ``piece_1``...

    Raises:
        EmptySurfaceError: no bone voxel at the level (or none in a piece of ``min_voxels``).
    """
    from scipy import ndimage

    from engine.level import resolve_level

    params = params or ReconParams()
    pieces = pieces or PiecesParams()
    choice = resolve_level(volume, params)
    if params.body is not None:
        from engine.volume.bodymask import isolate_bone

        volume, _ = isolate_bone(volume, choice.value, params.body, choice.hu_offset)
    mask = volume.data >= choice.value
    comp, n = ndimage.label(mask, structure=_structure(pieces.connectivity))
    sizes = np.bincount(comp.reshape(-1))[1:] if n else np.zeros(0, np.int64)
    order = [int(i) + 1 for i in np.argsort(-sizes, kind="stable") if sizes[i] >= pieces.min_voxels][: pieces.count]
    if not order:
        raise EmptySurfaceError(
            f"no bone piece of at least {pieces.min_voxels} voxels at level {choice.value:g} {volume.units}"
        )
    lut = np.zeros(n + 1, dtype=np.uint16 if len(order) > 255 else np.uint8)
    lut[order] = np.arange(1, len(order) + 1)
    labels = lut[comp]
    segments = tuple(Segment(i, f"piece_{i}", palette(i - 1)) for i in range(1, len(order) + 1))
    source = {
        **volume.source,
        "format": "pieces",
        "level": choice.value,
        "pieces_found": int(n),
        "pieces_kept": len(order),
        "piece_voxels": [int(sizes[i - 1]) for i in order],
    }
    return LabelVolume(
        labels, volume.spacing_zyx_mm, volume.origin_mm, volume.direction, segments, source, volume.patient_frame
    )
