"""Segmentations from the PACS against a real Orthanc (issue 30): a DICOM SEG sent by C-STORE after its CT series
(made a job, or kept when no rule takes it), and one pulled over DICOMweb with the CT it references, become label
jobs (a model per segment) whose models go back into the study as one Encapsulated STL per segment (or per segment
asked for); a SEG whose CT never comes fails saying so, and nothing is delivered.

Shares the PACS environment of ``tests.service.pacs_env`` (Orthanc, redis, API, worker, ``bonemesh pacs``).
"""

from __future__ import annotations

import io
import json
import warnings
import zipfile
from typing import Any

import httpx
import numpy as np
import pydicom
import pytest

from engine.export.dicom_stl import ENCAPSULATED_STL_STORAGE, stl_of
from engine.export.stl import from_stl
from tests.conftest import SHARED_DATA
from tests.engine.dicom_factory import FRAME_OF_REFERENCE_UID, PATIENT
from tests.service.pacs_env import (
    ORIGIN,
    SHAPE,
    SPACING,
    Pacs,
    assert_no_patient_data,
    c_store,
    download,
    generated_series,
    jobs_of_series,
    wait_delivered,
)
from tests.service.procs import wait_for_job, wait_until

pytest.importorskip("pynetdicom", reason="the PACS tests need pynetdicom (pip install 'bonemesh[pacs]')")
pytest.importorskip("highdicom", reason="the SEG tests make their SEG with highdicom")

NAMES = ("right half", "left half")  # the segments of tests.engine.labels.test_labels_io._seg, numbers 1 and 2
HEAD_PHANTOM = SHARED_DATA / "head_phantom_dicom" / "head_phantom_dicom.zip"


@pytest.fixture(scope="module")
def client(pacs_client: httpx.Client) -> httpx.Client:
    return pacs_client


def ball_halves() -> np.ndarray:
    """The generated series' bone ball split at its centre along x: 1 on the right (-x), 2 on the left."""
    nz, ny, nx = SHAPE
    dz, dy, dx = SPACING
    kk, jj, ii = np.mgrid[0:nz, 0:ny, 0:nx]
    xyz = ORIGIN + np.stack([ii * dx, jj * dy, kk * dz], axis=-1)
    centre = ORIGIN + np.array([(nx - 1) * dx, (ny - 1) * dy, (nz - 1) * dz]) / 2
    ball = np.linalg.norm(xyz - centre, axis=-1) < 7.0
    return np.where(ball, np.where(xyz[..., 0] < centre[0], 1, 2), 0).astype(np.uint8)


def ct_and_seg(**kwargs: Any) -> tuple[list[bytes], bytes, str, str, str]:
    """A generated CT series (``kwargs``: ``generated_series``'s) and a SEG (binary, highdicom) of its ball's halves:
    CT files, SEG file, study, CT series, SEG series."""
    from tests.engine.labels.test_labels_io import _seg

    files, study, series_uid = generated_series(**kwargs)
    seg = _seg({f"IM{k}": f for k, f in enumerate(files)}, ball_halves(), "BINARY")
    return files, seg, study, series_uid, pydicom.dcmread(io.BytesIO(seg)).SeriesInstanceUID


def label_models_in_orthanc(
    pacs: Pacs, job: dict[str, Any], study: str, frame: str = FRAME_OF_REFERENCE_UID
) -> dict[str, pydicom.Dataset]:
    """The job's Encapsulated STL objects in Orthanc, by Document Title; each in the CT's Frame of Reference
    (``frame``) and decoding to its labels.zip STL."""
    found = [pydicom.dcmread(io.BytesIO(b)) for b in pacs.orthanc.instances_of(study, "M3D")]
    mine = [ds for ds in found if ds.SeriesInstanceUID == job["delivery"]["series_instance_uid"]]
    stls = zipfile.ZipFile(io.BytesIO(download(job, "labels.zip")))
    report = json.loads(download(job, "report.json"))
    by_title = {}
    for ds in mine:
        assert ds.SOPClassUID == ENCAPSULATED_STL_STORAGE and ds.Modality == "M3D" and ds.StudyInstanceUID == study
        assert ds.FrameOfReferenceUID == frame
        assert ds.MeasurementUnitsCodeSequence[0].CodeValue == "mm"
        (row,) = [r for r in report["labels"] if r["name"] == ds.DocumentTitle]
        got_v, got_f = from_stl(stl_of(_bytes(ds)))
        want_v, want_f = from_stl(stls.read(row["file"]))
        np.testing.assert_allclose(got_v, want_v, rtol=0, atol=1e-6)
        np.testing.assert_array_equal(got_f, want_f)
        by_title[str(ds.DocumentTitle)] = ds
    assert len(by_title) == len(mine)  # one object per segment
    return by_title


def _bytes(ds: pydicom.Dataset) -> bytes:
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()


def test_a_seg_after_its_ct_comes_back_as_a_model_per_segment(pacs: Pacs, client: httpx.Client) -> None:
    files, seg, study, ct_uid, seg_uid = ct_and_seg()
    assert c_store(files, pacs.port) == [0] * len(files)
    (ct_job,) = wait_until(lambda: jobs_of_series(client, ct_uid), 60, "the CT's job")
    assert c_store([seg], pacs.port) == [0]
    (job,) = wait_until(lambda: jobs_of_series(client, seg_uid), 60, "the SEG's job")
    assert job["source"]["rule"] == "segments"
    job = wait_delivered(pacs, client, job["id"])
    names = {o["name"] for o in job["outputs"]}
    assert {"labels.zip", "labels.dcm.zip", "model.glb", "report.json"} <= names and "model.dcm" not in names
    assert job["delivery"]["sop_instance_uid"] is None
    models = label_models_in_orthanc(pacs, job, study)
    assert sorted(models) == sorted(NAMES)
    seg_ds = pydicom.dcmread(io.BytesIO(seg))
    for ds in models.values():  # each refers to the SEG it was made from, with the SEG's patient
        ref = ds.SourceInstanceSequence[0]
        assert (ref.ReferencedSOPClassUID, ref.ReferencedSOPInstanceUID) == (seg_ds.SOPClassUID, seg_ds.SOPInstanceUID)
        assert str(ds.PatientName) == PATIENT["PatientName"]
    report = json.loads(download(job, "report.json"))
    assert report["source"]["reference"]["completeness"]["complete"] is True
    assert_no_patient_data(pacs, job, PATIENT)
    wait_delivered(pacs, client, ct_job["id"])  # the CT's own bone model went back too


def test_a_seg_on_a_ct_no_rule_takes_finds_the_kept_series(pacs: Pacs, client: httpx.Client) -> None:
    files, seg, study, ct_uid, seg_uid = ct_and_seg(description="planning CT, no model")
    assert c_store(files, pacs.port) == [0] * len(files)
    wait_until(lambda: f"series {ct_uid} of study" in pacs.gateway.tail(20000), 60, "the CT's routing")
    assert "for a SEG drawn on it" in pacs.gateway.tail(20000) and jobs_of_series(client, ct_uid) == []
    assert c_store([seg], pacs.port) == [0]
    (job,) = wait_until(lambda: jobs_of_series(client, seg_uid), 60, "the SEG's job")
    job = wait_delivered(pacs, client, job["id"])
    assert sorted(label_models_in_orthanc(pacs, job, study)) == sorted(NAMES)
    assert f"its referenced series {ct_uid} taken from the kept series" in pacs.gateway.tail(20000)


def test_a_seg_pulled_over_dicomweb_brings_its_ct_and_only_the_segment_asked(pacs: Pacs, client: httpx.Client) -> None:
    from dicomweb_client.api import DICOMwebClient

    files, seg, study, _, seg_uid = ct_and_seg()
    DICOMwebClient(pacs.orthanc.dicomweb_url).store_instances([pydicom.dcmread(io.BytesIO(f)) for f in [*files, seg]])
    source = {"dicomweb": {"server": "orthanc", "study_uid": study, "series_uid": seg_uid}}
    resp = client.post("/v1/jobs", json={"source": source, "params": {"segments": ["Left Half"]}})
    assert resp.status_code == 202, resp.text
    job = wait_delivered(pacs, client, resp.json()["id"])
    models = label_models_in_orthanc(pacs, job, study)
    assert list(models) == ["left half"]
    report = json.loads(download(job, "report.json"))
    assert [r["name"] for r in report["labels"]] == ["left half"]

    resp = client.post("/v1/jobs", json={"source": source, "params": {"segments": ["femur"]}})
    job = wait_for_job(client, resp.json()["id"], stack=pacs.stack, timeout=300)
    assert job["state"] == "failed" and job["error"]["code"] == "bad_input", json.dumps(job)
    assert "no segment 'femur'" in job["error"]["message"] and "'left half'" in job["error"]["message"]
    assert job["delivery"]["state"] == "skipped"


def test_a_seg_whose_ct_is_not_on_the_server_fails_and_delivers_nothing(pacs: Pacs, client: httpx.Client) -> None:
    from dicomweb_client.api import DICOMwebClient

    _, seg, study, ct_uid, seg_uid = ct_and_seg()  # the CT is never stored
    DICOMwebClient(pacs.orthanc.dicomweb_url).store_instances([pydicom.dcmread(io.BytesIO(seg))])
    source = {"dicomweb": {"server": "orthanc", "study_uid": study, "series_uid": seg_uid}}
    resp = client.post("/v1/jobs", json={"source": source})
    job = wait_for_job(client, resp.json()["id"], stack=pacs.stack, timeout=300)
    assert job["state"] == "failed" and job["error"]["code"] == "source_unavailable", json.dumps(job)
    assert f"referenced series {ct_uid}" in job["error"]["message"]
    assert job["delivery"]["state"] == "skipped" and not job["outputs"]


def test_a_received_seg_whose_ct_never_comes_fails_saying_so(pacs: Pacs, client: httpx.Client) -> None:
    _, seg, _, ct_uid, seg_uid = ct_and_seg()
    assert c_store([seg], pacs.port) == [0]
    (job,) = wait_until(lambda: jobs_of_series(client, seg_uid), 60, "the SEG's job (after the wait for its CT)")
    job = wait_for_job(client, job["id"], stack=pacs.stack, timeout=300)
    assert job["state"] == "failed" and job["error"]["code"] == "bad_input", json.dumps(job)
    assert "without the CT series it was drawn on" in job["error"]["message"]
    assert f"referenced series {ct_uid} was not received" in pacs.gateway.tail(20000)
    assert job["delivery"]["state"] == "skipped"


@pytest.mark.skipif(not HEAD_PHANTOM.exists(), reason="../shared/data/head_phantom_dicom is absent")
def test_a_seg_of_a_real_skull_split_at_the_midline_comes_back_per_half(pacs: Pacs, client: httpx.Client) -> None:
    """The head phantom (28 x 512 x 512 CT) and a SEG of its bone (300 HU) split at the bone's mid-sagittal plane,
    both stored in Orthanc: the job pulls the SEG and its CT, and each half comes back as its own model, watertight,
    with the volume of its voxels (the halves touch along the midline and stay apart)."""
    from dicomweb_client.api import DICOMwebClient

    from tests.engine.labels.test_labels_io import _seg

    with zipfile.ZipFile(HEAD_PHANTOM) as zf:
        files = [zf.read(n) for n in zf.namelist() if not n.endswith(("/", "DIRFILE"))]
    slices = [(pydicom.dcmread(io.BytesIO(f)), f) for f in files if f[128:132] == b"DICM"]
    ordered = sorted(slices, key=lambda pair: float(pair[0].ImagePositionPatient[2]))
    stored = np.stack([ds.pixel_array for ds, _ in ordered])
    bone = stored >= 1324  # 300 HU (stored = HU + 1024), the scan's README
    centre = np.nonzero(bone)[2].mean()
    labels = np.where(bone, np.where(np.arange(stored.shape[2]) < centre, 1, 2), 0).astype(np.uint8)
    with warnings.catch_warnings():  # the phantom's patient name "HEAD" has one component: highdicom warns
        warnings.filterwarnings("ignore", "The string .* is unlikely to represent the intended person name")
        seg = _seg({f"CT{k}": f for k, (_, f) in enumerate(ordered)}, labels, "BINARY")
    first, seg_ds = ordered[0][0], pydicom.dcmread(io.BytesIO(seg))
    DICOMwebClient(pacs.orthanc.dicomweb_url).store_instances([ds for ds, _ in ordered] + [seg_ds])
    source = {"server": "orthanc", "study_uid": first.StudyInstanceUID, "series_uid": seg_ds.SeriesInstanceUID}
    resp = client.post("/v1/jobs", json={"source": {"dicomweb": source}})
    assert resp.status_code == 202, resp.text
    job = wait_delivered(pacs, client, resp.json()["id"], timeout=600)
    models = label_models_in_orthanc(pacs, job, first.StudyInstanceUID, first.FrameOfReferenceUID)
    assert sorted(models) == sorted(NAMES)
    step = float(ordered[1][0].ImagePositionPatient[2]) - float(first.ImagePositionPatient[2])
    voxel_mm3 = float(first.PixelSpacing[0]) * float(first.PixelSpacing[1]) * abs(step)
    for row in json.loads(download(job, "report.json"))["labels"]:
        assert row["watertight"], row
        voxels = np.count_nonzero(labels == row["value"]) * voxel_mm3
        assert 0.7 < row["volume_mm3"] / voxels < 1.3, (row, voxels)
