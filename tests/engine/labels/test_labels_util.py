"""Helpers of the label tests (no tests here): label maps made from the real scans, and a check that two closed
meshes are disjoint."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.io.labelmaps import LabelVolume, Segment, palette
from engine.io.stack import load_slice_zip

# a rotated, shifted grid (30 degrees about the patient z axis): the readers must keep it exactly
ANGLE = np.radians(30.0)
DIRECTION = ((np.cos(ANGLE), -np.sin(ANGLE), 0.0), (np.sin(ANGLE), np.cos(ANGLE), 0.0), (0.0, 0.0, 1.0))
ORIGIN = (-101.5, -87.25, 42.0)


def headsq_data() -> np.ndarray:
    return load_slice_zip(HEADSQ_ZIP)


def split_map(data: np.ndarray, level: float, soft: float | None = None) -> np.ndarray:
    """Bone (>= level) split at the mid-sagittal plane (x = nx / 2): 1 the right half of the image, 2 the left; the
    two halves touch across the plane. With ``soft``: 3 the largest piece of tissue in [soft, level)."""
    labels = np.zeros(data.shape, np.uint8)
    left = np.arange(data.shape[2]) >= data.shape[2] // 2
    bone = data >= level
    labels[bone & ~left] = 1
    labels[bone & left] = 2
    if soft is not None:
        comp, _ = ndimage.label((data >= soft) & ~bone)
        sizes = np.bincount(comp.reshape(-1))[1:]
        labels[comp == int(np.argmax(sizes)) + 1] = 3
    return labels


def headsq_labels(soft: float | None = None) -> LabelVolume:
    """The bundled headsq's bone halves (and tissue) on the rotated grid."""
    labels = split_map(headsq_data(), HEADSQ_LEVEL, soft)
    names = ["bone_right", "bone_left", "tissue"]
    values = sorted(int(v) for v in np.unique(labels) if v)
    segments = tuple(Segment(v, names[v - 1], palette(v)) for v in values)
    return LabelVolume(labels, HEADSQ_SPACING_ZYX_MM, ORIGIN, DIRECTION, segments, {"format": "test"})


def _edges(faces: np.ndarray) -> np.ndarray:
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def _bins(size: np.ndarray) -> np.ndarray:
    """Size classes (powers of two) so that near pairs are looked for with a reach fitting each class."""
    return np.clip(np.floor(np.log2(size / max(float(np.median(size)), 1e-9))).astype(int), 0, 12)


def _crossings(va: np.ndarray, fa: np.ndarray, vb: np.ndarray, fb: np.ndarray, chunk: int = 2000) -> int:
    """Edges of mesh A that pass through a triangle of mesh B (Moller-Trumbore on the pairs near enough to meet)."""
    e = _edges(fa)
    p0, p1 = va[e[:, 0]], va[e[:, 1]]
    mid, half = (p0 + p1) / 2, np.linalg.norm(p1 - p0, axis=1) / 2
    tri = vb[fb]
    centre = tri.mean(axis=1)
    rad = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)
    ebin, tbin = _bins(half), _bins(rad)
    hits = 0
    for tb in np.unique(tbin):
        tsel = np.flatnonzero(tbin == tb)
        tree = cKDTree(centre[tsel])
        for eb in np.unique(ebin):
            esel = np.flatnonzero(ebin == eb)
            reach = float(rad[tsel].max() + half[esel].max())
            for first in range(0, len(esel), chunk):
                part = esel[first : first + chunk]
                pairs = tree.query_ball_point(mid[part], reach)
                ei = np.repeat(part, [len(q) for q in pairs])
                if len(ei):
                    ti = tsel[np.concatenate([np.asarray(q, dtype=np.int64) for q in pairs])]
                    hits += _segment_hits(p0[ei], p1[ei], tri[ti])
    return hits


def _segment_hits(p0: np.ndarray, p1: np.ndarray, tri: np.ndarray) -> int:
    o, d = p0, p1 - p0
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - a
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    return int((ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)).sum())


def winding(points: np.ndarray, verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Generalised winding number of points w.r.t. a closed mesh (1 inside, 0 outside)."""
    out = np.empty(len(points))
    for i, p in enumerate(points):
        a, b, c = (verts[faces[:, k]] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
        den += np.einsum("ij,ij->i", c, a) * lb
        out[i] = 2 * np.arctan2(num, den).sum() / (4 * np.pi)
    return out


def assert_disjoint(va: np.ndarray, fa: np.ndarray, vb: np.ndarray, fb: np.ndarray) -> float:
    """Two closed meshes (x, y, z vertices) share no vertex, no edge of one crosses a face of the other, and no
    vertex of one lies inside the other; returns the smallest vertex distance between them."""
    gap = float(cKDTree(vb).query(va)[0].min())
    assert gap > 0, "the meshes share a vertex"
    assert _crossings(va, fa, vb, fb) == 0, "an edge of the first mesh crosses a face of the second"
    assert _crossings(vb, fb, va, fa) == 0, "an edge of the second mesh crosses a face of the first"
    rng = np.random.default_rng(0)
    for v, (w, f) in ((va, (vb, fb)), (vb, (va, fa))):
        sample = v[rng.choice(len(v), size=min(len(v), 200), replace=False)]
        assert np.abs(winding(sample, w, f)).max() < 0.5, "a vertex of one mesh lies inside the other"
    return gap


def highdicom_seg(
    sources: list[Any],
    labels: np.ndarray,
    segments: list[tuple[int, str, tuple[int, int, int] | None]],
    *,
    kind: str = "BINARY",
    series_number: int = 99,
    **extra: Any,
) -> Any:
    """A DICOM SEG written by highdicom over ``sources`` (pydicom datasets): ``segments`` as (number, name, display
    colour or None), bone in tissue; ``extra`` goes to ``highdicom.seg.Segmentation`` (``transfer_syntax_uid``)."""
    import highdicom as hd
    import pydicom
    from pydicom.sr.codedict import codes

    descriptions = [
        hd.seg.SegmentDescription(
            segment_number=n,
            segment_label=name,
            segmented_property_category=codes.SCT.Tissue,
            segmented_property_type=codes.SCT.Bone,
            algorithm_type="MANUAL",
            **({"display_color": hd.color.CIELabColor.from_rgb(*rgb)} if rgb is not None else {}),
        )
        for n, name, rgb in segments
    ]
    return hd.seg.Segmentation(
        source_images=sources,
        pixel_array=labels,
        segmentation_type=kind,
        segment_descriptions=descriptions,
        series_instance_uid=pydicom.uid.generate_uid(),
        series_number=series_number,
        sop_instance_uid=pydicom.uid.generate_uid(),
        instance_number=1,
        manufacturer="bonemesh tests",
        manufacturer_model_name="labels",
        software_versions="0",
        device_serial_number="0",
        **extra,
    )
