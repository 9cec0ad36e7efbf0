"""Label maps (segmentations) in: NIfTI (``.nii``, ``.nii.gz``), NRRD and 3D Slicer's ``.seg.nrrd``, and DICOM SEG
(``engine.labels.dicom_seg``), each read into one ``LabelVolume``.

Geometry follows ``engine.types.Volume`` and ``engine.orient``: ``labels`` is (z, y, x); ``origin_mm`` is the
patient position (DICOM LPS: +x left, +y posterior, +z superior) of sample (0, 0, 0) in (x, y, z); ``direction``'s
columns are the x, y, z array axes in LPS; a voxel (k, j, i) lies at ``origin + direction @ (i sx, j sy, k sz)``.
NIfTI's affine is RAS (its x, y negated here); NRRD says its frame in ``space`` (LPS, RAS or LAS, converted) and
places its axes with ``space directions`` / ``space origin``.

Bad input raises ``engine.errors.LabelError`` subclasses: a float (or scaled) NIfTI (``NotLabelsError``), a named
segment without voxels or a map with none (``EmptyLabelError``).
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.errors import EmptyLabelError, InputError, NotLabelsError
from engine.types import Volume

__all__ = [
    "LABEL_SUFFIXES",
    "LabelVolume",
    "Segment",
    "check_overlap",
    "is_label_path",
    "label_counts",
    "make_label_volume",
    "palette",
    "read_nifti_labels",
    "read_nrrd_labels",
]

LABEL_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".seg.nrrd", ".nhdr")
_TO_LPS = {  # NRRD/ITK space names -> the signs that take the space's (x, y, z) to LPS
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "las": (1.0, -1.0, 1.0),
}
MAX_LABELS = 1000  # more distinct values than this, none named: an image stored as integers, not a label map
_ORTHO_TOL = 1e-3  # axes this far from orthogonal (cosine) are a sheared grid: refused


@dataclass(frozen=True)
class Segment:
    """One label: its value in ``LabelVolume.labels``, its name and its display colour (sRGB, 0-1)."""

    value: int
    name: str
    color: tuple[float, float, float]

    def to_dict(self) -> dict[str, Any]:
        return {"value": self.value, "name": self.name, "color": [round(c, 4) for c in self.color]}


@dataclass
class LabelVolume:
    """A label map on a regular grid placed in the patient frame (see the module docstring).

    Args:
        labels: (z, y, x) integer array; 0 is background.
        spacing_zyx_mm: voxel size along z, y, x in mm.
        origin_mm: LPS (x, y, z) mm of sample (0, 0, 0).
        direction: 3x3, columns the unit x, y, z array axes in LPS.
        segments: the labels, one per value present (``value`` > 0).
        source: what was read (format, file, how it was placed, overlaps resolved...).
        patient_frame: False when the file did not place the grid (an NRRD without ``space``).
        masks: where segments overlap (a SEG's or a multi-layer seg.nrrd's segments are independent masks), the
            whole mask (bool, the map's shape) of each segment that lost voxels to a later one in ``labels``;
            ``layers`` gives maps in which every segment has all its voxels.
    """

    labels: npt.NDArray[np.integer[Any]]
    spacing_zyx_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    segments: tuple[Segment, ...] = ()
    source: dict[str, Any] = field(default_factory=dict)
    patient_frame: bool = True
    masks: dict[int, npt.NDArray[np.bool_]] = field(default_factory=dict)

    def position(self, index_zyx: Sequence[float] | npt.NDArray[Any]) -> npt.NDArray[np.float64]:
        """LPS (x, y, z) mm of voxel index/indices (k, j, i) (shape (3,) or (N, 3))."""
        idx = np.asarray(index_zyx, dtype=np.float64)
        grid_xyz = idx[..., ::-1] * np.asarray(self.spacing_zyx_mm[::-1])
        out: npt.NDArray[np.float64] = grid_xyz @ np.asarray(self.direction).T + np.asarray(self.origin_mm)
        return out

    def index_of(self, xyz_mm: Sequence[float] | npt.NDArray[Any]) -> npt.NDArray[np.float64]:
        """The (k, j, i) index (float) of LPS (x, y, z) mm point(s): the inverse of :meth:`position`."""
        p = np.asarray(xyz_mm, dtype=np.float64) - np.asarray(self.origin_mm)
        grid_xyz = p @ np.linalg.inv(np.asarray(self.direction)).T
        out: npt.NDArray[np.float64] = (grid_xyz / np.asarray(self.spacing_zyx_mm[::-1]))[..., ::-1]
        return out

    def as_volume(self) -> Volume:
        """The map as an ``engine.types.Volume`` (same grid; ``engine.orient.patient_frame`` places it)."""
        return Volume(
            self.labels,
            self.spacing_zyx_mm,
            self.origin_mm,
            self.direction,
            source=dict(self.source),
            patient_frame=self.patient_frame,
        )

    def segment(self, value: int) -> Segment:
        return next(s for s in self.segments if s.value == value)

    def layers(self) -> list[LabelVolume]:
        """The map as layers in which no two segments overlap and every segment has all its voxels: ``[self]``
        when none overlaps (``masks`` empty); else the map without the segments that lost voxels, then as few
        layers as hold those segments' whole masks (a segment joins the first layer it does not overlap). Each
        layer keeps the grid, source and frame, its segments in the map's order; mesh each one and join the parts
        in segment order (``Segment.value`` says which is which).

        Raises:
            ValueError: ``masks`` do not have the map's shape (cropped apart from it).
        """
        masked = {v: m for v, m in self.masks.items() if any(s.value == v for s in self.segments)}
        if not masked:
            return [self]
        if any(m.shape != self.labels.shape for m in masked.values()):
            raise ValueError("the segments' masks do not have the label map's shape (crop them with the map)")
        base = self.labels.copy()
        base[np.isin(base, list(masked))] = 0
        maps, members = [base], [[s.value for s in self.segments if s.value not in masked]]
        for value in (s.value for s in self.segments if s.value in masked):
            mask = masked[value]
            k = next((i for i in range(1, len(maps)) if not np.any(maps[i][mask])), len(maps))
            if k == len(maps):
                maps.append(np.zeros_like(self.labels))
                members.append([])
            maps[k][mask] = value
            members[k].append(value)
        out: list[LabelVolume] = []
        for labels, values in zip(maps, members, strict=True):
            if values:
                segments = tuple(s for s in self.segments if s.value in values)
                source = {**self.source, "layer": len(out)}
                out.append(
                    LabelVolume(
                        labels,
                        self.spacing_zyx_mm,
                        self.origin_mm,
                        self.direction,
                        segments,
                        source,
                        self.patient_frame,
                    )
                )
        return out


def check_overlap(lv: LabelVolume, scan: Volume) -> float:
    """The share of ``lv``'s labelled voxels whose centres lie inside ``scan``'s grid (both in the patient frame).

    Raises:
        LabelsOutsideScanError: none does (a segmentation of another scan or frame of reference).
    """
    from engine.errors import LabelsOutsideScanError
    from engine.orient import patient_frame

    k = np.argwhere(lv.labels > 0)
    if len(k) > 200_000:  # a sample is enough for a share
        k = k[np.linspace(0, len(k) - 1, 200_000).astype(np.int64)]
    frame = patient_frame(scan)
    grid_xyz = (lv.position(k) - frame.offset_mm) @ np.linalg.inv(frame.matrix).T
    idx = grid_xyz[:, ::-1] / np.asarray(scan.spacing_zyx_mm)
    inside = np.all((idx > -0.5) & (idx < np.asarray(scan.data.shape) - 0.5), axis=1)
    share = float(inside.mean()) if len(inside) else 0.0
    if share == 0.0:
        raise LabelsOutsideScanError(
            f"{lv.source.get('file', 'the label map')}: none of its labelled voxels lies inside the scan's grid "
            f"(a segmentation of another scan, or another frame of reference)"
        )
    return share


def palette(i: int) -> tuple[float, float, float]:
    """A distinct colour for the i-th unnamed label (golden-angle hues, bone-friendly saturation)."""
    r, g, b = colorsys.hsv_to_rgb((0.08 + i * 0.618034) % 1.0, 0.55, 0.92)
    return (round(r, 4), round(g, 4), round(b, 4))


def is_label_path(path: str | Path) -> bool:
    """Whether a file name says label map (``LABEL_SUFFIXES``)."""
    name = Path(path).name.lower()
    return any(name.endswith(s) for s in LABEL_SUFFIXES)


# --- NIfTI -------------------------------------------------------------------------------------------------------


def read_nifti_labels(path: str | Path) -> LabelVolume:
    """An integer NIfTI label map (TotalSegmentator's, ITK-SNAP's ...): its affine is RAS, turned into LPS."""
    import nibabel as nib

    try:
        img: Any = nib.load(str(path))
    except Exception as exc:  # nibabel raises several kinds for a bad file
        raise InputError(f"{Path(path).name}: not a readable NIfTI file ({exc})") from None
    dtype = img.get_data_dtype()
    slope, inter = img.header.get_slope_inter()
    scaled = (slope not in (None, 1.0) and np.isfinite(slope)) or (inter not in (None, 0.0) and np.isfinite(inter))
    if not np.issubdtype(dtype, np.integer) or scaled:
        raise NotLabelsError(
            f"{Path(path).name}: a {dtype} NIfTI{' with intensity scaling' if scaled else ''} is an image, not a "
            "label map; labels must be stored as integers (one value per structure)"
        )
    data = np.asarray(img.dataobj.get_unscaled())
    data = _three_d(data, Path(path).name)
    affine = np.asarray(img.affine, dtype=np.float64)
    flip = np.diag([-1.0, -1.0, 1.0])  # RAS -> LPS
    spacing, direction, origin = _geometry(flip @ affine[:3, :3], flip @ affine[:3, 3], Path(path).name)
    labels = _zyx(data)
    source = {"format": "nifti", "file": Path(path).name, "placed_by": nifti_placement(img.header)}
    return make_label_volume(labels, spacing, origin, direction, (), source)


_XFORM = {1: "scanner", 2: "aligned", 3: "Talairach", 4: "MNI 152", 5: "template"}


def nifti_placement(header: Any) -> str:
    """How a NIfTI header places its grid, as nibabel's ``affine`` takes it: the sform where its code is set, else
    the qform, else the voxel sizes alone (no orientation: RAS axes assumed)."""
    sform = int(header["sform_code"]) if "sform_code" in header else 0
    qform = int(header["qform_code"]) if "qform_code" in header else 0
    if sform > 0:
        return f"NIfTI sform ({_XFORM.get(sform, f'code {sform}')} space; RAS, turned into LPS)"
    if qform > 0:
        return f"NIfTI qform ({_XFORM.get(qform, f'code {qform}')} space; RAS, turned into LPS)"
    return "NIfTI voxel sizes only (no qform or sform: RAS axes assumed, turned into LPS)"


# --- NRRD / seg.nrrd ---------------------------------------------------------------------------------------------


def read_nrrd_labels(path: str | Path) -> LabelVolume:
    """An NRRD label map, or 3D Slicer's ``.seg.nrrd`` (segment names, colours, label values and layers from its
    header; several layers are merged, a voxel in two segments going to the later one, counted in
    ``source["overlap_voxels"]``)."""
    import nrrd

    label = Path(path).name
    try:
        data, header = nrrd.read(str(path))
    except Exception as exc:
        raise InputError(f"{label}: not a readable NRRD file ({exc})") from None
    if not np.issubdtype(data.dtype, np.integer):
        raise NotLabelsError(f"{label}: a {data.dtype} NRRD is an image, not a label map (labels are integers)")
    kinds = [str(k).lower() for k in header.get("kinds", ["domain"] * data.ndim)]
    spatial = [i for i, k in enumerate(kinds) if k in ("domain", "space")] or list(range(data.ndim))
    if len(spatial) != 3:
        raise InputError(f"{label}: expected 3 spatial axes, got kinds {kinds}")
    layer_axis = next((i for i in range(data.ndim) if i not in spatial), None)
    layers = np.moveaxis(data, layer_axis, 0) if layer_axis is not None else data[None]
    if layers.ndim != 4:
        raise InputError(f"{label}: expected a 3-D map or a list of 3-D layers, got shape {data.shape}")
    matrix, origin, placed = _nrrd_frame(header, spatial, label)
    spacing, direction, origin_lps = _geometry(matrix, origin, label)
    segs = _seg_nrrd_segments(header)
    masks: dict[int, np.ndarray] = {}
    if segs:
        merged, segments, overlap = _merge_layers(layers, segs)
        if overlap:  # segments are independent masks: each that lost voxels keeps its whole mask
            masks = _lost_masks(layers, segs, merged)
    elif len(layers) == 1:
        merged, segments, overlap = _three_d(layers[0], label), (), 0
    else:
        raise InputError(f"{label}: {len(layers)} layers but no Segment*_ header to say what they hold")
    source = {"format": "seg.nrrd" if segs else "nrrd", "file": label, "placed_by": placed, "layers": len(layers)}
    if overlap:
        source["overlap_voxels"] = overlap
    return make_label_volume(
        _zyx(merged), spacing, origin_lps, direction, segments, source, patient=placed != "none", masks=masks
    )


def _nrrd_frame(header: dict[str, Any], spatial: list[int], label: str) -> tuple[np.ndarray, np.ndarray, str]:
    """The LPS matrix (columns: the spatial axes' steps) and origin of an NRRD header, and how it was placed."""
    space = str(header.get("space", "")).lower()
    dirs = header.get("space directions")
    if dirs is None or not space:
        steps = header.get("spacings")
        sp = [float(steps[i]) if steps is not None and np.isfinite(steps[i]) else 1.0 for i in spatial]
        return np.diag(sp), np.zeros(3), "none"
    if space not in _TO_LPS:
        raise InputError(f"{label}: NRRD space {space!r} is not one bonemesh places (LPS, RAS or LAS)")
    d = np.asarray([np.asarray(dirs[i], dtype=np.float64) for i in spatial])  # rows: the axes' steps
    if d.shape != (3, 3) or not np.isfinite(d).all():
        raise InputError(f"{label}: NRRD space directions {dirs!r} do not give three spatial steps")
    sign = np.asarray(_TO_LPS[space])
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)
    return (d * sign).T, origin * sign, f"NRRD space directions ({space}, turned into LPS)"


def _seg_nrrd_segments(header: dict[str, Any]) -> list[dict[str, Any]]:
    """Slicer's ``Segment<i>_*`` header fields, in segment order."""
    out = []
    i = 0
    while f"Segment{i}_ID" in header or f"Segment{i}_Name" in header:
        name = str(header.get(f"Segment{i}_Name") or header.get(f"Segment{i}_ID"))
        color = header.get(f"Segment{i}_Color")
        rgb = tuple(float(c) for c in str(color).split()) if color else palette(i)
        out.append(
            {
                "name": name,
                "color": rgb if len(rgb) == 3 else palette(i),
                "value": int(header.get(f"Segment{i}_LabelValue", 1)),
                "layer": int(header.get(f"Segment{i}_Layer", 0)),
            }
        )
        i += 1
    return out


def _merge_layers(layers: np.ndarray, segs: list[dict[str, Any]]) -> tuple[np.ndarray, tuple[Segment, ...], int]:
    """One (x, y, z) map of the segments; values kept when one layer holds them all, else 1..n in segment order."""
    if len(layers) == 1:
        values = [s["value"] for s in segs]
        if len(set(values)) == len(values):
            segments = tuple(Segment(s["value"], s["name"], s["color"]) for s in segs)
            return layers[0], segments, 0
    merged = np.zeros(layers.shape[1:], dtype=np.uint16 if len(segs) > 255 else np.uint8)
    overlap = 0
    for n, s in enumerate(segs, start=1):
        if not 0 <= s["layer"] < len(layers):
            raise InputError(f"segment {s['name']!r} is in layer {s['layer']}, but the file has {len(layers)}")
        mask = layers[s["layer"]] == s["value"]
        overlap += int(np.count_nonzero(mask & (merged != 0)))
        merged[mask] = n
    segments = tuple(Segment(n, s["name"], s["color"]) for n, s in enumerate(segs, start=1))
    return merged, segments, overlap


def _lost_masks(layers: np.ndarray, segs: list[dict[str, Any]], merged: np.ndarray) -> dict[int, np.ndarray]:
    """The whole (z, y, x) mask of each merged segment (value n, 1..) that lost voxels to a later one."""
    masks: dict[int, np.ndarray] = {}
    for n, s in enumerate(segs, start=1):
        mask = layers[s["layer"]] == s["value"]
        if np.any(mask & (merged != n)):
            masks[n] = np.ascontiguousarray(np.transpose(mask, (2, 1, 0)))
    return masks


# --- shared ------------------------------------------------------------------------------------------------------


def _three_d(data: np.ndarray, label: str) -> np.ndarray:
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise InputError(f"{label}: expected a 3-D label map, got shape {data.shape}")
    return data


def _zyx(data_xyz: np.ndarray) -> np.ndarray:
    """(x, y, z) file order -> a contiguous (z, y, x) array of an unsigned type when the values allow."""
    out = np.ascontiguousarray(np.transpose(data_xyz, (2, 1, 0)))
    lo, hi = (int(out.min()), int(out.max())) if out.size else (0, 0)
    if lo < 0:
        raise NotLabelsError(f"label values must be >= 0 (0: background), got {lo}")
    for t in (np.uint8, np.uint16, np.uint32):
        if hi <= np.iinfo(t).max:
            return out.astype(t, copy=False)
    return out


def _geometry(
    matrix: np.ndarray, origin: np.ndarray, label: str
) -> tuple[tuple[float, float, float], tuple[tuple[float, float, float], ...], tuple[float, float, float]]:
    """Spacing (z, y, x), direction (unit columns x, y, z) and origin from an LPS matrix whose columns are the
    x, y, z axes' steps in mm."""
    norms = np.linalg.norm(matrix, axis=0)
    if not np.all(norms > 0) or not np.isfinite(matrix).all():
        raise InputError(f"{label}: the grid's axes {matrix.T.tolist()} are not three non-zero steps")
    unit = matrix / norms
    gram = unit.T @ unit
    if np.abs(gram - np.eye(3)).max() > _ORTHO_TOL:
        raise InputError(f"{label}: the grid's axes are not orthogonal (a sheared grid); resample it first")
    direction = tuple((float(r[0]), float(r[1]), float(r[2])) for r in unit)
    spacing = (float(norms[2]), float(norms[1]), float(norms[0]))
    return spacing, direction, (float(origin[0]), float(origin[1]), float(origin[2]))


def make_label_volume(
    labels: np.ndarray,
    spacing: tuple[float, float, float],
    origin: tuple[float, float, float],
    direction: tuple[tuple[float, float, float], ...],
    segments: tuple[Segment, ...],
    source: dict[str, Any],
    *,
    patient: bool = True,
    masks: dict[int, np.ndarray] | None = None,
) -> LabelVolume:
    """The ``LabelVolume``, with a segment for every value present and none declared but empty (a segment whose
    voxels all went to a later one is present by its mask in ``masks``)."""
    counts = label_counts(labels)
    present = [int(v) for v in np.flatnonzero(counts) if v > 0] if counts is not None else _present(labels)
    masks = {v: m for v, m in (masks or {}).items() if m.any()}
    present = sorted(set(present) | set(masks))
    if not present:
        raise EmptyLabelError(f"{source.get('file', 'the label map')}: no label in the map (every voxel is 0)")
    if len(present) > MAX_LABELS and not segments:
        raise NotLabelsError(
            f"{source.get('file', 'the map')}: {len(present)} distinct values (more than {MAX_LABELS}): an image "
            "stored as integers (a CT?), not a label map"
        )
    if segments:
        empty = [s.name for s in segments if s.value not in set(present)]
        if empty:
            raise EmptyLabelError(f"{source.get('file', 'the label map')}: segment(s) {empty} have no voxels")
        named = {s.value for s in segments}
        extra = [v for v in present if v not in named]
        segments = segments + tuple(Segment(v, f"label_{v}", palette(v)) for v in extra)
    else:
        segments = tuple(Segment(v, f"label_{v}", palette(v)) for v in present)
    return LabelVolume(labels, spacing, origin, direction, segments, source, patient, masks)


def label_counts(labels: np.ndarray) -> np.ndarray | None:
    """Voxels per value (``bincount``) when the values are small enough, else None."""
    if labels.dtype.itemsize <= 2:
        return np.bincount(labels.reshape(-1), minlength=1)
    hi = int(labels.max()) if labels.size else 0
    return np.bincount(labels.reshape(-1), minlength=1) if hi < 1 << 20 else None


def _present(labels: np.ndarray) -> list[int]:
    return [int(v) for v in np.unique(labels) if v > 0]
