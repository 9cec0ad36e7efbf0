"""Resampling of a DICOM series with uneven gaps or a gantry tilt onto a regular, orthogonal grid."""

from __future__ import annotations

import math

import numpy as np

from engine.io.archive import InputLimits


def regularise(
    data: np.ndarray,
    d: np.ndarray,
    ox: np.ndarray,
    oy: np.ndarray,
    sz: float,
    fill: float,
    limits: InputLimits,
    label: str,
) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Resample slices at normal positions ``d`` (mm), shifted in-plane by ``oy``/``ox`` pixels, onto a regular grid.

    Each slice is first shifted onto a canvas large enough for all of them (shear correction of a gantry tilt),
    then the canvases are interpolated linearly along the normal every ``sz`` mm from ``d[0]``. Integer data stay
    integer (rounded). Returns the volume, its z step and the (y, x) pixel offset of the canvas origin from
    slice 0's first pixel.
    """
    from scipy import ndimage

    n, rows, cols = data.shape
    off = (float(oy.min()) if np.ptp(oy) > 0.05 else 0.0, float(ox.min()) if np.ptp(ox) > 0.05 else 0.0)
    ox = ox - off[1] if np.ptp(ox) > 0.05 else np.zeros(n)
    oy = oy - off[0] if np.ptp(oy) > 0.05 else np.zeros(n)
    ny, nx = rows + math.ceil(float(oy.max()) - 1e-6), cols + math.ceil(float(ox.max()) - 1e-6)
    rel = d - d[0]
    nz = math.floor(float(rel[-1]) / sz + 1e-6) + 1
    limits.check_voxels((nz, ny, nx), f"{label} after resampling to a regular grid")
    out = np.empty((nz, ny, nx), dtype=data.dtype)
    cache: dict[int, np.ndarray] = {}

    def shifted(k: int) -> np.ndarray:
        if k not in cache:
            if len(cache) >= 2:
                cache.pop(min(cache))
            canvas = np.full((ny, nx), fill, dtype=np.float32)
            canvas[:rows, :cols] = data[k]
            if oy[k] or ox[k]:
                canvas = ndimage.shift(canvas, (oy[k], ox[k]), order=1, mode="constant", cval=fill, prefilter=False)
            cache[k] = canvas
        return cache[k]

    for m in range(nz):
        z = m * sz
        k = min(max(int(np.searchsorted(rel, z, side="right")) - 1, 0), n - 2) if n > 1 else 0
        w = min(max((z - rel[k]) / (rel[k + 1] - rel[k]), 0.0), 1.0) if n > 1 else 0.0
        sl = shifted(k) if w < 1e-4 else shifted(k + 1) if w > 1 - 1e-4 else (1 - w) * shifted(k) + w * shifted(k + 1)
        if out.dtype.kind in "iu":
            info = np.iinfo(out.dtype)
            out[m] = np.clip(np.rint(sl), info.min, info.max)
        else:
            out[m] = sl
    return out, sz, off
