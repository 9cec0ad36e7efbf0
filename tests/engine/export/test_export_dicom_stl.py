"""Encapsulated STL export: the IOD's attributes, the STL inside it, and dicom3tools' ``dciodvfy`` when present."""

from __future__ import annotations

import datetime as dt
import io
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pydicom
import pytest
import trimesh

from engine.export.dicom_stl import ENCAPSULATED_STL_STORAGE, stl_of, to_encapsulated_stl
from engine.export.stl import from_stl, to_stl
from tests.engine.dicom_factory import PATIENT, ct_slice


def _source() -> pydicom.Dataset:
    data = ct_slice(np.zeros((4, 4), np.uint16), ipp=(0, 0, 0), series_uid="1.2.3.4", instance=1)
    ds = pydicom.dcmread(io.BytesIO(data))
    ds.FrameOfReferenceUID = "1.2.826.0.1.3680043.8.498.77"
    ds.StudyDate, ds.StudyTime, ds.AccessionNumber = "20240102", "101010", "ACC1"
    return ds


def _box_lps() -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=[10.0, 20.0, 30.0])
    box.apply_translation([-120.0, -90.0, 640.0])  # far from the origin, like a patient
    return box.vertices[:, ::-1].astype(np.float32), box.faces.astype(np.int32)


def _encode(**kw: object) -> bytes:
    verts, faces = _box_lps()
    args: dict[str, object] = {
        "series_instance_uid": "1.2.826.0.1.3680043.8.498.100",
        "sop_instance_uid": "1.2.826.0.1.3680043.8.498.101",
        "software_version": "0.1.0",
        "created": dt.datetime(2024, 5, 6, 7, 8, 9, tzinfo=dt.UTC),
        "source_instances": [("1.2.840.10008.5.1.4.1.1.2", "1.2.826.0.1.3680043.8.498.5")],
    }
    args.update(kw)
    return to_encapsulated_stl(verts, faces, _source(), **args)  # type: ignore[arg-type]


def test_attributes_follow_the_iod_and_the_source() -> None:
    src = _source()
    ds = pydicom.dcmread(io.BytesIO(_encode()))
    assert ds.SOPClassUID == ENCAPSULATED_STL_STORAGE == ds.file_meta.MediaStorageSOPClassUID
    assert ds.Modality == "M3D"
    assert ds.MIMETypeOfEncapsulatedDocument == "model/stl"
    # same patient, same study, same frame of reference; a series of its own
    assert str(ds.PatientName) == PATIENT["PatientName"] and ds.PatientID == PATIENT["PatientID"]
    assert ds.PatientBirthDate == PATIENT["PatientBirthDate"]
    assert ds.StudyInstanceUID == src.StudyInstanceUID
    assert ds.AccessionNumber == "ACC1" and ds.StudyDate == "20240102"
    assert ds.FrameOfReferenceUID == src.FrameOfReferenceUID
    assert ds.SeriesInstanceUID == "1.2.826.0.1.3680043.8.498.100" != src.SeriesInstanceUID
    (unit,) = ds.MeasurementUnitsCodeSequence
    assert (unit.CodeValue, unit.CodingSchemeDesignator) == ("mm", "UCUM")
    assert (ds.Manufacturer, ds.ManufacturerModelName, ds.SoftwareVersions) == ("bonemesh", "bonemesh", "0.1.0")
    assert ds.SourceInstanceSequence[0].ReferencedSOPInstanceUID == "1.2.826.0.1.3680043.8.498.5"


def test_the_stl_inside_is_the_mesh_in_patient_mm() -> None:
    verts, faces = _box_lps()
    data = stl_of(_encode())
    assert data[80:] == to_stl(verts, faces)[80:]
    got_v, got_f = from_stl(data)
    mesh = trimesh.Trimesh(got_v[:, ::-1], got_f, process=False)
    assert mesh.is_watertight and mesh.volume == pytest.approx(6000.0)
    np.testing.assert_allclose(mesh.bounds, [[-125, -100, 625], [-115, -80, 655]], atol=1e-4)


def test_refuses_a_source_without_frame_of_reference() -> None:
    verts, faces = _box_lps()
    src = _source()
    del src.FrameOfReferenceUID
    with pytest.raises(ValueError, match="FrameOfReferenceUID"):
        to_encapsulated_stl(
            verts,
            faces,
            src,
            series_instance_uid="1.2",
            sop_instance_uid="1.3",
            software_version="0",
            created=dt.datetime(2024, 1, 1, tzinfo=dt.UTC),
        )


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dicom3tools' dciodvfy is not installed")
def test_dciodvfy_finds_no_error(tmp_path: Path) -> None:
    path = tmp_path / "model.dcm"
    path.write_bytes(_encode())
    out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    text = out.stdout + out.stderr
    errors = [line for line in text.splitlines() if line.startswith("Error")]
    assert "EncapsulatedSTL" in text or "Encapsulated STL" in text, text
    assert not errors, text
