"""PACS integration against a real Orthanc: series sent with a C-STORE SCU (pynetdicom) to a real ``bonemesh pacs``
run as jobs by a real API and worker; the model comes back into Orthanc as Encapsulated STL (by C-STORE, or by
STOW-RS for a series pulled over DICOMweb), and decodes to the job's ``model.stl``.

One Orthanc, one redis/API/worker stack and one ``bonemesh pacs`` serve the whole module (the last test stops
and restarts Orthanc). Series are small and generated (``tests.engine.dicom_factory``), plus the real head
phantom from ../shared/data when it is present.
"""

from __future__ import annotations

import io
import json
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pydicom
import pytest
from pydicom.uid import generate_uid

from engine.export.dicom_stl import ENCAPSULATED_STL_STORAGE, stl_of
from engine.export.stl import from_stl
from tests.conftest import SHARED_DATA
from tests.engine.dicom_factory import FRAME_OF_REFERENCE_UID, PATIENT, series
from tests.service.orthanc import AE_TITLE as ORTHANC_AE
from tests.service.orthanc import OrthancServer
from tests.service.procs import (
    API_KEYS,
    Proc,
    ProcessError,
    RedisServer,
    ServiceStack,
    bonemesh_argv,
    free_port,
    wait_for_job,
    wait_until,
)

pytest.importorskip("pynetdicom", reason="the PACS tests need pynetdicom (pip install 'bonemesh[pacs]')")

PACS_AE = "BONEMESH"
SCU_AE = "STORESCU"
STABLE_SECONDS = 2.0
ORIGIN = np.array([-140.0, -160.0, -420.0])
SHAPE = (24, 36, 36)  # z, y, x
SPACING = (1.0, 0.8, 0.8)
HEAD_PHANTOM = SHARED_DATA / "head_phantom_dicom" / "head_phantom_dicom.zip"


class Pacs:
    """The module's processes: Orthanc, the stack, ``bonemesh pacs``."""

    def __init__(self, root: Path) -> None:
        self.port = free_port()
        self.orthanc = OrthancServer(root / "orthanc", modalities={"bonemesh": (PACS_AE, self.port)})
        self.redis = RedisServer(root / "redis")
        env = {
            "BONEMESH_PACS_AE_TITLE": PACS_AE,
            "BONEMESH_PACS_HOST": "127.0.0.1",
            "BONEMESH_PACS_PORT": str(self.port),
            "BONEMESH_PACS_ALLOW": f"{SCU_AE},{ORTHANC_AE}@127.0.0.1",
            "BONEMESH_PACS_STABLE_SECONDS": str(STABLE_SECONDS),
            "BONEMESH_PACS_ROUTES": json.dumps([{"name": "bone", "min_slices": 10, "params": {"preset": "bone"}}]),
            "BONEMESH_PACS_DESTINATION": json.dumps(
                {"kind": "dicom", "ae_title": ORTHANC_AE, "host": "127.0.0.1", "port": self.orthanc.dicom_port}
            ),
            "BONEMESH_PACS_DICOMWEB_SERVERS": json.dumps({"orthanc": {"url": self.orthanc.dicomweb_url}}),
            "BONEMESH_PACS_DELIVERY_BACKOFF_SECONDS": "0.5",
            "BONEMESH_PACS_DELIVERY_MAX_BACKOFF_SECONDS": "2",
            "BONEMESH_PACS_POLL_SECONDS": "0.3",
            "BONEMESH_PACS_OWNER_KEY": API_KEYS[0],
        }
        self.stack = ServiceStack(root / "stack", self.redis.url, extra_env=env)
        self.stack.start_server()
        self.stack.start_worker()
        self.gateway = Proc(
            "pacs", [*bonemesh_argv(), "pacs"], self.stack.log_dir / "pacs.log", self.stack.env, cwd=self.stack.root
        )
        self.stack.workers.append(self.gateway)  # its log with the others', checked alive while waiting
        wait_until(lambda: "listening on" in self.gateway.tail() or not self.gateway.alive(), 60, "bonemesh pacs")
        if not self.gateway.alive():
            raise ProcessError(f"bonemesh pacs exited at start:\n{self.gateway.tail()}")

    def close(self) -> None:
        self.stack.close()
        self.redis.close()
        self.orthanc.close()

    def logs_text(self) -> str:
        return "\n".join(p.log.read_text(errors="replace") for p in [*self.stack.servers, *self.stack.workers])


@pytest.fixture(scope="module")
def pacs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pacs]:
    try:
        env = Pacs(tmp_path_factory.mktemp("pacs"))
    except ProcessError as exc:
        pytest.fail(str(exc), pytrace=False)
    yield env
    env.close()


@pytest.fixture(scope="module")
def client(pacs: Pacs) -> Iterator[httpx.Client]:
    with pacs.stack.client(API_KEYS[0]) as c:
        yield c


# -- helpers ----------------------------------------------------------------------------------------------------
def generated_series(**kwargs: Any) -> tuple[list[bytes], str, str]:
    """A small CT series (a 1000 HU ball in a water cylinder, in air) far from the origin; files, study, series."""
    nz, ny, nx = SHAPE
    dz, dy, dx = SPACING
    centre = ORIGIN + np.array([(nx - 1) * dx, (ny - 1) * dy, (nz - 1) * dz]) / 2

    def hu(p: np.ndarray) -> np.ndarray:
        body = np.linalg.norm((p - centre)[..., :2], axis=-1) < 12.0
        ball = np.linalg.norm(p - centre, axis=-1) < 7.0
        return np.where(ball, 1000.0, np.where(body, 0.0, -1000.0))

    study, series_uid = generate_uid(), generate_uid()
    files = series(
        hu,
        positions_mm=[k * dz for k in range(nz)],
        shape=(ny, nx),
        pixel_spacing=(dy, dx),
        origin=ORIGIN,
        series_uid=series_uid,
        study_uid=study,
        **kwargs,
    )
    return list(files.values()), study, series_uid


def c_store(files: list[bytes], port: int, calling: str = SCU_AE, sop_class: str | None = None) -> Any:
    """Send files with a pynetdicom C-STORE SCU; the statuses, or the association when it was not established."""
    from pynetdicom import AE

    datasets = [pydicom.dcmread(io.BytesIO(f)) for f in files]
    ae = AE(ae_title=calling)
    for ds in datasets[:1]:
        ae.add_requested_context(sop_class or ds.SOPClassUID, ds.file_meta.TransferSyntaxUID)
    assoc = ae.associate("127.0.0.1", port, ae_title=PACS_AE)
    if not assoc.is_established:
        return assoc
    try:
        return [int(assoc.send_c_store(ds).Status) for ds in datasets]
    finally:
        assoc.release()


def jobs_of_series(client: httpx.Client, series_uid: str) -> list[dict[str, Any]]:
    items = client.get("/v1/jobs", params={"limit": 200}).json()["items"]
    return [j for j in items if (j.get("source") or {}).get("series_uid") == series_uid]


def wait_delivered(pacs: Pacs, client: httpx.Client, job_id: str, timeout: float = 300) -> dict[str, Any]:
    def done(job: dict[str, Any]) -> bool:
        return job["state"] in ("failed", "cancelled") or (job.get("delivery") or {}).get("state") in (
            "delivered",
            "failed",
        )

    job = wait_for_job(client, job_id, stack=pacs.stack, timeout=timeout, until=done)
    assert job["state"] == "succeeded", json.dumps(job)
    assert job["delivery"]["state"] == "delivered", json.dumps(job)
    return job


def download(job: dict[str, Any], name: str) -> bytes:
    (out,) = [o for o in job["outputs"] if o["name"] == name]
    resp = httpx.get(out["url"], timeout=60)
    assert resp.status_code == 200, resp.text
    return resp.content


def check_model_in_orthanc(pacs: Pacs, job: dict[str, Any], study: str) -> pydicom.Dataset:
    """The Encapsulated STL is in Orthanc in the source's study and decodes to the job's model.stl."""
    found = [pydicom.dcmread(io.BytesIO(b)) for b in pacs.orthanc.instances_of(study, "M3D")]
    mine = [ds for ds in found if ds.SeriesInstanceUID == job["delivery"]["series_instance_uid"]]
    assert len(mine) == 1, [ds.SeriesInstanceUID for ds in found]
    ds = mine[0]
    assert ds.SOPClassUID == ENCAPSULATED_STL_STORAGE and ds.Modality == "M3D"
    assert ds.StudyInstanceUID == study
    assert ds.MeasurementUnitsCodeSequence[0].CodeValue == "mm"
    got_v, got_f = from_stl(stl_of(ds.to_bytes() if hasattr(ds, "to_bytes") else _bytes(ds)))
    want_v, want_f = from_stl(download(job, "model.stl"))
    np.testing.assert_allclose(got_v, want_v, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got_f, want_f)
    return ds


def _bytes(ds: pydicom.Dataset) -> bytes:
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=True)
    return buf.getvalue()


def assert_no_patient_data(pacs: Pacs, job: dict[str, Any], identity: dict[str, str]) -> None:
    texts = {name: download(job, name) for name in ("report.json", "phone.glb", "ar.glb")}
    texts["logs"] = pacs.logs_text().encode()
    texts["job"] = json.dumps(job).encode()
    for what, data in texts.items():
        for key, value in identity.items():
            if value:
                assert value.encode() not in data, f"{key} appears in {what}"


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
