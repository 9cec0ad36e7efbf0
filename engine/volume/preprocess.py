"""Stage: the paper's optional per-slice preprocessing (threshold, area opening, Canny edges) and a crop box.

Runs on the host with scikit-image, before the volume is uploaded.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from engine.errors import InputError
from engine.params import PreprocessParams
from engine.types import Volume


def crop_volume(volume: Volume, crop_zyx_mm: tuple[tuple[float, float], ...]) -> Volume:
    """Keep the samples inside a (z, y, x) box given in mm from the first sample (inclusive)."""
    slices = []
    for axis, ((lo, hi), step) in enumerate(zip(crop_zyx_mm, volume.spacing_zyx_mm, strict=True)):
        n = volume.data.shape[axis]
        i0 = max(0, math.ceil(lo / step - 1e-9))
        i1 = min(n, math.floor(hi / step + 1e-9) + 1)
        if i1 - i0 < 2:
            raise InputError(
                f"the crop box leaves fewer than 2 samples along {'zyx'[axis]}: {lo}-{hi} mm of a "
                f"{(n - 1) * step:g} mm axis"
            )
        slices.append(slice(i0, i1))
    # the first kept sample, in the volume's frame: origin + direction @ (x, y, z) offset in mm
    offset_xyz = np.array([s.start * d for s, d in zip(slices[::-1], volume.spacing_zyx_mm[::-1], strict=True)])
    shift = np.asarray(volume.direction, dtype=np.float64) @ offset_xyz
    origin = tuple(float(o + v) for o, v in zip(volume.origin_mm, shift, strict=True))
    return dataclasses.replace(volume, data=np.ascontiguousarray(volume.data[tuple(slices)]), origin_mm=origin)


def preprocess_volume(volume: Volume, params: PreprocessParams) -> Volume:
    """Apply the crop, then per slice: threshold, area opening, Canny edges (in that order, each only when set).

    The area opening runs before Canny: it removes bright specks of the (thresholded) slice, whose edges Canny
    would otherwise trace; on an edge map it would only erase short edges.
    """
    if params.crop_zyx_mm is not None:
        volume = crop_volume(volume, params.crop_zyx_mm)
    data = volume.data
    if params.threshold is None and params.canny_sigma is None and params.area_opening_px is None:
        return volume
    from skimage.feature import canny
    from skimage.morphology import area_opening

    out = data.copy()
    low = data.min()
    for z in range(out.shape[0]):
        sl = out[z]
        if params.threshold is not None:
            sl[sl < params.threshold] = low
        if params.area_opening_px is not None:
            sl[...] = area_opening(sl, area_threshold=params.area_opening_px)
        if params.canny_sigma is not None:
            edges = canny(sl.astype(np.float32), sigma=params.canny_sigma)
            sl[...] = np.where(edges, data.max(), low)
    return dataclasses.replace(volume, data=out)
