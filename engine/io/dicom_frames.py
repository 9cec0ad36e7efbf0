"""Multi-frame DICOM images (Enhanced CT, Legacy Converted Enhanced CT, other enhanced IODs) read frame by frame.

An enhanced image keeps what single-frame images hold at the top level in functional groups: a macro sequence in
the Shared Functional Groups Sequence (one item) holds for every frame, one in the frame's item of the Per-frame
Functional Groups Sequence for that frame only; either may hold each macro, and the per-frame one wins. Read here,
per frame:

- Plane Position (Patient) (``PlanePositionSequence`` > ImagePositionPatient);
- Plane Orientation (Patient) (``PlaneOrientationSequence`` > ImageOrientationPatient);
- Pixel Measures (``PixelMeasuresSequence`` > PixelSpacing, SpacingBetweenSlices, SliceThickness);
- Pixel Value Transformation (``PixelValueTransformationSequence`` > RescaleSlope, RescaleIntercept);
- CT Acquisition Details (``CTAcquisitionDetailsSequence`` > GantryDetectorTilt).

Where no functional group holds an attribute, the top-level one stands in (some writers leave Pixel Spacing or the
rescale there), except the position of an image of several frames: one position cannot place them all. The frames
become slices like single-frame images (``engine.io.dicom``), so the order comes from the positions, never from
the order of the frames in the file or from the Dimension Index; several files of one series (split stacks) and
several stacks or temporal positions in one file go through the same geometry checks (a repeated position is
refused there, naming the frames).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from engine.io.archive import Member

PER_FRAME = "PerFrameFunctionalGroupsSequence"
SEG_CLASSES = ("1.2.840.10008.5.1.4.1.1.66.4", "1.2.840.10008.5.1.4.1.1.66.7")  # Segmentation, Label Map Segmentation
SHARED = "SharedFunctionalGroupsSequence"
_ENHANCED = "an Enhanced or Legacy Converted Enhanced image with per-frame functional groups"


class FrameError(ValueError):
    """A multi-frame image whose frames cannot be placed (the message names the file and what is missing).

    Internal to the loader, outside ``engine.errors``' tree on purpose: it never leaves the engine. Only
    :func:`frames` raises it, and its one caller, ``engine.io.dicom._frames``, catches it and marks the image an
    unusable slice with this message, which becomes an ``InputError`` when that image's series is the one loaded
    (as for any unreadable image).
    """


@dataclass(frozen=True)
class Frame:
    """One frame's geometry and rescale, as a single-frame image's header would give them.

    Attributes:
        index: the frame's number in the file, from 0 (DICOM counts from 1: see :func:`frame_label`).
        ipp, iop: ImagePositionPatient (3) and ImageOrientationPatient (6), or None where absent or not finite.
        pixel_spacing: (row, column) spacing in mm, or None.
        thickness: SpacingBetweenSlices, else SliceThickness, in mm, or None.
        slope, intercept: the rescale to output units (HU for CT).
        gantry_tilt_deg: the Gantry/Detector Tilt (informative: the geometry comes from the positions).
        nonfinite: the geometry attributes present but holding NaN or an infinity.
    """

    index: int
    ipp: np.ndarray | None
    iop: np.ndarray | None
    pixel_spacing: tuple[float, float] | None
    thickness: float | None
    slope: float
    intercept: float
    gantry_tilt_deg: float
    nonfinite: tuple[str, ...] = ()


def frame_count(ds: Any) -> int:
    """NumberOfFrames (1 where absent, empty or not a positive number)."""
    try:
        n = int(ds.get("NumberOfFrames", 1) or 1)
    except (TypeError, ValueError):
        return 1
    return max(n, 1)


def is_multiframe(ds: Any) -> bool:
    """Whether a data set is read frame by frame: several frames, or functional groups (an enhanced image)."""
    return frame_count(ds) > 1 or PER_FRAME in ds or SHARED in ds


def frame_label(name: str, index: int) -> str:
    """How messages name frame ``index`` (from 0) of the file ``name``: DICOM's frame number, from 1."""
    return f"{name} [frame {index + 1}]"


def frame_member(member: Member, index: int) -> Member:
    """``member`` under the name of one of its frames (the same bytes: for messages and the geometry checks)."""
    return replace(member, name=frame_label(member.name, index))


def frames(ds: Any, name: str) -> list[Frame]:
    """Every frame of a multi-frame data set, in the file's order.

    Raises:
        FrameError: a Segmentation (its frames are segments' masks, not slices), no functional groups, their count
            differs from NumberOfFrames, or a frame has no Plane Position (Patient) or Plane Orientation (Patient).
    """
    n = frame_count(ds)
    if str(ds.get("SOPClassUID", "")) in SEG_CLASSES or str(ds.get("Modality", "")).upper() == "SEG":
        seq = ds.get("ReferencedSeriesSequence")
        ref = f" of series {seq[0].get('SeriesInstanceUID', '?')}" if seq else ""
        raise FrameError(
            f"{name} is a DICOM Segmentation (SEG){ref}: a label map, not a scan's images; read it as labels "
            "(with the CT series it was drawn on, or alone on its own grid), not as a scan"
        )
    per_frame = list(ds.get(PER_FRAME) or ())
    shared_items = list(ds.get(SHARED) or ())
    shared = shared_items[0] if shared_items else None
    if not per_frame and shared is None:
        raise FrameError(
            f"{name} is a multi-frame DICOM ({n} frames) without functional groups, so where its frames lie is "
            f"unknown; expected {_ENHANCED}, or single-frame images (export the series as one image per file)"
        )
    if per_frame and len(per_frame) != n:
        raise FrameError(
            f"{name} declares {n} frames (NumberOfFrames) but holds {len(per_frame)} items of per-frame "
            "functional groups: the file is damaged; export it again"
        )
    return [_frame(ds, per_frame[i] if per_frame else None, shared, i, n, name) for i in range(n)]


def _macro(own: Any, shared: Any, keyword: str) -> Any:
    """The first item of a functional group macro: the frame's own, else the shared one, else None."""
    for group in (own, shared):
        if group is not None:
            items = group.get(keyword)
            if items:
                return items[0]
    return None


def _value(item: Any, top: Any, keyword: str, fallback: bool = True) -> Any:
    """An attribute of a macro item, or of the top level data set where the macro does not hold it."""
    value = item.get(keyword) if item is not None else None
    if value in (None, "") and fallback:
        value = top.get(keyword)
    return None if value in (None, "") else value


def _numbers(value: Any, n: int) -> tuple[np.ndarray | None, bool]:
    """``value`` as ``n`` finite floats, or None; also whether it holds NaN or an infinity."""
    if value is None:
        return None, False
    try:
        arr = np.array([float(v) for v in (value if n > 1 else [value])], dtype=np.float64)
    except (TypeError, ValueError):
        return None, False
    if not np.all(np.isfinite(arr)):
        return None, True
    return (arr if arr.size == n else None), False


def _frame(ds: Any, own: Any, shared: Any, i: int, n: int, name: str) -> Frame:
    position = _macro(own, shared, "PlanePositionSequence")
    orientation = _macro(own, shared, "PlaneOrientationSequence")
    measures = _macro(own, shared, "PixelMeasuresSequence")
    rescale = _macro(own, shared, "PixelValueTransformationSequence")
    details = _macro(own, shared, "CTAcquisitionDetailsSequence")
    nonfinite = []
    ipp, bad = _numbers(_value(position, ds, "ImagePositionPatient", fallback=n == 1), 3)
    if bad:
        nonfinite.append("ImagePositionPatient")
    iop, bad = _numbers(_value(orientation, ds, "ImageOrientationPatient"), 6)
    if bad:
        nonfinite.append("ImageOrientationPatient")
    ps, bad = _numbers(_value(measures, ds, "PixelSpacing"), 2)
    if bad:
        nonfinite.append("PixelSpacing")
    thick = None
    for keyword in ("SpacingBetweenSlices", "SliceThickness"):
        value, bad = _numbers(_value(measures, ds, keyword), 1)
        if bad:
            nonfinite.append(keyword)
        if thick is None and value is not None and value[0] > 0:
            thick = float(value[0])
    for what, arr, keyword, macro in (
        ("Plane Position (Patient)", ipp, "ImagePositionPatient", "PlanePositionSequence"),
        ("Plane Orientation (Patient)", iop, "ImageOrientationPatient", "PlaneOrientationSequence"),
    ):
        if arr is None and keyword not in nonfinite:
            raise FrameError(
                f"{frame_label(name, i)} has no {what} ({keyword} in a {macro} of its per-frame or the shared "
                f"functional groups), so where its pixels lie is unknown; expected {_ENHANCED} (re-export the "
                "series from the scanner or PACS)"
            )
    slope = _number(_value(rescale, ds, "RescaleSlope"), 1.0, frame_label(name, i), "RescaleSlope")
    intercept = _number(_value(rescale, ds, "RescaleIntercept"), 0.0, frame_label(name, i), "RescaleIntercept")
    tilt = 0.0
    with contextlib.suppress(TypeError, ValueError):
        tilt = float(_value(details, ds, "GantryDetectorTilt") or 0.0)
    return Frame(
        index=i,
        ipp=ipp,
        iop=iop,
        pixel_spacing=(float(ps[0]), float(ps[1])) if ps is not None and np.all(ps > 0) else None,
        thickness=thick,
        slope=slope if slope != 0 else 1.0,  # a zero slope is a writer's placeholder, as for single-frame images
        intercept=intercept,
        gantry_tilt_deg=tilt if math.isfinite(tilt) else 0.0,
        nonfinite=tuple(nonfinite),
    )


def _number(value: Any, default: float, label: str, keyword: str) -> float:
    if value is None:
        return default
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise FrameError(f"{label} has a {keyword} of {str(value)[:40]!r}, not a number") from None
    if not math.isfinite(out):
        raise FrameError(f"{label} has a {keyword} of {out}, so its values are unknown")
    return out
