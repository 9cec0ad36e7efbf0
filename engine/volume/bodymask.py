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
import time
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
    """
    from scipy import ndimage as ndi

    tissue = (data >= outline) & (data < level)
    body = np.empty_like(tissue)
    for z in range(tissue.shape[0]):
        body[z] = ndi.binary_fill_holes(tissue[z])
    if thin_radius_mm is not None and body.any():
        body = _without_thin_parts(body, thin_radius_mm, min(spacing_zyx_mm[1:]))
    if dilate_mm > 0:
        for z in range(body.shape[0]):
            body[z] = ndi.distance_transform_edt(~body[z], sampling=spacing_zyx_mm[1:]) <= dilate_mm
    return body


def _without_thin_parts(body: np.ndarray, radius_mm: float, pixel_mm: float) -> np.ndarray:
    """``body`` without its thin in-plane parts (``body_outline``): a part is thick when something of it survives
    an in-plane erosion by the radius (city-block steps of a pixel, so a disc of that radius survives). Slice by
    slice, so that the labels take a slice's memory, not the volume's."""
    from scipy import ndimage as ndi

    cross = ndi.generate_binary_structure(2, 1)
    steps = max(1, round(radius_mm / pixel_mm))
    out = body
    for z in range(body.shape[0]):
        if not body[z].any():
            continue
        thick = ndi.binary_erosion(body[z], structure=cross, iterations=steps)
        if not thick.any():
            continue  # only thin parts in this slice: all kept
        parts, n = ndi.label(body[z], structure=cross)
        keep = np.bincount(parts[thick], minlength=n + 1) > 0
        keep[0] = False
        if keep[1:].all():
            continue
        if out is body:
            out = body.copy()
        out[z] = keep[parts]
    return out


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
    from scipy import ndimage as ndi

    t0 = time.perf_counter()
    data = volume.data
    voxel_mm3 = float(np.prod(volume.spacing_zyx_mm))
    bone = data >= level
    labels, n = ndi.label(bone, structure=np.ones((3, 3, 3), bool))
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
    flat = labels.ravel()
    size = np.bincount(flat, minlength=n + 1)
    inside = np.bincount(flat, weights=body.ravel(), minlength=n + 1)
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
    out[drop[labels]] = data.min()
    return dataclasses.replace(volume, data=out), {**info, "seconds": time.perf_counter() - t0}
