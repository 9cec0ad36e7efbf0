"""The iso level: given, from a HU preset, or automatic (Otsu, placed strictly between its two classes).

Also recognises integer stacks that store CT as HU + 1024 (air near 0, soft tissue near 1024), where Otsu's level
is a skin surface, so that the caller can say so and suggest the bone preset with ``hu_offset`` 1024.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from engine.errors import EmptySurfaceError, InputError
from engine.params import ISO_PRESETS_HU, ReconParams
from engine.types import Volume

# samples looked at for the automatic level and the histogram check
_SAMPLE_VOXELS = 4_000_000


def hu_offset(volume: Volume, params: ReconParams) -> float | None:
    """How stored values relate to HU: 0 for HU data, ``iso.hu_offset`` for stacks of HU + offset, else None."""
    if volume.units == "HU":
        return 0.0
    return params.iso.hu_offset


def _sample(data: npt.NDArray[Any]) -> npt.NDArray[Any]:
    step = max(1, round((data.size / _SAMPLE_VOXELS) ** (1 / 3)))
    return data[::step, ::step, ::step]


def otsu_level(sample: npt.NDArray[Any]) -> float:
    """Otsu's threshold, moved to the midpoint between the largest sample of the lower class and the smallest of
    the upper one, so that the level lies strictly between the classes (127.5 on 0/255 data, where Otsu's own
    value 0 would put every sample at or above the level, and leave no surface).

    Raises:
        EmptySurfaceError: the samples are constant.
    """
    from skimage.filters import threshold_otsu

    flat = np.asarray(sample).ravel()
    lo, hi = flat.min(), flat.max()
    if lo == hi:
        raise EmptySurfaceError(f"the volume is constant ({lo}): there is no surface to build")
    t = float(threshold_otsu(flat))
    below, above = flat[flat <= t], flat[flat > t]
    if below.size == 0 or above.size == 0:  # cannot happen for a non-constant sample, but stay inside the range
        return float((float(lo) + float(hi)) / 2)
    return (float(below.max()) + float(above.min())) / 2


def hu1024_hint(volume: Volume, sample: npt.NDArray[Any] | None = None) -> str | None:
    """A sentence when an integer stack's histogram looks like CT stored as HU + 1024, else None.

    The signs: no negative values, at least 5 % of the samples at air (stored <= 200, i.e. <= -824 HU) and the
    most common value of the rest within soft tissue (stored 924..1124, i.e. -100..+100 HU).
    """
    if volume.units == "HU" or volume.data.dtype.kind not in "iu":
        return None
    s = np.asarray(_sample(volume.data) if sample is None else sample).ravel()
    if s.size == 0 or int(s.min()) < 0 or int(s.max()) < 1324:
        return None
    air = np.count_nonzero(s <= 200) / s.size
    rest = s[(s > 200) & (s < 3000)]
    if air < 0.05 or rest.size < 0.05 * s.size:
        return None
    counts, edges = np.histogram(rest, bins=np.arange(200, 3001, 25))
    mode = float(edges[int(np.argmax(counts))]) + 12.5
    if not 924 <= mode <= 1124:
        return None
    return (
        f"the histogram looks like CT stored as HU + 1024 (air near 0, soft tissue near {mode:.0f}): an automatic "
        "level there is a skin surface; for bone give --preset bone --hu-offset 1024 (job params: "
        '"preset": "bone", "hu_offset": 1024), or --iso in the stack\'s units'
    )


def choose_level(volume: Volume, params: ReconParams) -> tuple[float, str]:
    """The iso level in the volume's units and how it was chosen.

    Given ``iso`` wins; else a preset (``bone`` by default for HU data) converted with ``hu_offset``; else Otsu's
    level between the two classes (see :func:`otsu_level`), with the HU + 1024 hint appended when it applies.

    Raises:
        InputError: a HU preset on data not in HU without ``hu_offset``.
        EmptySurfaceError: the volume is constant.
    """
    iso = params.iso
    if iso.iso is not None:
        return float(iso.iso), "given"
    preset = iso.preset
    if preset is None and volume.units == "HU":
        preset = "bone"
    if preset is not None:
        hu = ISO_PRESETS_HU[preset]
        if volume.units == "HU":
            return hu, f"preset {preset} ({hu:g} HU)"
        if iso.hu_offset is not None:
            return hu + iso.hu_offset, f"preset {preset} ({hu:g} HU + offset {iso.hu_offset:g})"
        raise InputError(
            f"preset '{preset}' is in HU but this volume is not calibrated in HU: give --iso in its units, "
            "or --hu-offset if it stores HU plus an offset (1024 for most PNG exports)"
        )
    sample = _sample(volume.data)
    level = otsu_level(sample)
    hint = hu1024_hint(volume, sample)
    return level, "Otsu (midway between its two classes)" + (f"; note: {hint}" if hint else "")
