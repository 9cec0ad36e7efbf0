"""PACS integration against a real Orthanc: series sent with a C-STORE SCU (pynetdicom) to a real ``bonemesh pacs``
run as jobs by a real API and worker; the model comes back into Orthanc as Encapsulated STL (by C-STORE, or by
STOW-RS for a series pulled over DICOMweb), and decodes to the job's ``model.stl``.

One Orthanc, one redis/API/worker stack and one ``bonemesh pacs`` (``tests.service.pacs_env``, shared with the
other PACS modules) serve the whole module (the last test stops and restarts Orthanc). Series are small and
generated (``tests.engine.dicom_factory``), plus the real head phantom from ../shared/data when it is present.
"""

from __future__ import annotations

import io
import json
import time
import zipfile
from typing import Any

import httpx
import numpy as np
import pydicom
import pytest

from engine.export.stl import from_stl
from tests.conftest import SHARED_DATA
from tests.engine.dicom_factory import FRAME_OF_REFERENCE_UID, PATIENT
from tests.service.pacs_env import (
    ORIGIN,
    SCU_AE,
    SHAPE,
    SPACING,
    STABLE_SECONDS,
    Pacs,
    assert_no_patient_data,
    c_store,
    check_model_in_orthanc,
    download,
    generated_series,
    jobs_of_series,
    wait_delivered,
)
from tests.service.procs import wait_for_job, wait_until

pytest.importorskip("pynetdicom", reason="the PACS tests need pynetdicom (pip install 'bonemesh[pacs]')")

HEAD_PHANTOM = SHARED_DATA / "head_phantom_dicom" / "head_phantom_dicom.zip"


@pytest.fixture(scope="module")
def client(pacs_client: httpx.Client) -> httpx.Client:
    return pacs_client


# -- tests ------------------------------------------------------------------------------------------------------
def test_generated_series_comes_back_as_encapsulated_stl(pacs: Pacs, client: httpx.Client) -> None:
    files, study, series_uid = generated_series()
    assert c_store(files, pacs.port) == [0] * len(files)
    (job,) = wait_until(lambda: jobs_of_series(client, series_uid), 60, "the series' job")
    assert job["source"] == {
        "kind": "dimse",
        "calling_ae": SCU_AE,
        "study_uid": study,
        "series_uid": series_uid,
        "images": len(files),
        "rule": "bone",
    }
    job = wait_delivered(pacs, client, job["id"])
    names = {o["name"] for o in job["outputs"]}
    assert {"model.stl", "model.dcm", "phone.glb", "ar.glb", "report.json"} <= names
    ds = check_model_in_orthanc(pacs, job, study)
    assert ds.FrameOfReferenceUID == FRAME_OF_REFERENCE_UID
    assert str(ds.PatientName) == PATIENT["PatientName"] and ds.PatientID == PATIENT["PatientID"]
    # in patient mm: inside the series' box, far from the grid origin
    verts, _ = from_stl(download(job, "model.stl"))
    xyz = verts[:, ::-1]
    extent = np.array([(SHAPE[2] - 1) * SPACING[2], (SHAPE[1] - 1) * SPACING[1], (SHAPE[0] - 1) * SPACING[0]])
    assert np.all(xyz.min(axis=0) >= ORIGIN - 1e-3) and np.all(xyz.max(axis=0) <= ORIGIN + extent + 1e-3)
    assert_no_patient_data(pacs, job, PATIENT)


@pytest.mark.skipif(not HEAD_PHANTOM.exists(), reason="../shared/data/head_phantom_dicom is absent")
def test_real_series_comes_back_into_its_study(pacs: Pacs, client: httpx.Client) -> None:
    with zipfile.ZipFile(HEAD_PHANTOM) as zf:
        files = [zf.read(n) for n in zf.namelist() if not n.endswith(("/", "DIRFILE"))]
    first = pydicom.dcmread(io.BytesIO(files[0]), stop_before_pixels=True)
    assert c_store(files, pacs.port) == [0] * len(files)
    (job,) = wait_until(lambda: jobs_of_series(client, first.SeriesInstanceUID), 60, "the series' job")
    job = wait_delivered(pacs, client, job["id"], timeout=600)
    ds = check_model_in_orthanc(pacs, job, first.StudyInstanceUID)
    assert ds.FrameOfReferenceUID == first.FrameOfReferenceUID
    identity = {k: str(first.get(k, "")) for k in ("PatientName", "PatientID", "PatientBirthDate")}
    assert_no_patient_data(pacs, job, identity)


def test_unlisted_callers_and_other_sop_classes_are_refused(pacs: Pacs) -> None:
    files, _, _ = generated_series()
    assoc = c_store(files[:1], pacs.port, calling="STRANGER")
    assert not isinstance(assoc, list) and assoc.is_rejected
    mr = c_store(files[:1], pacs.port, sop_class="1.2.840.10008.5.1.4.1.1.4")  # MR Image Storage: not offered
    assert not isinstance(mr, list) and not mr.is_rejected and not mr.accepted_contexts, mr  # context refused
    assert "calling AE 'STRANGER' is not on the allow-list" in pacs.gateway.tail()


def test_two_bursts_are_one_job_and_a_resent_series_is_another(pacs: Pacs, client: httpx.Client) -> None:
    files, _, series_uid = generated_series()
    scout, _, scout_uid = generated_series(image_type=("ORIGINAL", "PRIMARY", "LOCALIZER"))
    assert c_store(files[:10], pacs.port) == [0] * 10
    time.sleep(STABLE_SECONDS / 3)
    assert c_store([*files[5:], *scout[:12]], pacs.port) == [0] * (len(files) - 5 + 12)  # 5 repeated
    (job,) = wait_until(lambda: jobs_of_series(client, series_uid), 60, "the series' job")
    assert job["source"]["images"] == len(files)
    job = wait_for_job(client, job["id"], stack=pacs.stack, timeout=300)
    assert job["state"] == "succeeded", json.dumps(job)
    wait_until(lambda: f"series {scout_uid} of study" in pacs.gateway.tail(20000), 30, "the scout's log line")
    assert "ignored: not a volume: Image Type LOCALIZER" in pacs.gateway.tail(20000)
    assert jobs_of_series(client, scout_uid) == []

    assert c_store(files, pacs.port) == [0] * len(files)  # re-sent after its job ran: one more job, whole
    jobs = wait_until(lambda: (j := jobs_of_series(client, series_uid)) and len(j) == 2 and j, 60, "a second job")
    assert sorted(j["source"]["images"] for j in jobs) == [len(files), len(files)]
    assert len({j["delivery"]["series_instance_uid"] for j in jobs}) == 2


def test_dicomweb_series_is_pulled_and_stored_back(pacs: Pacs, client: httpx.Client) -> None:
    from dicomweb_client.api import DICOMwebClient

    files, study, series_uid = generated_series()
    DICOMwebClient(pacs.orthanc.dicomweb_url).store_instances([pydicom.dcmread(io.BytesIO(f)) for f in files])
    body = {
        "source": {"dicomweb": {"server": "orthanc", "study_uid": study, "series_uid": series_uid}},
        "params": {"preset": "bone"},
    }
    resp = client.post("/v1/jobs", json=body)
    assert resp.status_code == 202, resp.text
    job = resp.json()
    assert job["source"]["kind"] == "dicomweb" and job["delivery"]["destination"] == {
        "kind": "dicomweb",
        "server": "orthanc",
    }
    job = wait_delivered(pacs, client, job["id"])
    check_model_in_orthanc(pacs, job, study)
    bad = client.post("/v1/jobs", json={**body, "source": {"dicomweb": {**body["source"]["dicomweb"], "server": "x"}}})
    assert bad.status_code == 422 and "unknown DICOMweb server" in bad.json()["detail"]


def test_delivery_is_retried_until_orthanc_is_back(pacs: Pacs, client: httpx.Client) -> None:
    files, study, series_uid = generated_series()
    pacs.orthanc.stop()
    try:
        assert c_store(files, pacs.port) == [0] * len(files)
        (job,) = wait_until(lambda: jobs_of_series(client, series_uid), 60, "the series' job")

        def retried(j: dict[str, Any]) -> bool:
            return j["state"] != "running" and j["state"] != "queued" and j["delivery"]["attempts"] >= 2

        job = wait_for_job(client, job["id"], stack=pacs.stack, timeout=300, until=retried)
        assert job["state"] == "succeeded" and job["delivery"]["state"] in ("retrying", "sending"), json.dumps(job)
        assert job["delivery"]["error"] and "C-STORE" in job["delivery"]["error"]
        assert {o["name"] for o in job["outputs"]} >= {"model.stl", "model.dcm"}  # links work meanwhile
    finally:
        pacs.orthanc.start()
    job = wait_delivered(pacs, client, job["id"], timeout=120)
    check_model_in_orthanc(pacs, job, study)
