"""DICOM Segmentation (SEG) in: BINARY, FRACTIONAL and LABELMAP encodings, read with pydicom into one
``engine.io.labelmaps.LabelVolume``.

Segments come from the SegmentSequence (SegmentNumber is the label value, SegmentLabel the name,
RecommendedDisplayCIELabValue the colour, turned into sRGB). Each frame is placed by its Per-frame Plane Position
(ImagePositionPatient): into the referenced CT's grid when that CT is given (``reference``: the frames must lie on
its grid, with its row and column directions), else on the SEG's own grid (its slice positions along the normal of
ImageOrientationPatient; a SEG leaves out empty frames, so missing positions are empty slices). A voxel in two
segments goes to the later one (``source["overlap_voxels"]``).

Errors: ``MissingReferenceError`` (the SEG's referenced series is not the CT given, or not in the folder),
``LabelsOutsideScanError`` (no labelled voxel lands in the CT's grid), ``NotLabelsError`` (not a SEG).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.errors import InputError, LabelsOutsideScanError, MissingReferenceError, NotLabelsError
from engine.io.labelmaps import LabelVolume, Segment, make_label_volume, palette
from engine.types import Volume

__all__ = ["lab_to_srgb", "read_dicom_seg", "read_seg_folder", "referenced_series"]

SEG_CLASSES = ("1.2.840.10008.5.1.4.1.1.66.4", "1.2.840.10008.5.1.4.1.1.66.7")  # Segmentation, Label Map Seg.
_GRID_TOL = 0.05  # frame positions this far (in voxels) from the CT's grid are not on it


@dataclass
class _Frames:
    """The SEG's frames: pixels (F, rows, cols), positions (F, 3) LPS mm, segment number per frame (0: label map)."""

    pixels: np.ndarray
    positions: np.ndarray
    numbers: np.ndarray
    row: np.ndarray
    col: np.ndarray
    spacing_rc: tuple[float, float]
    slice_step: float | None


def lab_to_srgb(dicom_lab: Any) -> tuple[float, float, float]:
    """DICOM's scaled CIELab (0-65535 each; D65 white as in highdicom) as sRGB 0-1, clipped."""
    lab = [float(v) for v in dicom_lab]
    l_star, a_star, b_star = lab[0] / 65535 * 100, lab[1] / 65535 * 255 - 128, lab[2] / 65535 * 255 - 128
    fy = (l_star + 16) / 116
    f = np.array([a_star / 500 + fy, fy, fy - b_star / 200])
    xyz = np.where(f**3 > 0.008856, f**3, (f - 16 / 116) / 7.787) * np.array([0.95047, 1.0, 1.08883])
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    lin = m @ xyz
    rgb = np.where(lin > 0.0031308, 1.055 * np.abs(lin) ** (1 / 2.4) - 0.055, 12.92 * lin)
    r, g, b = (round(float(c), 4) for c in np.clip(rgb, 0, 1))
    return (r, g, b)


def _dataset(path: Path) -> Any:
    import pydicom

    try:
        ds = pydicom.dcmread(str(path))
    except Exception as exc:
        raise NotLabelsError(f"{path.name}: neither a NIfTI, an NRRD nor a DICOM file ({exc})") from None
    if str(ds.get("SOPClassUID", "")) not in SEG_CLASSES and ds.get("Modality") != "SEG":
        raise NotLabelsError(f"{path.name}: a DICOM {ds.get('Modality', '?')} object, not a Segmentation (SEG)")
    return ds


def referenced_series(ds: Any) -> str | None:
    """The SeriesInstanceUID the SEG was drawn on (ReferencedSeriesSequence), if it says."""
    seq = ds.get("ReferencedSeriesSequence")
    return str(seq[0].SeriesInstanceUID) if seq else None


def _segments(ds: Any) -> tuple[Segment, ...]:
    out = []
    for i, item in enumerate(ds.SegmentSequence):
        if int(item.SegmentNumber) <= 0:  # a label map's background segment
            continue
        lab = item.get("RecommendedDisplayCIELabValue")
        colour = lab_to_srgb(lab) if lab is not None else palette(i)
        name = str(item.get("SegmentLabel") or f"segment_{item.SegmentNumber}")
        out.append(Segment(int(item.SegmentNumber), name, colour))
    return tuple(out)


def _frames(ds: Any, label: str) -> _Frames:
    kind = str(ds.get("SegmentationType", "BINARY")).upper()
    pixels = np.asarray(ds.pixel_array)
    pixels = pixels.reshape(-1, int(ds.Rows), int(ds.Columns))
    if kind == "FRACTIONAL":
        pixels = (pixels.astype(np.float32) >= 0.5 * float(ds.get("MaximumFractionalValue", 255))).astype(np.uint8)
    shared = ds.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in ds else None
    per = ds.PerFrameFunctionalGroupsSequence
    if len(per) != len(pixels):
        raise InputError(f"{label}: {len(pixels)} frames but {len(per)} per-frame functional groups")

    def group(item: Any, name: str) -> Any:
        if name in item:
            return item[name].value[0]
        if shared is not None and name in shared:
            return shared[name].value[0]
        raise InputError(f"{label}: no {name} (per-frame or shared): the frames cannot be placed")

    iop = np.asarray(group(per[0], "PlaneOrientationSequence").ImageOrientationPatient, dtype=np.float64)
    measures = group(per[0], "PixelMeasuresSequence")
    spacing = tuple(float(v) for v in measures.PixelSpacing)
    step = measures.get("SpacingBetweenSlices")
    positions = np.array(
        [[float(v) for v in group(f, "PlanePositionSequence").ImagePositionPatient] for f in per], dtype=np.float64
    )
    if kind == "LABELMAP":
        numbers = np.zeros(len(per), dtype=np.int64)
    else:
        numbers = np.array([int(group(f, "SegmentIdentificationSequence").ReferencedSegmentNumber) for f in per])
    return _Frames(pixels, positions, numbers, iop[:3], iop[3:], (spacing[0], spacing[1]), step and float(step))


def _paint(labels: np.ndarray, k: int, j0: int, i0: int, frame: np.ndarray, number: int) -> tuple[int, int]:
    """Frame pixels into slice k at (j0, i0), clipped to the grid; returns (voxels painted, overlaps)."""
    nz, ny, nx = labels.shape
    if not 0 <= k < nz:
        return 0, 0
    r0, c0 = max(0, -j0), max(0, -i0)
    r1, c1 = min(frame.shape[0], ny - j0), min(frame.shape[1], nx - i0)
    if r0 >= r1 or c0 >= c1:
        return 0, 0
    part = frame[r0:r1, c0:c1]
    dst = labels[k, j0 + r0 : j0 + r1, i0 + c0 : i0 + c1]
    values = part.astype(labels.dtype) if number == 0 else np.where(part != 0, number, 0).astype(labels.dtype)
    on = values != 0
    overlaps = int(np.count_nonzero(on & (dst != 0)))
    dst[on] = values[on]
    return int(np.count_nonzero(on)), overlaps


def _into_reference(fr: _Frames, ref: Volume, dtype: Any, label: str) -> tuple[np.ndarray, int, int]:
    """The frames painted into the CT's grid: (labels, voxels painted, overlaps)."""
    direction = np.asarray(ref.direction, dtype=np.float64)
    if abs(fr.row @ direction[:, 0]) < 0.999 or abs(fr.col @ direction[:, 1]) < 0.999:
        raise LabelsOutsideScanError(
            f"{label}: the SEG's rows and columns do not run along the CT's; it is not on the CT's grid"
        )
    sp_xyz = np.asarray(ref.spacing_zyx_mm[::-1], dtype=np.float64)
    idx = ((fr.positions - np.asarray(ref.origin_mm)) @ np.linalg.inv(direction).T) / sp_xyz  # (F, 3) i, j, k
    if np.abs(idx - np.round(idx)).max() > _GRID_TOL:
        raise LabelsOutsideScanError(f"{label}: the SEG's frames do not lie on the CT's grid (off by a fraction)")
    idx = np.round(idx).astype(np.int64)
    row_sign, col_sign = np.sign(fr.row @ direction[:, 0]), np.sign(fr.col @ direction[:, 1])
    labels = np.zeros(ref.data.shape, dtype=dtype)
    painted = overlaps = 0
    for f in range(len(fr.pixels)):
        frame = fr.pixels[f][:: int(col_sign), :: int(row_sign)]
        j0 = idx[f, 1] - (frame.shape[0] - 1 if col_sign < 0 else 0)
        i0 = idx[f, 0] - (frame.shape[1] - 1 if row_sign < 0 else 0)
        n, o = _paint(labels, int(idx[f, 2]), int(j0), int(i0), frame, int(fr.numbers[f]))
        painted, overlaps = painted + n, overlaps + o
    return labels, painted, overlaps


def _own_grid(fr: _Frames, dtype: Any, label: str) -> tuple[np.ndarray, tuple[float, ...], np.ndarray, np.ndarray]:
    """The frames on the SEG's own grid: (labels, spacing zyx, origin, direction)."""
    normal = np.cross(fr.row, fr.col)
    d = fr.positions @ normal
    levels = np.unique(np.round(d, 4))
    gaps = np.diff(levels)
    step = fr.slice_step or (float(gaps.min()) if len(gaps) else 1.0)
    k = np.round((d - levels[0]) / step).astype(np.int64)
    if len(gaps) and np.abs((levels - levels[0]) / step - np.round((levels - levels[0]) / step)).max() > _GRID_TOL:
        raise InputError(f"{label}: the SEG's frame positions are not on a regular grid of {step:g} mm")
    first = int(np.argmin(d))
    origin = fr.positions[first]
    rows, cols = fr.pixels.shape[1:]
    labels = np.zeros((int(k.max()) + 1, rows, cols), dtype=dtype)
    for f in range(len(fr.pixels)):
        _paint(labels, int(k[f]), 0, 0, fr.pixels[f], int(fr.numbers[f]))
    direction = np.column_stack([fr.row, fr.col, normal])
    return labels, (float(step), fr.spacing_rc[0], fr.spacing_rc[1]), origin, direction


def read_dicom_seg(path: str | Path, *, reference: Volume | None = None) -> LabelVolume:
    """A DICOM SEG as a ``LabelVolume``: on ``reference``'s grid (its referenced CT) when given, else its own.

    Raises:
        MissingReferenceError: ``reference`` is another series than the one the SEG references.
        LabelsOutsideScanError: the SEG's frames are not on the CT's grid, or none of its voxels lands in it.
        NotLabelsError: the file is not a DICOM SEG.
    """
    p = Path(path)
    ds = _dataset(p)
    segments = _segments(ds)
    fr = _frames(ds, p.name)
    dtype = np.uint8 if max(s.value for s in segments) < 256 else np.uint16
    wanted = referenced_series(ds)
    source: dict[str, Any] = {"format": "dicom-seg", "file": p.name, "encoding": str(ds.get("SegmentationType"))}
    source["referenced_series_uid"] = wanted
    if reference is not None:
        have = reference.source.get("series_uid")
        if wanted and have and wanted != have:
            raise MissingReferenceError(
                f"{p.name}: the SEG was drawn on series {wanted}, but the CT given is series {have}"
            )
        labels, painted, overlaps = _into_reference(fr, reference, dtype, p.name)
        if painted == 0:
            raise LabelsOutsideScanError(f"{p.name}: no labelled voxel of the SEG lies inside the referenced CT")
        source["placed_by"] = "Per-frame Plane Position into the referenced CT's grid"
        spacing, origin, direction = reference.spacing_zyx_mm, reference.origin_mm, reference.direction
    else:
        labels, sp, o, dmat = _own_grid(fr, dtype, p.name)
        overlaps = 0
        source["placed_by"] = "Per-frame Plane Position on the SEG's own grid"
        spacing = (sp[0], sp[1], sp[2])
        origin = (float(o[0]), float(o[1]), float(o[2]))
        direction = tuple((float(r[0]), float(r[1]), float(r[2])) for r in dmat)
    if overlaps:
        source["overlap_voxels"] = overlaps
    return make_label_volume(labels, spacing, origin, direction, segments, source)


def read_seg_folder(folder: str | Path) -> LabelVolume:
    """The SEG of a folder placed on its referenced CT series in the same folder (``engine.io.load_volume``).

    ``source["reference"]`` says what the CT's completeness checks found (``engine.io.completeness``).

    Raises:
        MissingReferenceError: the folder lacks the series the SEG references (or the SEG names none).
    """
    import pydicom

    from engine.io import load_volume
    from engine.labels.uploads import is_seg_file

    root = Path(folder)
    segs = [f for f in sorted(q for q in root.rglob("*") if q.is_file()) if is_seg_file(f)]  # by the file meta
    if len(segs) != 1:
        raise InputError(f"{root.name}: expected one DICOM SEG in the folder, found {len(segs)}")
    path = segs[0]
    wanted = referenced_series(pydicom.dcmread(str(path), stop_before_pixels=True))
    if not wanted:
        raise MissingReferenceError(f"{path.name}: the SEG names no referenced series to place it on")
    try:
        ct = load_volume(root, series_uid=wanted)
    except InputError as exc:
        raise MissingReferenceError(
            f"{path.name}: its referenced series {wanted} is not in {root.name} ({exc})"
        ) from None
    lv = read_dicom_seg(path, reference=ct)
    # what the CT's checks found: a model for the PACS is made only on a CT checked whole (``worker.pacs``)
    lv.source["reference"] = {"images": int(ct.data.shape[0]), "completeness": ct.source.get("completeness")}
    return lv
