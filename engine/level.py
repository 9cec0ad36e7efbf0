"""The iso level: given, from a HU preset, or automatic; and the checks that say when a model is not bone.

The automatic level (neither ``iso`` nor ``preset``):

* HU data (DICOM CT): the bone preset (300 HU);
* a stack that stores CT as HU + an offset (``detect_hu_offset``: air near the offset - 1000, soft tissue near the
  offset; PNG exports of HU + 1024, raw scanner values, int16 HU without a label, int16 HU shifted into uint16), or
  one given ``hu_offset``: the bone preset at that offset, said so in ``chosen_by``; the body mask then runs as for
  DICOM;
* anything else (micro-CT, segmented or binary stacks, unknown units): Otsu's level, placed strictly between its two
  classes.

``skin_warning`` flags a model that still looks like a skin surface (it fills most of the body outline, or it holds
a second, brighter class inside); the pipeline puts it in the report's ``warnings`` (``engine.job.plans``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.errors import EmptySurfaceError, InputError
from engine.params import ISO_PRESETS_HU, ReconParams, spacing_order_warning
from engine.report import IsoLevel
from engine.types import Volume

# samples looked at for the automatic level and the histogram checks
_SAMPLE_VOXELS = 4_000_000
# the offsets a stack of HU + offset is recognised with: 1024 (PNG/TIFF exports, DICOM stored values with a
# RescaleIntercept of -1024, raw scanner values; an offset of 1000 reads the same within 24 HU), 0 (HU in an
# unlabelled .npy or TIFF) and 32768 (signed HU shifted into uint16)
HU_OFFSETS = (1024.0, 0.0, 32768.0)
# a level at or above this many HU cannot be a skin surface (soft tissue is below +100 HU): no skin check
_SKIN_CHECK_BELOW_HU = 150.0
# a model that fills at least this share of the body outline is a skin surface (bone fills 4-25 % of it on the
# real head and pelvis scans, a skin surface 94-98 %)
SKIN_BODY_SHARE = 0.6


@dataclass(frozen=True)
class HuOffset:
    """A stack recognised as CT stored as HU + ``offset``: where its air and soft-tissue peaks are (stored values)
    and their shares of the samples."""

    offset: float
    air: float
    tissue: float
    air_share: float
    tissue_share: float

    def describe(self) -> str:
        stored = "CT in HU" if self.offset == 0 else f"CT stored as HU + {self.offset:g}"
        return f"{stored} detected (air near {self.air:.0f}, soft tissue near {self.tissue:.0f})"

    def to_dict(self) -> dict[str, float]:
        return {
            "offset": self.offset,
            "air_peak": round(self.air, 1),
            "tissue_peak": round(self.tissue, 1),
            "air_share": round(self.air_share, 4),
            "tissue_share": round(self.tissue_share, 4),
        }


@dataclass(frozen=True)
class LevelChoice:
    """The iso level in the volume's units, how it was chosen, and how stored values relate to HU.

    ``hu_offset``: stored value = HU + this (0 for HU data); None when the units are unknown (the body mask is then
    skipped). ``hu_offset_from``: "HU data", "given", "detected" or None. ``detected``: the histogram's evidence when
    the offset was detected.
    """

    value: float
    how: str
    hu_offset: float | None
    hu_offset_from: str | None = None
    detected: HuOffset | None = None

    def report(self, units: str) -> IsoLevel:
        """The report's ``iso_level`` entry."""
        out: IsoLevel = {
            "value": self.value,
            "units": units,
            "chosen_by": self.how,
            "hu_offset": self.hu_offset,
            "hu_offset_from": self.hu_offset_from,
        }
        if self.detected is not None:
            out["hu_offset_detected"] = self.detected.to_dict()
        return out


def _strided(data: npt.NDArray[Any], step: int) -> npt.NDArray[Any]:
    """``data[::step, ::step, ::step]``; from a volume read slab by slab (``engine.io.slabs.SlabSource``, out of core)
    the same samples, read plane by plane."""
    if isinstance(data, np.ndarray):
        return data[::step, ::step, ::step]
    sample: npt.NDArray[Any] = data.strided(step)
    return sample


def _sample(data: npt.NDArray[Any]) -> npt.NDArray[Any]:
    step = max(1, round((data.size / _SAMPLE_VOXELS) ** (1 / 3)))
    return _strided(data, step)


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


def _peak(values: npt.NDArray[np.float64], lo: float, hi: float, smooth: int = 5) -> float:
    """The centre of the most populated 10-unit bin of ``values`` in [lo, hi), the counts smoothed over ``smooth``
    bins."""
    counts, edges = np.histogram(values, bins=np.arange(lo, hi + 10, 10.0))
    if smooth > 1:
        counts = np.convolve(counts, np.ones(smooth), mode="same")
    i = int(np.argmax(counts))
    return float(edges[i] + 5.0)


def detect_hu_offset(volume: Volume, sample: npt.NDArray[Any] | None = None) -> HuOffset | None:
    """Whether a volume not labelled HU stores CT as HU + an offset (one of ``HU_OFFSETS``), from its histogram.

    The signs, for an offset o (stored values): at least 3 % of the samples are air (o - 1100 .. o - 850, i.e.
    -1100 .. -850 HU: air and the padding of a clipped export); the most common value of the rest (o - 850 ..
    o + 3100) is soft tissue (o - 150 .. o + 120), which holds at least 3 % of all samples and 30 % of the rest;
    almost nothing lies beyond CT's range (> o + 4000); and the stack reaches the bone level (o + 300). Binary and
    segmented stacks (no soft-tissue peak), micro-CT (no air peak 1000 below a tissue peak) and stacks without
    bone-level values are not taken for CT.

    Returns:
        The offset and its evidence, or None (HU data, or no offset fits).
    """
    if volume.units == "HU" or volume.data.dtype.kind not in "iuf":
        return None
    s = np.asarray(_sample(volume.data) if sample is None else sample).ravel()
    s = s[:: max(1, s.size // 1_000_000)]  # a million samples tell the peaks apart
    if s.dtype.kind == "f":
        s = s[np.isfinite(s)]
    if s.size < 64:
        return None
    s = s.astype(np.float64, copy=False)
    n, top = s.size, float(s.max())
    for o in HU_OFFSETS:
        if top < o + 300:
            continue
        air = s[(s >= o - 1100) & (s <= o - 850)]
        rest = s[(s > o - 850) & (s < o + 3100)]
        if air.size < 0.03 * n or rest.size < 0.03 * n or np.count_nonzero(s > o + 4000) > 0.005 * n:
            continue
        tissue_peak = _peak(rest, o - 850, o + 3100)
        tissue = np.count_nonzero((s >= o - 200) & (s <= o + 150))
        if not (o - 150 <= tissue_peak <= o + 120) or tissue < 0.03 * n or tissue < 0.3 * rest.size:
            continue
        return HuOffset(o, _peak(air, o - 1100, o - 850, smooth=1), tissue_peak, air.size / n, tissue / n)
    return None


def resolve_level(volume: Volume, params: ReconParams) -> LevelChoice:
    """The iso level in the volume's units, how it was chosen and the HU offset (see the module docstring).

    A given ``iso`` wins (the stack's units; nothing is detected). Else a preset, or the bone preset when the
    offset is known (HU data, ``hu_offset`` given, or detected), converted with the offset; else Otsu's level.

    Raises:
        InputError: a HU preset on data whose offset is neither given nor detected.
        EmptySurfaceError: the volume is constant.
    """
    iso = params.iso
    if volume.units == "HU":
        offset: float | None = 0.0
        source: str | None = "HU data"
    elif iso.hu_offset is not None:
        offset, source = float(iso.hu_offset), "given"
    else:
        offset, source = None, None
    if iso.iso is not None:
        return LevelChoice(float(iso.iso), "given", offset, source)
    sample = None
    found = None
    if offset is None:
        sample = _sample(volume.data)
        found = detect_hu_offset(volume, sample)
        if found is not None:
            offset, source = found.offset, "detected"
    preset = iso.preset
    automatic = preset is None and offset is not None
    if automatic:
        preset = "bone"
    if preset is not None:
        hu = ISO_PRESETS_HU[preset]
        if offset is None:
            raise InputError(
                f"preset '{preset}' is in HU, but this volume is not calibrated in HU and its histogram does not look "
                "like CT stored as HU + an offset (air near offset - 1000, soft tissue near the offset): give "
                "--hu-offset (job params hu_offset) if it stores HU + an offset (1024 for most PNG exports), or "
                "--iso in its units"
            )
        level = hu + offset
        if found is not None:
            name = "bone preset" if automatic else f"preset {preset}"
            how = f"{name} ({hu:g} HU = {level:g} stored), {found.describe()}"
        elif source == "HU data":
            how = f"preset {preset} ({hu:g} HU)"
        else:
            how = f"preset {preset} ({hu:g} HU + offset {offset:g})"
        return LevelChoice(level, how, offset, source, found)
    sample = _sample(volume.data) if sample is None else sample
    return LevelChoice(otsu_level(sample), "Otsu (midway between its two classes)", None, None)


def choose_level(volume: Volume, params: ReconParams) -> tuple[float, str]:
    """The iso level in the volume's units and how it was chosen (``resolve_level``)."""
    choice = resolve_level(volume, params)
    return choice.value, choice.how


def hu_offset(volume: Volume, params: ReconParams) -> float | None:
    """How stored values relate to HU: 0 for HU data, ``iso.hu_offset`` when given, the detected offset when the
    level is not given (``resolve_level``), else None."""
    return resolve_level(volume, params).hu_offset


SKIN_SAMPLE_VOXELS = 2_000_000  # the skin check's strided sample: its labelling is single-threaded host work per job


def _subsample(data: npt.NDArray[Any], most: int = 8_000_000) -> npt.NDArray[Any]:
    step = max(1, int(np.ceil((data.size / most) ** (1 / 3))))
    return _strided(data, step)


def skin_warning(volume: Volume, level: float, offset: float | None) -> dict[str, Any] | None:
    """A warning (``{"code": "looks_like_skin", "message": ...}`` plus the measure) when the surface at ``level``
    looks like skin rather than bone, else None.

    With a known HU offset: the voxels at or above the level fill at least ``SKIN_BODY_SHARE`` of the body outline
    (voxels at or above -500 HU, holes filled per slice). A level at or above +150 HU is never checked (soft tissue
    lies below it). With unknown units: the voxels at or above the level hold two well separated classes, the
    brighter one a minority (soft tissue with bone inside). Binary and segmented stacks are never flagged.
    """
    data = _subsample(volume.data, SKIN_SAMPLE_VOXELS)
    model = data >= level
    n_model = int(np.count_nonzero(model))
    if n_model == 0:
        return None
    if offset is not None:
        if level >= offset + _SKIN_CHECK_BELOW_HU:
            return None
        from engine.volume.bodymask import fill_holes_in_plane

        body = fill_holes_in_plane(data >= offset - 500.0)  # the outline's holes filled slice by slice
        n_body = int(np.count_nonzero(body))
        share = float(np.count_nonzero(model & body)) / n_body if n_body else 0.0
        if share < SKIN_BODY_SHARE:
            return None
        return {
            "code": "looks_like_skin",
            "message": (
                f"the model looks like a skin surface, not bone: at level {level:g} ({level - offset:g} HU) it "
                f"fills {share:.0%} of the body outline (a bone model fills far less); for bone use the bone "
                f"preset ({ISO_PRESETS_HU['bone']:g} HU)"
            ),
            "body_share": round(share, 3),
        }
    if np.unique(data[model][:: max(1, n_model // 100_000)]).size <= 2:  # binary or segmented
        return None
    from scipy import ndimage as ndi

    labels, n = ndi.label(model, structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    sizes[0] = 0
    values = data[labels == int(np.argmax(sizes))].astype(np.float64)  # the largest piece
    from skimage.filters import threshold_otsu

    t = float(threshold_otsu(values[:: max(1, values.size // 2_000_000)]))
    lo, hi = values[values <= t], values[values > t]
    if lo.size == 0 or hi.size == 0:
        return None
    upper = hi.size / values.size
    pooled = np.sqrt((lo.var() * lo.size + hi.var() * hi.size) / values.size)
    separation = float((hi.mean() - lo.mean()) / pooled) if pooled > 0 else float("inf")
    if separation < 4.5 or not 0.01 <= upper <= 0.35:
        return None
    return {
        "code": "looks_like_skin",
        "message": (
            f"the model may be an outer (skin) surface, not bone: at level {level:g} it encloses a brighter class "
            f"({upper:.0%} of it, around {hi.mean():.0f} against {lo.mean():.0f}); for bone give --iso near "
            f"{t:.0f} (job params iso), or --preset bone --hu-offset if the stack stores HU + an offset"
        ),
        "brighter_share": round(upper, 3),
        "separation": round(separation, 2),
    }


def hu1024_hint(volume: Volume) -> dict[str, Any] | None:
    """A warning when a stack that ``detect_hu_offset`` did not take for CT still looks like HU + 1024 by a looser
    sign (the hint of earlier releases): no negative values, at least 5 % of the samples at air (stored <= 200) and
    the most common value of the rest within soft tissue (924..1124) though too little of it to be sure (a hollow
    head phantom). The level stays Otsu's; the warning says how to ask for bone."""
    if volume.units == "HU" or volume.data.dtype.kind not in "iu":
        return None
    s = np.asarray(_sample(volume.data)).ravel()
    s = s[:: max(1, s.size // 1_000_000)]
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
    return {
        "code": "maybe_hu_offset",
        "message": (
            f"the histogram looks somewhat like CT stored as HU + 1024 (air near 0, a peak near {mode:.0f}), but "
            "with too little soft tissue to be sure, so the level is Otsu's; for bone give --preset bone "
            '--hu-offset 1024 (job params "preset": "bone", "hu_offset": 1024), or --iso in the stack\'s units'
        ),
    }


def model_warnings(volume: Volume, choice: LevelChoice) -> list[dict[str, Any]]:
    """The report's ``warnings`` about a volume about to be meshed at ``choice``, each ``{"code": ..., "message":
    ...}`` plus its measures:

    * ``voxel_size_order``: a voxel size the caller gave (to ``load_volume``, or in a ``Volume`` made by hand; not
      one read from DICOM headers or TIFF tags) in an order that looks swapped (``spacing_order_warning``);
    * ``looks_like_skin``: the level makes a skin surface (``skin_warning``);
    * ``maybe_hu_offset``: an automatic Otsu level on a stack that may be HU + 1024 after all (``hu1024_hint``).
    """
    out: list[dict[str, Any]] = []
    given = volume.source.get("spacing_from", "dicom" if volume.source.get("format") == "dicom" else "call")
    if given == "call":  # the caller's (a loader's call, or a Volume made by hand), not a header's
        order = spacing_order_warning(volume.spacing_zyx_mm)
        if order is not None:
            out.append(order)
    skin = skin_warning(volume, choice.value, choice.hu_offset)
    if skin is not None:
        out.append(skin)
    if choice.how.startswith("Otsu"):
        maybe = hu1024_hint(volume)
        if maybe is not None:
            out.append(maybe)
    return out
