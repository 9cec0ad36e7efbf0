"""Overlapping segments (allowed in a BINARY or FRACTIONAL DICOM SEG, and in a multi-layer Slicer .seg.nrrd) are
independent masks (issue 41): the reader keeps ``labels`` as before (a voxel in two segments goes to the later
one, counted in ``source["overlap_voxels"]``), and the whole mask of each segment that lost voxels
(``LabelVolume.masks``); ``LabelVolume.layers()`` gives maps in which no two segments overlap and each has all its
voxels. Checked on highdicom's two-segment SEG (on its own grid and on pydicom's CT), on a .seg.nrrd of two
overlapping boxes and one inside another, and meshed layer by layer (``engine.labels.parts.label_models``): each
box's model within a voxel of its own voxels, where the single map gives the first box half its volume."""

from __future__ import annotations

import zipfile
from pathlib import Path

import nrrd
import numpy as np
import pydicom
import pytest

from engine.io.labelmaps import LabelVolume
from engine.labels.dicom_seg import read_dicom_seg
from engine.labels.uploads import find_label_upload, read_label_upload, read_labels
from tests.engine.labels.test_dicom_seg_inputs import CONTIGUOUS, CT2, DATA, needs_ct2

OVERLAP = DATA / "seg_image_ct_binary_overlap.dcm"


def _check_layers(lv: LabelVolume, whole: dict[int, np.ndarray]) -> list[LabelVolume]:
    """Every segment in exactly one layer, with exactly its whole mask; no layer with two segments on a voxel."""
    layers = lv.layers()
    seen: list[int] = []
    for layer in layers:
        assert layer.labels.shape == lv.labels.shape and layer.spacing_zyx_mm == lv.spacing_zyx_mm
        for s in layer.segments:
            np.testing.assert_array_equal(layer.labels == s.value, whole[s.value])
            seen.append(s.value)
        assert set(np.unique(layer.labels).tolist()) <= {0, *(s.value for s in layer.segments)}
    assert sorted(seen) == sorted(s.value for s in lv.segments)
    return layers


def test_highdicom_overlapping_segments_on_their_own_grid() -> None:
    lv = read_dicom_seg(OVERLAP)
    px = pydicom.dcmread(OVERLAP).pixel_array.astype(bool)  # frames 0-3: segment 1, 4-7: segment 2, same places
    overlap = int((px[:4] & px[4:]).sum())
    assert overlap > 0 and lv.source["overlap_voxels"] == overlap
    assert list(lv.masks) == [1]  # segment 1 lost voxels to segment 2
    assert int(lv.masks[1].sum()) == int(px[:4].sum())
    assert int((lv.labels == 1).sum()) == int(px[:4].sum()) - overlap  # the single map, as before
    whole = {1: lv.masks[1], 2: lv.labels == 2}
    layers = _check_layers(lv, whole)
    assert [[s.value for s in layer.segments] for layer in layers] == [[2], [1]]


@needs_ct2
def test_highdicom_overlapping_segments_on_their_ct(tmp_path: Path) -> None:
    path = tmp_path / "seg_ct.zip"
    with zipfile.ZipFile(path, "w") as zf:
        zf.write(OVERLAP, "seg.dcm")
        for name in CONTIGUOUS:
            zf.write(CT2 / name, f"ct/{name}")
    lv = read_label_upload(path, find_label_upload(path), "seg_ct.zip")
    assert lv.labels.shape == (3, 16, 16) and 1 in lv.masks
    px = pydicom.dcmread(OVERLAP).pixel_array.astype(bool)[[1, 2, 3, 5, 6, 7]]  # the frames on these 3 slices
    assert int(lv.masks[1].sum()) == int(px[:3].sum())
    _check_layers(lv, {1: lv.masks[1], 2: lv.labels == 2})


def _boxes(tmp_path: Path, inside: bool = False) -> tuple[Path, dict[int, np.ndarray]]:
    """A two-layer .seg.nrrd: box A (segment 1, layer 0) and box B (segment 2, layer 1) overlapping by half of A
    (or, ``inside``, B containing A whole), 1 mm voxels; and the boxes' masks (z, y, x)."""
    shape = (40, 40, 48)
    a = np.zeros(shape, bool)
    b = np.zeros(shape, bool)
    a[10:30, 10:30, 8:28] = True
    if inside:
        b[6:34, 6:34, 4:32] = True
    else:
        b[10:30, 10:30, 18:38] = True
    layers = np.stack([a, b]).astype(np.uint8).transpose(0, 3, 2, 1)  # (layer, x, y, z)
    header = {
        "space": "left-posterior-superior",
        "space origin": np.zeros(3),
        "space directions": np.vstack([np.full(3, np.nan), np.eye(3)]),
        "kinds": ["list", "domain", "domain", "domain"],
    }
    for i, (name, layer) in enumerate((("A", 0), ("B", 1))):
        header.update({f"Segment{i}_ID": name, f"Segment{i}_Name": name, f"Segment{i}_LabelValue": "1"})
        header.update({f"Segment{i}_Layer": str(layer), f"Segment{i}_Color": "0.9 0.5 0.1"})
    path = tmp_path / "boxes.seg.nrrd"
    nrrd.write(str(path), layers.copy(), header)
    return path, {1: a, 2: b}


@pytest.mark.parametrize("inside", [False, True])
def test_seg_nrrd_overlapping_layers(tmp_path: Path, inside: bool) -> None:
    """Half of A under B, or A wholly inside B (the single map has no voxel of A: present by its mask)."""
    path, whole = _boxes(tmp_path, inside)
    lv = read_labels(path)
    assert [s.name for s in lv.segments] == ["A", "B"]
    assert lv.source["overlap_voxels"] == int((whole[1] & whole[2]).sum())
    assert int((lv.labels == 1).sum()) == (0 if inside else 4000)
    layers = _check_layers(lv, whole)
    assert [[s.name for s in layer.segments] for layer in layers] == [["B"], ["A"]]


def test_each_overlapping_segment_meshed_whole(tmp_path: Path) -> None:
    """Meshed layer by layer, each box's model is within a voxel of its own voxels (A: 8000 mm3 as a 20 mm cube;
    its faces at the box's voxel faces, so the volume within one voxel layer); meshed as the single map, A keeps
    about half."""
    from engine.labels.parts import label_models

    path, whole = _boxes(tmp_path)
    lv = read_labels(path)
    parts = [p for layer in lv.layers() for p in label_models(layer, device="cpu").parts]
    volumes = {p.name: float(p.stats["volume_mm3"]) for p in parts}
    for name, mask in (("A", whole[1]), ("B", whole[2])):
        voxels = int(mask.sum())
        shell = 2 * (20 * 20 + 20 * 20 + 20 * 20)  # one voxel layer over the cube's faces, mm3
        assert abs(volumes[name] - voxels) < shell, (name, volumes[name], voxels)
        part = next(p for p in parts if p.name == name)
        lo, hi = part.vertices_xyz.min(axis=0), part.vertices_xyz.max(axis=0)
        zyx = np.argwhere(mask)
        np.testing.assert_allclose(lo, zyx.min(axis=0)[::-1], atol=1.0)
        np.testing.assert_allclose(hi, zyx.max(axis=0)[::-1], atol=1.0)
    import dataclasses

    whole_models = label_models(lv, device="cpu")  # what a job meshes: the layers, joined in segment order
    assert [p.name for p in whole_models.parts] == ["A", "B"]
    assert [r["name"] for r in whole_models.report["labels"]] == ["A", "B"]
    assert {p.name: float(p.stats["volume_mm3"]) for p in whole_models.parts} == pytest.approx(volumes, rel=1e-6)
    assert whole_models.report["labels_mesh"]["layers"] == 2
    one_map = label_models(dataclasses.replace(lv, masks={}), device="cpu")  # the masks ignored: one map
    single = {p.name: float(p.stats["volume_mm3"]) for p in one_map.parts}
    assert single["A"] < 0.6 * volumes["A"]  # "later segment wins": what the layers fix


def test_a_job_with_overlapping_segments_gives_each_its_whole_model(tmp_path: Path) -> None:
    """``engine.job.run_job`` (the CLI's and the worker's path) on the two-layer .seg.nrrd, also cropped to a box
    that keeps both: each box's model has all its voxels, as meshed alone."""
    from engine.job import InputSpec, JobSpec, resolve_runtime, run_job
    from engine.params import ReconParams, RoiParams

    path, whole = _boxes(tmp_path)
    recon = ReconParams.from_dict({"export": {"phone_max_triangles": 2000, "ar_max_triangles": 800}})
    for roi in (None, RoiParams(((0, 40), (0, 40), (0, 48)))):
        out = tmp_path / f"out{roi is not None}"
        result = run_job(path, out, JobSpec(recon=recon, input=InputSpec(roi=roi)), resolve_runtime("cpu"))
        rows = {r["name"]: r for r in result.report["labels"]}
        assert list(rows) == ["A", "B"] and rows["A"]["voxels"] == int(whole[1].sum()) == 8000
        assert abs(rows["A"]["volume_mm3"] - 8000) < 2400 and abs(rows["B"]["volume_mm3"] - 8000) < 2400
