"""A label job's files (``engine.labels.outputs.write_label_outputs``) from the headsq bone halves: the GLB files hold
one node per label, named and coloured by its segment; labels.zip holds one watertight STL per label (LPS mm); the
report lists each label's volume, area and faces; the viewing copies share their budget by area. And label-map
uploads found by content (``engine.labels.uploads``), read as the worker reads them (``engine.job.run_job``)."""

from __future__ import annotations

import gzip
import io
import json
import zipfile
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import trimesh

from engine.errors import InputError, NotLabelsError
from engine.export.files import engine_files
from engine.params import ReconParams
from tests.engine.labels.test_labels_util import headsq_labels

BUDGETS = {"export": {"phone_max_triangles": 3000, "ar_max_triangles": 1200}}


def nifti_bytes(lv, dtype=np.uint8) -> bytes:
    """A label map as a gzipped NIfTI (RAS affine), the way TotalSegmentator writes them."""
    affine = np.eye(4)
    affine[:3, :3] = np.diag([-1.0, -1.0, 1.0]) @ (np.asarray(lv.direction) * np.asarray(lv.spacing_zyx_mm[::-1]))
    affine[:3, 3] = np.diag([-1.0, -1.0, 1.0]) @ np.asarray(lv.origin_mm)
    image = nib.Nifti1Image(lv.labels.transpose(2, 1, 0).astype(dtype), affine)
    return gzip.compress(image.to_bytes(), compresslevel=1)


def _glb_document(data: bytes) -> dict:
    n = int.from_bytes(data[12:16], "little")
    return json.loads(data[20 : 20 + n])


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    from engine.labels.outputs import write_label_outputs
    from engine.labels.parts import label_models

    lv = headsq_labels()
    params = ReconParams.from_dict(BUDGETS)
    models = label_models(lv, params, device="cpu")
    out = tmp_path_factory.mktemp("labels")
    return lv, models, out, write_label_outputs(models, out, params, device="cpu")


def test_the_files_are_the_registrys_and_nothing_else_is_left(written):
    _, _, out, paths = written
    assert list(paths) == list(engine_files(labels=True))
    assert sorted(p.name for p in out.iterdir()) == sorted(paths)  # no temporary folder, no labels/ folder
    assert all(p.stat().st_size > 0 for p in paths.values())


def test_each_glb_has_a_named_coloured_node_per_label(written):
    lv, _, _, paths = written
    names = [s.name for s in lv.segments]
    report = json.loads(paths["report.json"].read_text())
    for name in ("model.glb", "phone.glb", "ar.glb"):
        doc = _glb_document(paths[name].read_bytes())
        assert [n["name"] for n in doc["nodes"]] == names, name
        for node, seg in zip(doc["nodes"], lv.segments, strict=True):
            material = doc["materials"][doc["meshes"][node["mesh"]]["primitives"][0]["material"]]
            assert material["name"] == seg.name
            assert material["pbrMetallicRoughness"]["baseColorFactor"] == pytest.approx([*seg.color, 1.0])
    scene = trimesh.load(io.BytesIO(paths["model.glb"].read_bytes()), file_type="glb")
    faces = {name: len(g.faces) for name, g in scene.geometry.items()}
    assert sorted(faces.values()) == sorted(r["faces"] for r in report["labels"])
    # the viewing copies: each label at its area share of the copy's budget (the share is at least 200 faces)
    for name, budget in (("phone.glb", 3000), ("ar.glb", 1200)):
        shares = report["exports"][name]["labels"]
        assert sum(s["share"] for s in shares) <= budget and report["exports"][name]["faces"] <= 1.1 * budget
        assert [s["name"] for s in shares] == names


def test_labels_zip_holds_a_watertight_stl_per_label_in_patient_mm(written):
    lv, _, _, paths = written
    report = json.loads(paths["report.json"].read_text())
    with zipfile.ZipFile(paths["labels.zip"]) as zf:
        assert sorted(zf.namelist()) == sorted(r["file"] for r in report["labels"])
        for row in report["labels"]:
            mesh = trimesh.load(io.BytesIO(zf.read(row["file"])), file_type="stl")
            assert mesh.is_watertight and len(mesh.faces) == row["faces"]
            assert mesh.volume == pytest.approx(row["volume_mm3"], rel=1e-3) and row["area_mm2"] > 0
            idx = np.clip(np.round(lv.index_of(mesh.vertices)).astype(int), 0, np.array(lv.labels.shape) - 1)
            assert np.mean(lv.labels[tuple(idx.T)] == row["value"]) > 0.5  # on its label's voxels
    total = sum(r["faces"] for r in report["labels"])
    assert report["mesh"]["n_faces"] == total == report["exports"]["labels.zip"]["faces"]
    assert report["mesh"]["watertight"] is True and len(report["frame"]["gltf_centre_lps_mm"]) == 3


def test_labels_zip_is_the_same_bytes_when_written_again(written, tmp_path: Path) -> None:
    """The archive carries no write time or file mode of its own: the same parts give the same bytes (a re-run's
    labels.zip is byte-identical, so its ETag and checksum are too)."""
    from engine.labels.parts import write_label_stls

    _, models, _, paths = written
    again = write_label_stls(models, tmp_path)
    assert again["labels.zip"].read_bytes() == paths["labels.zip"].read_bytes()
    with zipfile.ZipFile(again["labels.zip"]) as zf:
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_label_uploads_are_found_by_content(tmp_path: Path) -> None:
    from engine.labels.uploads import find_label_upload

    lv = headsq_labels()
    (tmp_path / "upload").write_bytes(nifti_bytes(lv))  # stored without its name, as the service stores it
    assert find_label_upload(tmp_path / "upload").kind == "nifti-gz"
    raw = nib.Nifti1Image(np.zeros((4, 4, 4), np.float32), np.eye(4)).to_bytes()
    (tmp_path / "float").write_bytes(raw)
    with pytest.raises(NotLabelsError, match="not integer"):
        find_label_upload(tmp_path / "float")
    one, two, none = (tmp_path / f"{n}.zip" for n in ("one", "two", "none"))
    with zipfile.ZipFile(one, "w") as zf:
        zf.writestr("seg/halves.nii.gz", nifti_bytes(lv))
        zf.writestr("notes.txt", "hello")
    with zipfile.ZipFile(two, "w") as zf:
        zf.writestr("a.nii.gz", nifti_bytes(lv))
        zf.writestr("b.nii.gz", nifti_bytes(lv))
    with zipfile.ZipFile(none, "w") as zf:
        zf.writestr("notes.txt", "hello")
    found = find_label_upload(one)
    assert (found.kind, found.member) == ("nifti-gz", "seg/halves.nii.gz")
    with pytest.raises(InputError, match="2 label maps"):
        find_label_upload(two)
    assert find_label_upload(none) is None
    with pytest.raises(NotLabelsError, match="no label map"):
        find_label_upload(none, force=True)


def test_a_label_job_reads_a_zipped_map_and_crops_it(tmp_path: Path) -> None:
    """``engine.job.run_job`` finds the label map in a nameless upload by its content, as the worker runs it."""
    from engine.job import InputSpec, JobSpec, resolve_runtime, run_job
    from engine.params import RoiParams

    lv = headsq_labels()
    with zipfile.ZipFile(tmp_path / "upload", "w") as zf:
        zf.writestr("halves.nii.gz", nifti_bytes(lv))
    roi = RoiParams(((0, 60), (0, 64), (0, 64)))
    spec = JobSpec(recon=ReconParams.from_dict(BUDGETS), input=InputSpec(roi=roi))
    result = run_job(tmp_path / "upload", tmp_path / "out", spec, resolve_runtime("cpu"))
    paths, report = result.paths, result.report
    assert result.plan == "labels" and result.volume is None
    assert list(paths) == list(engine_files(labels=True))
    assert report["input"]["shape_zyx"] == [60, 64, 64] and [r["value"] for r in report["labels"]] == [1, 2]
    assert report["source"]["file"] == "halves.nii.gz"


def seg_zip(with_ct: bool = True) -> bytes:
    """A zip of a DICOM SEG (binary, highdicom) of the headsq bone halves and, ``with_ct``, the CT series it was
    drawn on (the scan on the map's rotated grid)."""
    import pydicom

    from tests.engine.labels.test_labels_io import _ct_files, _seg
    from tests.engine.labels.test_labels_util import headsq_data

    lv = headsq_labels()
    ct = _ct_files(lv, headsq_data(), pydicom.uid.generate_uid())
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("study/seg/seg.dcm", _seg(ct, lv.labels, "BINARY"))
        for name, data in ct.items() if with_ct else ():
            zf.writestr(f"study/ct/{name}", data)
    return buf.getvalue()


def test_seg_nrrd_and_dicom_seg_uploads(tmp_path: Path) -> None:
    """A Slicer .seg.nrrd stored without its name, and a DICOM SEG zipped with its CT, read as the worker reads them:
    the segments' names from the files; a zip of a SEG without its CT is refused."""
    import nrrd

    from engine.errors import MissingReferenceError
    from engine.labels.uploads import find_label_upload, read_label_upload

    lv = headsq_labels()
    header = {
        "space": "left-posterior-superior",
        "space origin": np.asarray(lv.origin_mm),
        "space directions": (np.asarray(lv.direction) * np.asarray(lv.spacing_zyx_mm[::-1])).T,
        "kinds": ["domain"] * 3,
        **{f"Segment{i}_{k}": v for i, name in enumerate(("femur", "tibia")) for k, v in
           (("ID", name), ("Name", name), ("Color", "0.9 0.2 0.1"), ("LabelValue", str(i + 1)), ("Layer", "0"))},
    }  # fmt: skip
    nrrd.write(str(tmp_path / "seg.nrrd"), lv.labels.transpose(2, 1, 0).copy(), header)
    (tmp_path / "seg.nrrd").rename(tmp_path / "upload")
    found = find_label_upload(tmp_path / "upload")
    assert found.kind == "nrrd"
    assert [s.name for s in read_label_upload(tmp_path / "upload", found).segments] == ["femur", "tibia"]
    (tmp_path / "seg.zip").write_bytes(seg_zip())
    found = find_label_upload(tmp_path / "seg.zip")
    assert found.kind == "dicom-seg"
    got = read_label_upload(tmp_path / "seg.zip", found)
    assert [s.name for s in got.segments] == ["right half", "left half"]
    np.testing.assert_array_equal(got.labels, lv.labels)
    (tmp_path / "alone.zip").write_bytes(seg_zip(with_ct=False))
    with pytest.raises(MissingReferenceError, match="the CT series it was drawn on"):
        find_label_upload(tmp_path / "alone.zip")


def test_a_pacs_folder_of_seg_and_ct_and_the_segments_asked(tmp_path: Path) -> None:
    """A folder as a PACS job leaves it (the SEG, its CT under ``reference/``) is a SEG upload read on its CT, whose
    completeness the label map carries; ``select_segments`` keeps the segments asked by number or name, and refuses
    one the map lacks, naming those it has; a folder with the SEG alone is refused."""
    from engine.errors import MissingReferenceError
    from engine.labels.pieces import select_segments
    from engine.labels.uploads import find_label_upload, read_label_upload

    with zipfile.ZipFile(io.BytesIO(seg_zip())) as zf:
        for name in zf.namelist():
            target = tmp_path / "upload" / ("reference" if "/ct/" in name else "") / Path(name).name
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(zf.read(name))
    found = find_label_upload(tmp_path / "upload")
    assert found.kind == "dicom-seg"
    lv = read_label_upload(tmp_path / "upload", found)
    reference = lv.source["reference"]
    assert reference["images"] == lv.labels.shape[0]
    assert reference["completeness"]["checked"] and reference["completeness"]["complete"]

    left = select_segments(lv, ["LEFT HALF"])
    assert [s.name for s in left.segments] == ["left half"]
    assert set(np.unique(left.labels).tolist()) == {0, 2}
    np.testing.assert_array_equal(left.labels == 2, lv.labels == 2)
    assert [s.value for s in select_segments(lv, [1, "2"]).segments] == [1, 2]
    with pytest.raises(InputError, match=r"no segment 'femur'; it has 1 'right half', 2 'left half'"):
        select_segments(lv, ["femur"])

    for f in (tmp_path / "upload" / "reference").iterdir():
        f.unlink()
    with pytest.raises(MissingReferenceError, match="without the CT series it was drawn on"):
        find_label_upload(tmp_path / "upload")
