"""A wrong model never reaches a patient's study, against the real Orthanc, API, worker and ``bonemesh pacs``:
a series with a slice removed fails ``incomplete_series`` by C-STORE and by DICOMweb, and nothing goes back; a
delivered model references its series and exactly its images, and ``POST /v1/jobs/{id}/deliver`` puts it back
(same UIDs) after the PACS lost it; a multi-frame Enhanced CT sent by C-STORE becomes a model like its
single-frame twin's."""

from __future__ import annotations

import io
import json
from typing import Any

import httpx
import pydicom
import pytest

from tests.service.pacs_env import (
    Pacs,
    c_store,
    check_model_in_orthanc,
    download,
    generated_series,
    jobs_of_series,
    wait_delivered,
)
from tests.service.procs import wait_for_job, wait_until

pytest.importorskip("pynetdicom", reason="the PACS tests need pynetdicom (pip install 'bonemesh[pacs]')")
pytest.importorskip("dicomweb_client", reason="DICOMweb needs dicomweb-client (pip install 'bonemesh[pacs]')")

REMOVED = 11  # the slice left out (of 24)


@pytest.fixture(scope="module")
def client(pacs_client: httpx.Client) -> httpx.Client:
    return pacs_client


def _failed(pacs: Pacs, client: httpx.Client, job_id: str) -> dict[str, Any]:
    job = wait_for_job(client, job_id, stack=pacs.stack, timeout=300)
    assert job["state"] == "failed", json.dumps(job)
    return job


def _nothing_delivered(pacs: Pacs, job: dict[str, Any], study: str) -> None:
    assert job["error"]["code"] == "incomplete_series", job["error"]
    assert "1 slice(s) missing between" in job["error"]["message"], job["error"]
    assert job["outputs"] in (None, []) and job["delivery"]["state"] == "skipped", json.dumps(job)
    assert job["delivery"]["attempts"] == 0
    assert pacs.orthanc.instances_of(study, "M3D") == []


def test_cstore_series_with_a_slice_removed_fails_and_nothing_goes_back(pacs: Pacs, client: httpx.Client) -> None:
    files, study, series_uid = generated_series()
    del files[REMOVED]
    assert c_store(files, pacs.port) == [0] * len(files)
    (job,) = wait_until(lambda: jobs_of_series(client, series_uid), 60, "the series' job")
    _nothing_delivered(pacs, _failed(pacs, client, job["id"]), study)


def test_dicomweb_series_with_a_slice_removed_fails_and_nothing_goes_back(pacs: Pacs, client: httpx.Client) -> None:
    """The server holds 23 of 24 images: the fetch is complete (every listed instance arrives), the series is not."""
    from dicomweb_client.api import DICOMwebClient

    files, study, series_uid = generated_series()
    del files[REMOVED]
    DICOMwebClient(pacs.orthanc.dicomweb_url).store_instances([pydicom.dcmread(io.BytesIO(f)) for f in files])
    body = {"source": {"dicomweb": {"server": "orthanc", "study_uid": study, "series_uid": series_uid}}}
    resp = client.post("/v1/jobs", json=body)
    assert resp.status_code == 202, resp.text
    _nothing_delivered(pacs, _failed(pacs, client, resp.json()["id"]), study)


def _m3d_ids(pacs: Pacs, study: str) -> list[str]:
    query = {"Level": "Instance", "Query": {"StudyInstanceUID": study, "Modality": "M3D"}}
    return list(pacs.orthanc.post("/tools/find", query))


def test_model_references_its_images_and_is_delivered_again(pacs: Pacs, client: httpx.Client) -> None:
    files, study, series_uid = generated_series()
    sent = {pydicom.dcmread(io.BytesIO(f)).SOPInstanceUID for f in files}
    assert c_store(files, pacs.port) == [0] * len(files)
    (job,) = wait_until(lambda: jobs_of_series(client, series_uid), 60, "the series' job")
    job = wait_delivered(pacs, client, job["id"])
    ds = check_model_in_orthanc(pacs, job, study)
    assert {r.ReferencedSOPInstanceUID for r in ds.SourceInstanceSequence} == sent
    (ref,) = ds.ReferencedSeriesSequence
    assert ref.SeriesInstanceUID == series_uid
    assert {r.ReferencedSOPInstanceUID for r in ref.ReferencedInstanceSequence} == sent
    report = json.loads(download(job, "report.json"))
    assert report["input"]["source"]["completeness"]["images_used"] == len(files)
    assert report["input"]["source"]["series"]["used"]["uid"] == series_uid

    # the PACS loses the model; the job sends it again, with the same UIDs
    (orthanc_id,) = _m3d_ids(pacs, study)
    httpx.delete(f"{pacs.orthanc.url}/instances/{orthanc_id}", timeout=30).raise_for_status()
    assert _m3d_ids(pacs, study) == []
    assert httpx.post(f"{pacs.stack.base_url}/v1/jobs/{job['id']}/deliver", timeout=30).status_code == 401
    resp = client.post(f"/v1/jobs/{job['id']}/deliver")
    assert resp.status_code == 202, resp.text
    assert resp.json()["delivery"]["state"] in ("waiting", "sending", "delivered")
    again = wait_delivered(pacs, client, job["id"])
    assert again["delivery"]["sop_instance_uid"] == job["delivery"]["sop_instance_uid"]
    back = check_model_in_orthanc(pacs, again, study)
    assert back.SOPInstanceUID == ds.SOPInstanceUID and len(_m3d_ids(pacs, study)) == 1


def test_enhanced_ct_by_cstore_becomes_a_model(pacs: Pacs, client: httpx.Client) -> None:
    from tests.engine.multiframe_factory import enhanced_ct

    files, study, series_uid = generated_series()
    enhanced = enhanced_ct(files, order=list(reversed(range(len(files)))), series_uid=series_uid)
    uid = pydicom.dcmread(io.BytesIO(enhanced), stop_before_pixels=True).SOPInstanceUID
    assert c_store([enhanced], pacs.port) == [0]
    (job,) = wait_until(lambda: jobs_of_series(client, series_uid), 60, "the series' job")
    assert job["source"]["images"] == len(files)
    job = wait_delivered(pacs, client, job["id"])
    ds = check_model_in_orthanc(pacs, job, study)
    assert [r.ReferencedSOPInstanceUID for r in ds.SourceInstanceSequence] == [uid]
    report = json.loads(download(job, "report.json"))
    assert report["input"]["source"]["completeness"]["images_used"] == len(files)
    assert report["input"]["source"]["files"] == 1
