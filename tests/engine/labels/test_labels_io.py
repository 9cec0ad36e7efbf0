"""Label maps in (engine.io.labelmaps, engine.labels.dicom_seg): maps made from the real headsq scan (bone halves
either side of the mid-sagittal plane, on a rotated and shifted grid) written as NIfTI, NRRD (LPS and RAS),
Slicer .seg.nrrd (one layer and several) and DICOM SEG (binary and label-map, highdicom) over a CT series made of
the same scan; read back through every reader with the same labels, and a voxel's patient position the same as the
source's; and the bad inputs refused with their errors."""

from __future__ import annotations

import io
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pydicom
import pytest

from engine.errors import EmptyLabelError, LabelsOutsideScanError, MissingReferenceError, NotLabelsError
from engine.io import load_volume
from engine.io.labelmaps import LabelVolume, check_overlap, is_label_path
from engine.labels.dicom_seg import lab_to_srgb, read_dicom_seg, read_seg_folder
from engine.labels.uploads import read_labels
from tests.engine.dicom_factory import ct_slice
from tests.engine.labels.test_labels_util import headsq_data, headsq_labels, highdicom_seg

STUDY_DEFAULTS = {
    "PatientSex": "O",
    "PatientBirthDate": "",
    "PatientName": "TEST",
    "PatientID": "TEST",
    "StudyDate": "20260101",
    "StudyTime": "000000",
    "StudyID": "1",
    "AccessionNumber": "",
    "ReferringPhysicianName": "",
}
VOXELS = [(0, 0, 0), (40, 20, 33), (92, 63, 63), (55, 31, 12)]


@pytest.fixture(scope="module")
def lv() -> LabelVolume:
    return headsq_labels()


def _matrix(lv: LabelVolume) -> np.ndarray:
    """Columns: the x, y, z axes' steps in LPS mm."""
    return np.asarray(lv.direction) * np.asarray(lv.spacing_zyx_mm[::-1])


def _same_geometry(got: LabelVolume, want: LabelVolume) -> None:
    np.testing.assert_array_equal(got.labels, want.labels)
    for v in VOXELS:
        np.testing.assert_allclose(got.position(v), want.position(v), atol=1e-4)
    np.testing.assert_allclose(got.spacing_zyx_mm, want.spacing_zyx_mm, rtol=1e-6)


def test_nifti(tmp_path: Path, lv: LabelVolume) -> None:
    ras = np.eye(4)
    ras[:3, :3] = np.diag([-1.0, -1.0, 1.0]) @ _matrix(lv)
    ras[:3, 3] = np.diag([-1.0, -1.0, 1.0]) @ np.asarray(lv.origin_mm)
    path = tmp_path / "bones.nii.gz"
    nib.save(nib.Nifti1Image(lv.labels.transpose(2, 1, 0).astype(np.int16), ras), str(path))
    got = read_labels(path)
    _same_geometry(got, lv)
    assert [s.value for s in got.segments] == [1, 2] and got.source["format"] == "nifti"
    assert is_label_path(path) and not is_label_path(tmp_path / "scan.zip")


@pytest.mark.parametrize("space", ["left-posterior-superior", "right-anterior-superior"])
def test_nrrd(tmp_path: Path, lv: LabelVolume, space: str) -> None:
    sign = np.array([1.0, 1.0, 1.0]) if space.startswith("left") else np.array([-1.0, -1.0, 1.0])
    header = {
        "space": space,
        "space directions": (_matrix(lv) * sign[:, None]).T,
        "space origin": np.asarray(lv.origin_mm) * sign,
        "kinds": ["domain"] * 3,
    }
    path = tmp_path / "bones.nrrd"
    nrrd.write(str(path), lv.labels.transpose(2, 1, 0).copy(), header)
    _same_geometry(read_labels(path), lv)


def _seg_header(lv: LabelVolume, segs: list[tuple[str, int, int, str]]) -> dict[str, object]:
    header: dict[str, object] = {
        "space": "left-posterior-superior",
        "space origin": np.asarray(lv.origin_mm),
    }
    for i, (name, value, layer, colour) in enumerate(segs):
        header.update(
            {
                f"Segment{i}_ID": f"Segment_{i}",
                f"Segment{i}_Name": name,
                f"Segment{i}_Color": colour,
                f"Segment{i}_LabelValue": str(value),
                f"Segment{i}_Layer": str(layer),
            }
        )
    return header


def test_seg_nrrd_one_layer(tmp_path: Path, lv: LabelVolume) -> None:
    """Slicer's labelmap form: label values 5 and 7 named and coloured in the header."""
    data = np.where(lv.labels == 1, 5, np.where(lv.labels == 2, 7, 0)).astype(np.uint8)
    header = _seg_header(lv, [("right half", 5, 0, "0.9 0.1 0.1"), ("left half", 7, 0, "0.1 0.2 0.9")])
    header.update({"space directions": _matrix(lv).T, "kinds": ["domain"] * 3})
    path = tmp_path / "bones.seg.nrrd"
    nrrd.write(str(path), data.transpose(2, 1, 0).copy(), header)
    got = read_labels(path)
    assert [(s.value, s.name, s.color) for s in got.segments] == [
        (5, "right half", (0.9, 0.1, 0.1)),
        (7, "left half", (0.1, 0.2, 0.9)),
    ]
    np.testing.assert_array_equal(got.labels, data)
    np.testing.assert_allclose(got.position(VOXELS[1]), lv.position(VOXELS[1]), atol=1e-4)


def test_seg_nrrd_layers(tmp_path: Path, lv: LabelVolume) -> None:
    """The multi-layer form: a whole-head segment (tissue and bone) overlapping both halves in a second layer; the
    halves are painted after it, so they win where they overlap, and the overlap is counted."""
    head = headsq_data() >= 500
    layers = np.stack([lv.labels, head.astype(np.uint8)])  # (layer, z, y, x)
    header = _seg_header(lv, [("head", 1, 1, "1 1 1"), ("right", 1, 0, "1 0 0"), ("left", 2, 0, "0 0 1")])
    dirs = np.vstack([np.full(3, np.nan), _matrix(lv).T])
    header.update({"space directions": dirs, "kinds": ["list", "domain", "domain", "domain"]})
    path = tmp_path / "layers.seg.nrrd"
    nrrd.write(str(path), layers.transpose(0, 3, 2, 1).copy(), header)
    got = read_labels(path)
    assert [s.name for s in got.segments] == ["head", "right", "left"]
    np.testing.assert_array_equal(got.labels, np.where(lv.labels > 0, lv.labels + 1, head.astype(np.uint8)))
    assert got.source["overlap_voxels"] == int((lv.labels > 0).sum())
    np.testing.assert_allclose(got.position(VOXELS[3]), lv.position(VOXELS[3]), atol=1e-4)


# --- DICOM SEG ---------------------------------------------------------------------------------------------------


def _ct_files(lv: LabelVolume, data: np.ndarray, series_uid: str) -> dict[str, bytes]:
    """A CT series of the scan on the map's grid (the rotated axes and origin)."""
    d = np.asarray(lv.direction)
    iop = [*d[:, 0], *d[:, 1]]
    _, sy, sx = lv.spacing_zyx_mm
    return {
        f"CT{k:03d}.dcm": ct_slice(
            data[k], ipp=lv.position((k, 0, 0)), iop=iop, pixel_spacing=(sy, sx), series_uid=series_uid, instance=k + 1
        )
        for k in range(len(data))
    }


def _seg(files: dict[str, bytes], labels: np.ndarray, kind: str) -> bytes:

    sources = [pydicom.dcmread(io.BytesIO(b)) for b in files.values()]
    for ds in sources:  # the study attributes highdicom copies (the synthetic series leaves them out)
        for key, value in STUDY_DEFAULTS.items():
            if key not in ds:
                setattr(ds, key, value)
    halves = [(1, "right half", (230, 40, 40)), (2, "left half", (30, 60, 220))]
    seg = highdicom_seg(sources, labels, halves, kind=kind)
    buf = io.BytesIO()
    seg.save_as(buf)
    return buf.getvalue()


@pytest.fixture(scope="module")
def ct_and_seg(tmp_path_factory: pytest.TempPathFactory, lv: LabelVolume) -> dict[str, object]:
    root = tmp_path_factory.mktemp("seg")
    uid = pydicom.uid.generate_uid()
    files = _ct_files(lv, headsq_data(), uid)
    for name, data in files.items():
        (root / "study" / "ct").mkdir(parents=True, exist_ok=True)
        (root / "study" / "ct" / name).write_bytes(data)
    out: dict[str, object] = {"root": root, "ct": load_volume(root / "study" / "ct")}
    for kind in ("BINARY", "LABELMAP"):
        path = root / f"{kind.lower()}.dcm"
        path.write_bytes(_seg(files, lv.labels, kind))
        out[kind] = path
    return out


@pytest.mark.parametrize("kind", ["BINARY", "LABELMAP"])
def test_dicom_seg_on_its_ct(ct_and_seg: dict[str, object], lv: LabelVolume, kind: str) -> None:
    ct = ct_and_seg["ct"]
    got = read_dicom_seg(ct_and_seg[kind], reference=ct)
    _same_geometry(got, lv)
    names = [(s.value, s.name) for s in got.segments]
    assert names == [(1, "right half"), (2, "left half")]
    assert np.allclose(got.segments[0].color, (230 / 255, 40 / 255, 40 / 255), atol=0.01)


@pytest.mark.parametrize("kind", ["BINARY", "LABELMAP"])
def test_dicom_seg_on_its_own_grid(ct_and_seg: dict[str, object], lv: LabelVolume, kind: str) -> None:
    """Without the CT, the frames (empty ones left out) make their own grid: every labelled voxel lies where the
    source's does."""
    got = read_dicom_seg(ct_and_seg[kind])
    k = np.argwhere(got.labels > 0)
    src = np.round(lv.index_of(got.position(k))).astype(int)
    np.testing.assert_array_equal(lv.labels[tuple(src.T)], got.labels[tuple(k.T)])
    assert len(k) == int((lv.labels > 0).sum())


def test_dicom_seg_folder(ct_and_seg: dict[str, object], lv: LabelVolume, tmp_path: Path) -> None:
    root = ct_and_seg["root"] / "study"
    (root / "seg.dcm").write_bytes(Path(ct_and_seg["BINARY"]).read_bytes())
    try:
        _same_geometry(read_seg_folder(root), lv)
    finally:
        (root / "seg.dcm").unlink()
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "seg.dcm").write_bytes(Path(ct_and_seg["BINARY"]).read_bytes())
    with pytest.raises(MissingReferenceError, match="referenced series"):
        read_seg_folder(alone)


def test_dicom_seg_on_another_series_or_outside(ct_and_seg: dict[str, object]) -> None:
    import dataclasses

    ct = ct_and_seg["ct"]
    other = dataclasses.replace(ct, source={**ct.source, "series_uid": "1.2.3.4"})
    with pytest.raises(MissingReferenceError, match="drawn on series"):
        read_dicom_seg(ct_and_seg["BINARY"], reference=other)
    moved = dataclasses.replace(ct, origin_mm=(ct.origin_mm[0], ct.origin_mm[1], ct.origin_mm[2] + 1500.0))
    with pytest.raises(LabelsOutsideScanError):
        read_dicom_seg(ct_and_seg["BINARY"], reference=moved)


def test_lab_to_srgb() -> None:
    import highdicom as hd

    for rgb in ((255, 0, 0), (20, 200, 90), (128, 128, 128)):
        value = hd.color.CIELabColor.from_rgb(*rgb).value
        np.testing.assert_allclose(lab_to_srgb(value), np.array(rgb) / 255, atol=0.01)


@pytest.mark.filterwarnings("ignore:The string:UserWarning")  # highdicom on the phantom's one-part PatientName
def test_real_ct_dicom_seg(tmp_path: Path) -> None:
    """The head phantom's real DICOM series (../shared/data): its bone halves as a SEG read back onto it."""
    import zipfile

    from tests.conftest import shared_file
    from tests.engine.labels.test_labels_util import split_map

    archive = shared_file("head_phantom_dicom", "head_phantom_dicom.zip")
    with zipfile.ZipFile(archive) as zf:
        names = sorted(n for n in zf.namelist() if not n.endswith("/"))
        files = {Path(n).name: zf.read(n) for n in names}
    images = [d for d in (pydicom.dcmread(io.BytesIO(b)) for b in files.values()) if "ImagePositionPatient" in d]
    ds = sorted(images, key=lambda d: float(d.ImagePositionPatient[2]))
    ds = ds[len(ds) // 2 : len(ds) // 2 + 12]
    for d in ds:
        d.save_as(tmp_path / f"{d.SOPInstanceUID}.dcm")
    ct = load_volume(tmp_path)
    labels = split_map(ct.data, 300)
    keep = {n: (tmp_path / f"{d.SOPInstanceUID}.dcm").read_bytes() for n, d in enumerate(ds)}
    seg_path = tmp_path.parent / "real_seg.dcm"
    seg_path.write_bytes(_seg({str(n): b for n, b in keep.items()}, labels, "BINARY"))
    got = read_dicom_seg(seg_path, reference=ct)
    np.testing.assert_array_equal(got.labels, labels)
    assert got.origin_mm == ct.origin_mm


# --- refused -----------------------------------------------------------------------------------------------------


def test_float_nifti_is_not_labels(tmp_path: Path) -> None:
    path = tmp_path / "ct.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros((4, 4, 4), np.float32), np.eye(4)), str(path))
    with pytest.raises(NotLabelsError, match="float32"):
        read_labels(path)


def test_empty_map_and_empty_segment(tmp_path: Path, lv: LabelVolume) -> None:
    path = tmp_path / "zero.nii"
    nib.save(nib.Nifti1Image(np.zeros((4, 4, 4), np.uint8), np.eye(4)), str(path))
    with pytest.raises(EmptyLabelError, match="no label"):
        read_labels(path)
    header = _seg_header(lv, [("right", 1, 0, "1 0 0"), ("lost", 9, 0, "0 1 0")])
    header.update({"space directions": _matrix(lv).T, "kinds": ["domain"] * 3})
    seg = tmp_path / "lost.seg.nrrd"
    nrrd.write(str(seg), (lv.labels == 1).astype(np.uint8).transpose(2, 1, 0).copy(), header)
    with pytest.raises(EmptyLabelError, match="lost"):
        read_labels(seg)


def test_integer_image_is_not_labels(tmp_path: Path) -> None:
    """A CT stored as unsigned integers has thousands of values: refused rather than meshed as labels."""
    path = tmp_path / "ct_uint16.nii.gz"
    nib.save(nib.Nifti1Image(headsq_data().transpose(2, 1, 0).copy(), np.eye(4)), str(path))
    with pytest.raises(NotLabelsError, match="distinct values"):
        read_labels(path)


def test_labels_must_overlap_the_scan(lv: LabelVolume) -> None:
    import dataclasses

    scan = lv.as_volume()
    assert check_overlap(lv, scan) == 1.0
    far = dataclasses.replace(scan, origin_mm=(lv.origin_mm[0], lv.origin_mm[1], lv.origin_mm[2] + 1000.0))
    with pytest.raises(LabelsOutsideScanError, match="inside the scan"):
        check_overlap(lv, far)
